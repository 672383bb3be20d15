// CUDA kernels of modi_ext::fk (semantics: fk/fk.h, mirrored from fk/cpu.cpp).
//
// One thread per sample (flattened batch x time) walks the joints root to leaf (forward) or leaf to root
// (backward).  The parent list travels by value in the kernel parameters (no host-to-device copy, so the op can be
// captured in a CUDA graph) and is staged in shared memory with the offsets.  Each thread keeps the running state of
// its walk (forward: global rotation + position per joint; backward: accumulated rotation + position gradient per
// joint), 7 values per joint in fp32 (fp64 for double):
//   * in shared memory, laid out [joint][component][thread] (conflict-free), when it fits in 48 KB for a block of
//     128, 64 or 32 threads;
//   * else in a global workspace of N * J * 7 accumulator values (bounded by the size of the outputs x 7/3).
// The offsets gradient is reduced without atomics: per warp (shuffles) into a workspace of
// J * 3 * (number of warps) accumulator values, then one block per offset component sums the warps.
#include <torch/library.h>

#include <ATen/ATen.h>

#include <vector>

#include "common/cuda_common.cuh"
#include "fk/check.h"
#include "fk/fk.h"
#include "fk/quat.h"

namespace modi_ext {
namespace {

using namespace cuda;  // acc_t, ld, st, ceil_div, warp_sum, block_sum, ...
using fk::qmul;
using fk::qrot;

constexpr int kMaxJoints = fk::kCudaMaxJoints;
constexpr size_t kSmemBudget = 48 * 1024;

struct FkParents {
  int J;
  int16_t p[kMaxJoints];
};

// Dynamic shared memory: [state (kSmem only): J * 7 * threads][offsets: J * 3] (accumulator type), [parents: J].
template <typename A>
struct FkSmem {
  A* state;
  A* off;
  int16_t* par;
};

template <typename T, bool kSmem>
__device__ __forceinline__ FkSmem<acc_t<T>> stage_topology(const T* off, const FkParents& par) {
  using A = acc_t<T>;
  MODI_DYNAMIC_SHARED(unsigned char, fk_smem_raw);
  const int J = par.J, nt = blockDim.x;
  FkSmem<A> s;
  s.state = reinterpret_cast<A*>(fk_smem_raw);
  s.off = s.state + (kSmem ? int64_t(J) * 7 * nt : 0);
  s.par = reinterpret_cast<int16_t*>(s.off + 3 * J);
  for (int j = threadIdx.x; j < J; j += nt) s.par[j] = par.p[j];
  for (int j = threadIdx.x; j < 3 * J; j += nt) s.off[j] = ld(off + j);
  __syncthreads();
  return s;
}

// A thread's walk state: joint j, component c (rotation c = 0..3, position c = 4..6) at S[j * sj + c * sc], in
// shared memory laid out [joint][component][thread] (kSmem), else in the thread's slice of the global workspace.
template <typename A>
struct WalkState {
  A* S;
  int64_t sj, sc;
};

template <bool kSmem, typename A>
__device__ __forceinline__ WalkState<A> walk_state(const FkSmem<A>& sm, A* ws, int64_t n, int J) {
  if constexpr (kSmem) {
    const int nt = blockDim.x;
    return {sm.state + threadIdx.x, int64_t(7) * nt, nt};
  } else {
    return {ws + n * J * 7, 7, 1};
  }
}

// ---- forward ----
template <typename T, bool kSmem>
__global__ void fk_forward_kernel(const T* __restrict__ lq, const T* __restrict__ off, const T* __restrict__ root,
                                  T* __restrict__ pos, T* __restrict__ gq, acc_t<T>* __restrict__ ws, int64_t N,
                                  const FkParents par) {
  using A = acc_t<T>;
  const FkSmem<A> sm = stage_topology<T, kSmem>(off, par);
  const int J = par.J, nt = blockDim.x;
  const int64_t n = int64_t(blockIdx.x) * nt + threadIdx.x;
  if (n >= N) return;  // no barrier below
  const auto [S, sj, sc] = walk_state<kSmem>(sm, ws, n, J);
  const T* q = lq + n * J * 4;
  T* Qo = gq + n * J * 4;
  T* Po = pos + n * J * 3;
#pragma unroll
  for (int c = 0; c < 4; ++c) {
    const A v = ld(q + c);
    S[c * sc] = v;
    st(Qo + c, v);
  }
#pragma unroll
  for (int c = 0; c < 3; ++c) {
    const A v = ld(root + n * 3 + c);
    S[(4 + c) * sc] = v;
    st(Po + c, v);
  }
  A qn[4] = {A(0), A(0), A(0), A(0)};
  if (J > 1) {
#pragma unroll
    for (int c = 0; c < 4; ++c) qn[c] = ld(q + 4 + c);
  }
  for (int j = 1; j < J; ++j) {
    A qj[4];
#pragma unroll
    for (int c = 0; c < 4; ++c) qj[c] = qn[c];
    if (j + 1 < J) {  // prefetch the next local rotation: it does not depend on the walk
#pragma unroll
      for (int c = 0; c < 4; ++c) qn[c] = ld(q + (j + 1) * 4 + c);
    }
    const int p = sm.par[j];
    const A* Sp = S + p * sj;
    A Qp[4], Pp[3];
#pragma unroll
    for (int c = 0; c < 4; ++c) Qp[c] = Sp[c * sc];
#pragma unroll
    for (int c = 0; c < 3; ++c) Pp[c] = Sp[(4 + c) * sc];
    A Q[4], r[3];
    qmul(Qp, qj, Q);
    qrot(Qp[0], Qp[1], Qp[2], Qp[3], sm.off + 3 * j, r);
    A* Sj = S + j * sj;
#pragma unroll
    for (int c = 0; c < 4; ++c) {
      Sj[c * sc] = Q[c];
      st(Qo + j * 4 + c, Q[c]);
    }
#pragma unroll
    for (int c = 0; c < 3; ++c) {
      const A v = Pp[c] + r[c];
      Sj[(4 + c) * sc] = v;
      st(Po + j * 3 + c, v);
    }
  }
}

// ---- backward ----
// For P[j] = P[p] + A(Q[p], o), A = o + 2w (u x o) + 2u (u.o) - 2o (u.u):
//   dL/dw += 2 g.(u x o);   dL/du += 2w (o x g) + 2 (u.o) g + 2 (g.u) o - 4 (g.o) u;   dL/do += A((w, -u), g)
// and for Q[j] = Q[p] (x) q[j]:  dL/dq[j] = conj(Q[p]) (x) G,  dL/dQ[p] += G (x) conj(q[j]).
// State: accumulated rotation gradient (c = 0..3) and position gradient (c = 4..6) per joint.
template <typename T, bool kSmem>
__global__ void fk_backward_kernel(const T* __restrict__ gpos, const T* __restrict__ ggq, const T* __restrict__ lq,
                                   const T* __restrict__ gq, const T* __restrict__ off, T* __restrict__ glq,
                                   T* __restrict__ groot, acc_t<T>* __restrict__ goff_part, int64_t n_warps,
                                   acc_t<T>* __restrict__ ws, int64_t N, const FkParents par) {
  using A = acc_t<T>;
  const FkSmem<A> sm = stage_topology<T, kSmem>(off, par);
  const int J = par.J, nt = blockDim.x;
  const int64_t gt = int64_t(blockIdx.x) * nt + threadIdx.x;
  const bool active = gt < N;  // inactive lanes stay for the warp shuffles of the offsets gradient
  const int64_t n = active ? gt : 0;
  const int64_t warp = gt >> 5;
  const int lane = threadIdx.x & 31;
  const auto [S, sj, sc] = walk_state<kSmem>(sm, ws, n, J);
  if (active) {
    for (int j = 0; j < J; ++j) {
      A* Sj = S + j * sj;
#pragma unroll
      for (int c = 0; c < 4; ++c) Sj[c * sc] = ggq ? ld(ggq + (n * J + j) * 4 + c) : A(0);
#pragma unroll
      for (int c = 0; c < 3; ++c) Sj[(4 + c) * sc] = ld(gpos + (n * J + j) * 3 + c);
    }
  }
  for (int j = J - 1; j >= 1; --j) {
    A r[3] = {A(0), A(0), A(0)};
    if (active) {
      const int p = sm.par[j];
      const T* Qg = gq + (n * J + p) * 4;
      const A w = ld(Qg), ux = ld(Qg + 1), uy = ld(Qg + 2), uz = ld(Qg + 3);
      const A* o = sm.off + 3 * j;
      A* Sj = S + j * sj;
      A* Sp = S + p * sj;
      const A gx = Sj[4 * sc], gy = Sj[5 * sc], gz = Sj[6 * sc];
      Sp[4 * sc] += gx;
      Sp[5 * sc] += gy;
      Sp[6 * sc] += gz;
      // position term -> gradient of Q[p]
      A gQp[4];
      fk::position_grad(w, ux, uy, uz, o, gx, gy, gz, gQp);
      if (goff_part) {
        const A g[3] = {gx, gy, gz};
        qrot(w, -ux, -uy, -uz, g, r);
      }
      // rotation term
      const A G[4] = {Sj[0], Sj[sc], Sj[2 * sc], Sj[3 * sc]};
      const T* qj = lq + (n * J + j) * 4;
      const A qc[4] = {ld(qj), -ld(qj + 1), -ld(qj + 2), -ld(qj + 3)};  // conj(q[j])
      const A Qc[4] = {w, -ux, -uy, -uz};                                // conj(Q[p])
      A out[4], t[4];
      qmul(Qc, G, out);
      qmul(G, qc, t);
      T* go = glq + (n * J + j) * 4;
#pragma unroll
      for (int c = 0; c < 4; ++c) {
        st(go + c, out[c]);
        Sp[c * sc] += gQp[c] + t[c];
      }
    }
    if (goff_part) {  // uniform branch: every lane of the warp takes part
#pragma unroll
      for (int c = 0; c < 3; ++c) {
        const A v = cuda::warp_sum(r[c]);
        if (lane == 0) goff_part[int64_t(3 * j + c) * n_warps + warp] = v;
      }
    }
  }
  if (goff_part && lane == 0) {
#pragma unroll
    for (int c = 0; c < 3; ++c) goff_part[int64_t(c) * n_warps + warp] = A(0);  // joint 0 has no offset term
  }
  if (active) {
#pragma unroll
    for (int c = 0; c < 4; ++c) st(glq + n * J * 4 + c, S[c * sc]);
#pragma unroll
    for (int c = 0; c < 3; ++c) st(groot + n * 3 + c, S[(4 + c) * sc]);
  }
}

// goff[e] = sum_w part[e * n_warps + w], one block per offset component e.
template <typename T>
__global__ void fk_offsets_reduce_kernel(const acc_t<T>* __restrict__ part, int64_t n_warps, T* __restrict__ goff) {
  using A = acc_t<T>;
  MODI_SHARED(A, scratch, [32]);
  const A* row = part + int64_t(blockIdx.x) * n_warps;
  A s = A(0);
  for (int64_t w = threadIdx.x; w < n_warps; w += blockDim.x) s += row[w];
  s = cuda::block_sum(s, scratch);
  if (threadIdx.x == 0) st(goff + blockIdx.x, s);
}

// ---- host side ----
// The checked parent list (fk::check_inputs), as the kernels receive it.
FkParents make_parents(const std::vector<int64_t>& parents) {
  FkParents par{};
  par.J = static_cast<int>(parents.size());
  for (size_t j = 0; j < parents.size(); ++j) par.p[j] = static_cast<int16_t>(parents[j]);
  return par;
}

struct Plan {
  int threads;
  bool smem_state;
  size_t smem_bytes;
};

// Largest block (128 / 64 / 32 threads) whose per-thread walk state fits in shared memory; else a global workspace.
Plan plan_launch(int64_t J, size_t acc_bytes) {
  const size_t fixed = static_cast<size_t>(J) * 3 * acc_bytes + static_cast<size_t>(J) * sizeof(int16_t);
  for (int t : {128, 64, 32}) {
    const size_t bytes = fixed + static_cast<size_t>(t) * J * 7 * acc_bytes;
    if (bytes <= kSmemBudget) return {t, true, bytes};
  }
  return {128, false, fixed};
}

std::tuple<at::Tensor, at::Tensor> fk_cuda(const at::Tensor& local_quats, const at::Tensor& offsets,
                                           at::IntArrayRef parents, const at::Tensor& root_positions) {
  const fk::Call d = fk::check_forward_inputs(kCudaBackend, local_quats, offsets, parents, root_positions);
  const FkParents par = make_parents(d.parents);
  const c10::cuda::CUDAGuard guard(local_quats.device());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(local_quats.device().index());
  at::Tensor positions = at::empty(fk::positions_shape_of(local_quats), local_quats.options());
  at::Tensor global_quats = at::empty_like(local_quats, at::MemoryFormat::Contiguous);
  const at::ScalarType acc_type = cuda::acc_scalar_type(local_quats.scalar_type());
  const Plan plan = plan_launch(d.J, c10::elementSize(acc_type));
  at::Tensor ws;
  if (!plan.smem_state) ws = at::empty({d.N * d.J * 7}, local_quats.options().dtype(acc_type));
  const unsigned blocks = static_cast<unsigned>(ceil_div(d.N, plan.threads));
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, local_quats.scalar_type(), "modi_ext::fk_cuda", [&] {
    using T = scalar_t;
    using A = acc_t<T>;
    A* wsp = ws.defined() ? ws.data_ptr<A>() : nullptr;
    if (plan.smem_state) {
      MODI_LAUNCH((fk_forward_kernel<T, true>), blocks, plan.threads, plan.smem_bytes, stream,
          local_quats.data_ptr<T>(), offsets.data_ptr<T>(), root_positions.data_ptr<T>(), positions.data_ptr<T>(),
          global_quats.data_ptr<T>(), wsp, d.N, par);
    } else {
      MODI_LAUNCH((fk_forward_kernel<T, false>), blocks, plan.threads, plan.smem_bytes, stream,
          local_quats.data_ptr<T>(), offsets.data_ptr<T>(), root_positions.data_ptr<T>(), positions.data_ptr<T>(),
          global_quats.data_ptr<T>(), wsp, d.N, par);
    }
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {positions, global_quats};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> fk_backward_cuda(
    const at::Tensor& grad_positions, const std::optional<at::Tensor>& grad_global_quats,
    const at::Tensor& local_quats, const at::Tensor& global_quats, const at::Tensor& offsets,
    at::IntArrayRef parents, bool offsets_grad) {
  const fk::Call d = fk::check_backward_inputs(kCudaBackend, grad_positions, grad_global_quats, local_quats,
                                               global_quats, offsets, parents);
  const FkParents par = make_parents(d.parents);
  const at::Tensor gpos = grad_positions.contiguous();
  at::Tensor ggq;
  if (grad_global_quats.has_value() && grad_global_quats->defined()) ggq = grad_global_quats->contiguous();
  const c10::cuda::CUDAGuard guard(local_quats.device());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(local_quats.device().index());
  at::Tensor grad_local = at::empty_like(local_quats, at::MemoryFormat::Contiguous);
  at::Tensor grad_root = at::empty(fk::root_shape_of(local_quats), local_quats.options());
  at::Tensor grad_off = offsets_grad ? at::empty({d.J, 3}, local_quats.options())
                                     : at::zeros({d.J, 3}, local_quats.options());
  const at::ScalarType acc_type = cuda::acc_scalar_type(local_quats.scalar_type());
  const Plan plan = plan_launch(d.J, c10::elementSize(acc_type));
  at::Tensor ws;
  if (!plan.smem_state) ws = at::empty({d.N * d.J * 7}, local_quats.options().dtype(acc_type));
  const int64_t blocks = ceil_div(d.N, plan.threads);
  const int64_t n_warps = blocks * plan.threads / 32;
  at::Tensor part;
  if (offsets_grad) part = at::empty({d.J * 3 * n_warps}, local_quats.options().dtype(acc_type));
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, local_quats.scalar_type(), "modi_ext::fk_backward_cuda",
                                  [&] {
    using T = scalar_t;
    using A = acc_t<T>;
    A* wsp = ws.defined() ? ws.data_ptr<A>() : nullptr;
    A* pp = part.defined() ? part.data_ptr<A>() : nullptr;
    const T* ggq_p = ggq.defined() ? ggq.data_ptr<T>() : nullptr;
    if (plan.smem_state) {
      MODI_LAUNCH((fk_backward_kernel<T, true>), static_cast<unsigned>(blocks), plan.threads, plan.smem_bytes,
                  stream,
          gpos.data_ptr<T>(), ggq_p, local_quats.data_ptr<T>(), global_quats.data_ptr<T>(), offsets.data_ptr<T>(),
          grad_local.data_ptr<T>(), grad_root.data_ptr<T>(), pp, n_warps, wsp, d.N, par);
    } else {
      MODI_LAUNCH((fk_backward_kernel<T, false>), static_cast<unsigned>(blocks), plan.threads, plan.smem_bytes,
                  stream,
          gpos.data_ptr<T>(), ggq_p, local_quats.data_ptr<T>(), global_quats.data_ptr<T>(), offsets.data_ptr<T>(),
          grad_local.data_ptr<T>(), grad_root.data_ptr<T>(), pp, n_warps, wsp, d.N, par);
    }
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    if (offsets_grad) {
      MODI_LAUNCH((fk_offsets_reduce_kernel<T>), static_cast<unsigned>(d.J * 3), 256, 0, stream, pp, n_warps,
                  grad_off.data_ptr<T>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    }
  });
  return {grad_local, grad_root, grad_off};
}

}  // namespace

TORCH_LIBRARY_IMPL(MODI_CUDA_LIB, MODI_CUDA_KEY, m) {
  m.impl("fk", &fk_cuda);
  m.impl("fk_backward", &fk_backward_cuda);
}

}  // namespace modi_ext
