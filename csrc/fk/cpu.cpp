// CPU kernels of modi_ext::fk. One sample (b, t) is a sequential walk down the joint tree; samples
// are independent, so the flattened batch x time range is cut into fixed blocks that threads claim dynamically
// (common/tasks.h: a thread slowed by another process takes fewer blocks instead of holding up the call).
// The backward walks the tree leaf-to-root, accumulating each joint's position/rotation gradient into
// its parent, so every joint is visited once per sample in each direction (O(J), no J x J Jacobian).
#include <ATen/Dispatch.h>
#include <ATen/OpMathType.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <vector>

#include "common/tasks.h"
#include "fk/check.h"
#include "fk/fk.h"
#include "fk/quat.h"

namespace modi_ext {
namespace {

using fk::qmul;
using fk::qrot;

// out = a (x) conj(b).
template <typename T>
inline void qmul_conj_b(const T* a, const T* b, T* out) {
  const T bc[4] = {b[0], -b[1], -b[2], -b[3]};
  qmul(a, bc, out);
}

// out = conj(a) (x) b.
template <typename T>
inline void qmul_conj_a(const T* a, const T* b, T* out) {
  const T ac[4] = {a[0], -a[1], -a[2], -a[3]};
  qmul(ac, b, out);
}

// Samples per task: ~8k joint visits (tens of microseconds), so small calls stay on the calling thread.
int64_t grain_for(int64_t J) { return std::max<int64_t>(1, 8192 / std::max<int64_t>(J, 1)); }

// Run body(begin, end) over [0, N) in blocks of `block` samples, claimed dynamically.
template <typename F>
void for_blocks(int64_t N, int64_t block, const F& body) {
  const int64_t n_blocks = (N + block - 1) / block;
  auto task = [&](int64_t b, int) { body(b * block, std::min(N, (b + 1) * block)); };
  cpu_tasks::run_phases({cpu_tasks::phase(n_blocks, task)}, n_blocks > 1);
}

// ---- forward ----

template <typename T>
void fk_forward_kernel(const T* lq, const T* off, const int64_t* par, const T* root, T* pos, T* gq, int64_t N,
                       int64_t J) {
  for_blocks(N, grain_for(J), [&](int64_t begin, int64_t end) {
    for (int64_t n = begin; n < end; ++n) {
      const T* q = lq + n * J * 4;
      T* Q = gq + n * J * 4;
      T* P = pos + n * J * 3;
      Q[0] = q[0]; Q[1] = q[1]; Q[2] = q[2]; Q[3] = q[3];
      P[0] = root[n * 3]; P[1] = root[n * 3 + 1]; P[2] = root[n * 3 + 2];
      for (int64_t j = 1; j < J; ++j) {
        const int64_t p = par[j];
        const T* Qp = Q + p * 4;
        const T* Pp = P + p * 3;
        qmul(Qp, q + j * 4, Q + j * 4);
        T r[3];
        qrot(Qp[0], Qp[1], Qp[2], Qp[3], off + j * 3, r);
        P[j * 3] = Pp[0] + r[0];
        P[j * 3 + 1] = Pp[1] + r[1];
        P[j * 3 + 2] = Pp[2] + r[2];
      }
    }
  });
}

// ---- backward ----
// For P[j] = P[p] + A(Q[p], o), A = o + 2w (u x o) + 2u (u.o) - 2o (u.u), the vector-Jacobian products are
//   dL/dw += 2 g.(u x o)
//   dL/du += 2w (o x g) + 2 (u.o) g + 2 (g.u) o - 4 (g.o) u
//   dL/do += A((w, -u), g)                      (the transpose of the linear map o -> A(Q, o))
// and for Q[j] = Q[p] (x) q[j]:  dL/dq[j] = conj(Q[p]) (x) G,  dL/dQ[p] += G (x) conj(q[j]).

template <typename T>
void fk_backward_kernel(const T* gpos, const T* ggq, const T* lq, const T* gq, const T* off, const int64_t* par,
                        T* glq, T* groot, T* goff, int64_t N, int64_t J) {
  using acc_t = at::opmath_type<T>;
  // Fixed block count, independent of the thread count, so the offsets reduction is deterministic.
  const int64_t grain = grain_for(J);
  const int64_t n_blocks = goff ? std::max<int64_t>(1, std::min<int64_t>(64, (N + grain - 1) / grain)) : 1;
  std::vector<acc_t> goff_blocks(goff ? n_blocks * J * 3 : 0, acc_t(0));

  auto run = [&](int64_t begin, int64_t end, acc_t* goff_acc) {
    std::vector<T> buf(static_cast<size_t>(J) * 7);
    T* gP = buf.data();       // (J, 3) accumulated position gradient
    T* gQ = buf.data() + J * 3;  // (J, 4) accumulated global-rotation gradient
    for (int64_t n = begin; n < end; ++n) {
      std::copy(gpos + n * J * 3, gpos + (n + 1) * J * 3, gP);
      if (ggq) {
        std::copy(ggq + n * J * 4, ggq + (n + 1) * J * 4, gQ);
      } else {
        std::fill(gQ, gQ + J * 4, T(0));
      }
      const T* q = lq + n * J * 4;
      const T* Q = gq + n * J * 4;
      T* gq_out = glq + n * J * 4;
      for (int64_t j = J - 1; j >= 1; --j) {
        const int64_t p = par[j];
        const T* Qp = Q + p * 4;
        const T w = Qp[0], ux = Qp[1], uy = Qp[2], uz = Qp[3];
        const T* o = off + j * 3;
        const T gx = gP[j * 3], gy = gP[j * 3 + 1], gz = gP[j * 3 + 2];
        gP[p * 3] += gx;
        gP[p * 3 + 1] += gy;
        gP[p * 3 + 2] += gz;
        // position term -> gradient of Q[p]
        T* gQp = gQ + p * 4;
        T pg[4];
        fk::position_grad(w, ux, uy, uz, o, gx, gy, gz, pg);
        gQp[0] += pg[0];
        gQp[1] += pg[1];
        gQp[2] += pg[2];
        gQp[3] += pg[3];
        if (goff_acc) {
          const T g[3] = {gx, gy, gz};
          T r[3];
          qrot(w, -ux, -uy, -uz, g, r);
          goff_acc[j * 3] += r[0];
          goff_acc[j * 3 + 1] += r[1];
          goff_acc[j * 3 + 2] += r[2];
        }
        // rotation term
        const T* G = gQ + j * 4;
        qmul_conj_a(Qp, G, gq_out + j * 4);
        T t[4];
        qmul_conj_b(G, q + j * 4, t);
        gQp[0] += t[0];
        gQp[1] += t[1];
        gQp[2] += t[2];
        gQp[3] += t[3];
      }
      gq_out[0] = gQ[0]; gq_out[1] = gQ[1]; gq_out[2] = gQ[2]; gq_out[3] = gQ[3];
      groot[n * 3] = gP[0]; groot[n * 3 + 1] = gP[1]; groot[n * 3 + 2] = gP[2];
    }
  };

  if (!goff) {
    for_blocks(N, grain, [&](int64_t b, int64_t e) { run(b, e, nullptr); });
    return;
  }
  const int64_t per_block = (N + n_blocks - 1) / n_blocks;
  for_blocks(N, per_block, [&](int64_t begin, int64_t end) {
    run(begin, end, goff_blocks.data() + (begin / per_block) * J * 3);
  });
  for (int64_t i = 0; i < J * 3; ++i) {
    acc_t s = 0;
    for (int64_t b = 0; b < n_blocks; ++b) s += goff_blocks[b * J * 3 + i];
    goff[i] = static_cast<T>(s);
  }
}

}  // namespace

std::tuple<at::Tensor, at::Tensor> fk_cpu(const at::Tensor& local_quats, const at::Tensor& offsets,
                                          at::IntArrayRef parents, const at::Tensor& root_positions) {
  const fk::Call d = fk::check_forward_inputs(kCpuBackend, local_quats, offsets, parents, root_positions);
  const std::vector<int64_t>& par = d.parents;
  at::Tensor positions = at::empty(fk::positions_shape_of(local_quats), local_quats.options());
  at::Tensor global_quats = at::empty_like(local_quats, at::MemoryFormat::Contiguous);
  AT_DISPATCH_FLOATING_TYPES(local_quats.scalar_type(), "modi_ext::fk", [&] {
    fk_forward_kernel<scalar_t>(local_quats.data_ptr<scalar_t>(), offsets.data_ptr<scalar_t>(), par.data(),
                                root_positions.data_ptr<scalar_t>(), positions.data_ptr<scalar_t>(),
                                global_quats.data_ptr<scalar_t>(), d.N, d.J);
  });
  return {positions, global_quats};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> fk_backward_cpu(
    const at::Tensor& grad_positions, const std::optional<at::Tensor>& grad_global_quats,
    const at::Tensor& local_quats, const at::Tensor& global_quats, const at::Tensor& offsets,
    at::IntArrayRef parents, bool offsets_grad) {
  const fk::Call d = fk::check_backward_inputs(kCpuBackend, grad_positions, grad_global_quats, local_quats,
                                               global_quats, offsets, parents);
  const std::vector<int64_t>& par = d.parents;
  const auto dtype = local_quats.scalar_type();
  const at::Tensor gpos = grad_positions.contiguous();
  at::Tensor ggq;
  if (grad_global_quats.has_value() && grad_global_quats->defined()) ggq = grad_global_quats->contiguous();
  at::Tensor grad_local = at::empty_like(local_quats, at::MemoryFormat::Contiguous);
  at::Tensor grad_root = at::empty(fk::root_shape_of(local_quats), local_quats.options());
  at::Tensor grad_off = at::zeros({d.J, 3}, local_quats.options());
  AT_DISPATCH_FLOATING_TYPES(dtype, "modi_ext::fk_backward", [&] {
    fk_backward_kernel<scalar_t>(gpos.data_ptr<scalar_t>(), ggq.defined() ? ggq.data_ptr<scalar_t>() : nullptr,
                                 local_quats.data_ptr<scalar_t>(), global_quats.data_ptr<scalar_t>(),
                                 offsets.data_ptr<scalar_t>(), par.data(), grad_local.data_ptr<scalar_t>(),
                                 grad_root.data_ptr<scalar_t>(),
                                 offsets_grad ? grad_off.data_ptr<scalar_t>() : nullptr, d.N, d.J);
  });
  return {grad_local, grad_root, grad_off};
}

TORCH_LIBRARY_IMPL(modi_ext, CPU, m) {
  m.impl("fk", &fk_cpu);
  m.impl("fk_backward", &fk_backward_cpu);
}

}  // namespace modi_ext
