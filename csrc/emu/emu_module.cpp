// Python module of the test-only emulated CUDA kernels (modi_ext._C_emu): the ops of csrc/<op>/cuda.cu under their
// own namespace (torch.ops.modi_ext_emu.*, CPU dispatch key only) plus the emulator's controls.
#include <Python.h>
#include <torch/library.h>

#include <cstring>
#include <utility>

#include "emu/emu_control.h"
#include "common/ops.h"
#include "skeletal/launch_plan.h"

#define MODI_EMU_TORCH_LIBRARY(ns, m) TORCH_LIBRARY(ns, m)
MODI_EMU_TORCH_LIBRARY(MODI_EMU_LIB, m) {
  modi_ext::define_skeletal_ops(m);
  modi_ext::define_fk_ops(m);
  modi_ext::define_demod_ops(m);
  m.def("emu_selftest(str name, int threads) -> Tensor");  // emu_selftest.cpp: the emulator's own checks
}

#define MODI_EMU_STR2(x) #x
#define MODI_EMU_STR(x) MODI_EMU_STR2(x)

namespace {

PyObject* py_set_seed(PyObject*, PyObject* arg) {
  const unsigned long long v = PyLong_AsUnsignedLongLong(arg);
  if (PyErr_Occurred()) return nullptr;
  modi_emu::set_seed(v);
  Py_RETURN_NONE;
}

PyObject* py_get_seed(PyObject*, PyObject*) { return PyLong_FromUnsignedLongLong(modi_emu::get_seed()); }

PyObject* py_set_sm_count(PyObject*, PyObject* arg) {
  const long v = PyLong_AsLong(arg);
  if (PyErr_Occurred()) return nullptr;
  if (v < 1 || v > 100000) {
    PyErr_SetString(PyExc_ValueError, "sm count must be in [1, 100000]");
    return nullptr;
  }
  modi_emu::set_sm_count(static_cast<int>(v));
  Py_RETURN_NONE;
}

PyObject* py_launch_counts(PyObject*, PyObject*) {
  PyObject* d = PyDict_New();
  if (!d) return nullptr;
  for (const auto& [name, n] : modi_emu::launch_counts()) {
    PyObject* v = PyLong_FromLongLong(n);
    if (!v || PyDict_SetItemString(d, name.c_str(), v) < 0) {
      Py_XDECREF(v);
      Py_DECREF(d);
      return nullptr;
    }
    Py_DECREF(v);
  }
  return d;
}

// Test-only run-time defects (cuda_emu.h): "" (none), "drop_sync", "off_by_one", "global_oob", "wrong_scale",
// "split_edge", "wrong_slope", "mma_fragment_offset", "mma_tile_edge", "mma_wgrad_fragment_offset",
// "mma_wgrad_tile_edge".
const std::pair<const char*, int> kDefects[] = {{"", 0},
                                                {"drop_sync", MODI_EMU_INJECT_DROP_SYNC_ID},
                                                {"off_by_one", MODI_EMU_INJECT_OFF_BY_ONE_ID},
                                                {"global_oob", MODI_EMU_INJECT_GLOBAL_OOB_ID},
                                                {"wrong_scale", MODI_EMU_INJECT_WRONG_SCALE_ID},
                                                {"split_edge", MODI_EMU_INJECT_SPLIT_EDGE_ID},
                                                {"wrong_slope", MODI_EMU_INJECT_WRONG_SLOPE_ID},
                                                {"mma_fragment_offset", MODI_EMU_INJECT_MMA_FRAGMENT_OFFSET_ID},
                                                {"mma_tile_edge", MODI_EMU_INJECT_MMA_TILE_EDGE_ID},
                                                {"mma_wgrad_fragment_offset",
                                                 MODI_EMU_INJECT_MMA_WGRAD_FRAGMENT_OFFSET_ID},
                                                {"mma_wgrad_tile_edge", MODI_EMU_INJECT_MMA_WGRAD_TILE_EDGE_ID}};

PyObject* py_set_injected_defect(PyObject*, PyObject* arg) {
  const char* name = PyUnicode_AsUTF8(arg);
  if (!name) return nullptr;
  for (const auto& [n, id] : kDefects) {
    if (std::strcmp(n, name) == 0) {
      modi_emu::set_injected_defect(id);
      Py_RETURN_NONE;
    }
  }
  PyErr_Format(PyExc_ValueError,
               "unknown defect '%s' (expected '', 'drop_sync', 'off_by_one', 'global_oob', 'wrong_scale', 'split_edge', "
               "'wrong_slope', 'mma_fragment_offset', 'mma_tile_edge', 'mma_wgrad_fragment_offset' or "
               "'mma_wgrad_tile_edge')", name);
  return nullptr;
}

PyObject* py_injected_defect(PyObject*, PyObject*) {
  const int id = modi_emu::injected_defect();
  for (const auto& [n, i] : kDefects)
    if (i == id) return PyUnicode_FromString(n);
  return PyUnicode_FromString("?");
}

PyObject* py_registered_kernels(PyObject*, PyObject*) {
  PyObject* l = PyList_New(0);
  if (!l) return nullptr;
  for (const auto& name : modi_emu::registered_kernels()) {
    PyObject* v = PyUnicode_FromString(name.c_str());
    if (!v || PyList_Append(l, v) < 0) {
      Py_XDECREF(v);
      Py_DECREF(l);
      return nullptr;
    }
    Py_DECREF(v);
  }
  return l;
}

// {name: value} of int64 pairs; null (Python error set) on failure.
PyObject* int_dict(std::initializer_list<std::pair<const char*, long long>> items) {
  PyObject* d = PyDict_New();
  if (!d) return nullptr;
  for (const auto& [k, n] : items) {
    PyObject* v = PyLong_FromLongLong(n);
    if (!v || PyDict_SetItemString(d, k, v) < 0) {
      Py_XDECREF(v);
      Py_DECREF(d);
      return nullptr;
    }
    Py_DECREF(v);
  }
  return d;
}

PyObject* py_wgrad_plan(PyObject*, PyObject* args) {
  long long N, rows, nnz, cu, M;
  int sms;
  if (!PyArg_ParseTuple(args, "LLLLLi", &N, &rows, &nnz, &cu, &M, &sms)) return nullptr;
  const auto p = modi_ext::skeletal::plan::wgrad_plan(N, rows, nnz, cu, M, sms);
  return int_dict({{"ktiles", p.ktiles}, {"mtiles", p.mtiles}, {"splits", p.splits}, {"n_chunk", p.n_chunk},
                   {"ctas", p.ctas()}});
}

PyObject* py_gemm_plan(PyObject*, PyObject* args) {
  long long N, M, ents, nnz, cu;
  int sms;
  if (!PyArg_ParseTuple(args, "LLLLLi", &N, &M, &ents, &nnz, &cu, &sms)) return nullptr;
  const auto p = modi_ext::skeletal::plan::gemm_plan(N, M, ents, nnz, cu, sms);
  return int_dict({{"ntiles", p.ntiles}, {"mtiles", p.mtiles}, {"ents", p.ents}, {"splits", p.splits},
                   {"ctas", p.ctas()}});
}

PyObject* py_last_grids(PyObject*, PyObject*) {
  PyObject* d = PyDict_New();
  if (!d) return nullptr;
  for (const auto& [name, g] : modi_emu::last_grids()) {
    PyObject* v = Py_BuildValue("(kkk)", (unsigned long)g[0], (unsigned long)g[1], (unsigned long)g[2]);
    if (!v || PyDict_SetItemString(d, name.c_str(), v) < 0) {
      Py_XDECREF(v);
      Py_DECREF(d);
      return nullptr;
    }
    Py_DECREF(v);
  }
  return d;
}

PyObject* py_reset_launch_counts(PyObject*, PyObject*) {
  modi_emu::reset_launch_counts();
  Py_RETURN_NONE;
}

PyMethodDef kMethods[] = {
    {"set_schedule_seed", py_set_seed, METH_O, "Thread/block order: 0 = index order, else a seeded permutation."},
    {"schedule_seed", py_get_seed, METH_NOARGS, "The current schedule seed."},
    {"set_sm_count", py_set_sm_count, METH_O, "Multiprocessor count the host code sees (cuda::sm_count; default 108)."},
    {"launch_counts", py_launch_counts, METH_NOARGS, "{kernel instantiation: launches} since the last reset."},
    {"reset_launch_counts", py_reset_launch_counts, METH_NOARGS, "Clear the launch counters (and the last grids)."},
    {"last_grids", py_last_grids, METH_NOARGS, "{kernel instantiation: (x, y, z)} grid of its latest launch."},
    {"wgrad_plan", py_wgrad_plan, METH_VARARGS,
     "wgrad_plan(N, rows, nnz, C*U, M, sms): the weight gradient's launch (skeletal/launch_plan.h)."},
    {"gemm_plan", py_gemm_plan, METH_VARARGS,
     "gemm_plan(N, M, ents, nnz, C*U, sms): a row / transposed GEMM's launch (skeletal/launch_plan.h)."},
    {"set_injected_defect", py_set_injected_defect, METH_O,
     "Test-only: turn on a defect ('drop_sync', 'off_by_one', 'global_oob', 'wrong_scale', 'split_edge', "
     "'wrong_slope', 'mma_fragment_offset', 'mma_tile_edge', 'mma_wgrad_fragment_offset', 'mma_wgrad_tile_edge') "
     "or off ('')."},
    {"injected_defect", py_injected_defect, METH_NOARGS, "The run-time defect in force ('' = none)."},
    {"registered_kernels", py_registered_kernels, METH_NOARGS,
     "Sorted names of every kernel instantiation the module can launch (registered at load time)."},
    {nullptr, nullptr, 0, nullptr}};

}  // namespace

#define MODI_EMU_CAT2(a, b) a##b
#define MODI_EMU_CAT(a, b) MODI_EMU_CAT2(a, b)

// Built with -fvisibility=hidden: PyMODINIT_FUNC keeps the init function exported.
PyMODINIT_FUNC MODI_EMU_CAT(PyInit_, TORCH_EXTENSION_NAME)(void) {
  static PyModuleDef def = {PyModuleDef_HEAD_INIT, MODI_EMU_STR(TORCH_EXTENSION_NAME),
                            "Test-only: the CUDA kernels run by the CPU emulator", -1, kMethods};
  PyObject* m = PyModule_Create(&def);
  if (!m) return nullptr;
  if (PyModule_AddStringConstant(m, "LIBRARY", MODI_EMU_STR(MODI_EMU_LIB)) < 0) return nullptr;
  return m;
}
