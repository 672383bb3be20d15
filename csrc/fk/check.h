// The one input check of the FK ops (fk, fk_backward), called by the CPU (cpu.cpp) and the CUDA (cuda.cu)
// registrations alike: every failure names the argument, so a bad call never reaches a kernel.
#pragma once

#include <ATen/ATen.h>

#include <optional>
#include <vector>

#include "common/check.h"

namespace modi_ext {
namespace fk {

constexpr int64_t kCudaMaxJoints = 1024;  // the CUDA kernels pass the parent list by value (kernel parameters)

// A checked call: N samples (the flattened leading dims, batch x time) of J joints, and the parent list.
struct Call {
  int64_t N;
  int64_t J;
  std::vector<int64_t> parents;
};

// local_quats.shape[:-2] + (3,): the shape of root_positions and of its gradient.
inline std::vector<int64_t> root_shape_of(const at::Tensor& local_quats) {
  std::vector<int64_t> s(local_quats.sizes().begin(), local_quats.sizes().end());
  if (!s.empty()) s.pop_back();
  if (!s.empty()) s.back() = 3;
  return s;
}

// local_quats.shape[:-1] + (3,): the shape of the positions and of their gradient.
inline std::vector<int64_t> positions_shape_of(const at::Tensor& local_quats) {
  std::vector<int64_t> s(local_quats.sizes().begin(), local_quats.sizes().end());
  if (!s.empty()) s.back() = 3;
  return s;
}

// A tensor that goes with local_quats: defined, its device, its dtype, contiguous.
inline void check_like_quats(const at::Tensor& t, const char* name, const at::Tensor& local_quats) {
  TORCH_CHECK(t.defined(), "modi_ext::fk: ", name, " is undefined");
  TORCH_CHECK(t.device() == local_quats.device(), "modi_ext::fk: ", name, " is on ", t.device(),
              " but local_quats is on ", local_quats.device());
  TORCH_CHECK(t.scalar_type() == local_quats.scalar_type(), "modi_ext::fk: ", name, " has dtype ", t.scalar_type(),
              ", expected ", local_quats.scalar_type(), " (same as local_quats)");
  TORCH_CHECK(t.is_contiguous(), "modi_ext::fk: ", name, " must be contiguous");
}

// The parent list: one per joint, topologically sorted, the root first.
inline std::vector<int64_t> check_parents(at::IntArrayRef parents, int64_t J) {
  TORCH_CHECK(static_cast<int64_t>(parents.size()) == J, "modi_ext::fk: parents has ", parents.size(),
              " entries but local_quats has ", J, " joints (dim -2)");
  std::vector<int64_t> par(parents.begin(), parents.end());
  TORCH_CHECK(J >= 1 && par[0] == -1, "modi_ext::fk: parents[0] must be -1 (joint 0 is the root)");
  for (int64_t j = 1; j < J; ++j) {
    TORCH_CHECK(par[j] >= 0 && par[j] < j, "modi_ext::fk: parents[", j, "] = ", par[j],
                " is out of range; parents must be topologically sorted (0 <= parents[j] < j)");
  }
  return par;
}

// local_quats, offsets, the parent list and the shape of root_positions (the backward has no root tensor, only
// its shape).
inline Call check_inputs(const Backend& be, const at::Tensor& local_quats, const at::Tensor& offsets,
                         at::IntArrayRef parents, at::IntArrayRef root_sizes) {
  TORCH_CHECK(local_quats.defined() && local_quats.dim() >= 2 && local_quats.size(-1) == 4,
              "modi_ext::fk: local_quats must have shape (..., J, 4), got ",
              local_quats.defined() ? local_quats.sizes() : at::IntArrayRef{});
  TORCH_CHECK(be.on_device(local_quats), "modi_ext::fk: local_quats must be a ", be.name, " tensor for the ", be.name,
              " kernel, got ", local_quats.device());
  TORCH_CHECK(takes_float(be, local_quats.scalar_type()), "modi_ext::fk: local_quats must be ", float_names(be),
              ", got ", local_quats.scalar_type());
  TORCH_CHECK(local_quats.is_contiguous(), "modi_ext::fk: local_quats must be contiguous");
  const int64_t J = local_quats.size(-2);
  TORCH_CHECK(J >= 1, "modi_ext::fk: local_quats has no joints");
  TORCH_CHECK(local_quats.numel() > 0, "modi_ext::fk: local_quats is empty (shape ", local_quats.sizes(), ")");
  check_like_quats(offsets, "offsets", local_quats);
  TORCH_CHECK(offsets.dim() == 2 && offsets.size(0) == J && offsets.size(1) == 3,
              "modi_ext::fk: offsets must have shape (J, 3) = (", J, ", 3), got ", offsets.sizes());
  const auto lead = local_quats.sizes().slice(0, local_quats.dim() - 2);
  TORCH_CHECK(root_sizes.size() == lead.size() + 1 && root_sizes.back() == 3 &&
                  root_sizes.slice(0, root_sizes.size() - 1) == lead,
              "modi_ext::fk: root_positions must have shape local_quats.shape[:-2] + (3,), got ", root_sizes,
              " for local_quats ", local_quats.sizes());
  const int64_t N = local_quats.numel() / (J * 4);
  if (be.cuda) {
    TORCH_CHECK(J <= kCudaMaxJoints, "modi_ext::fk: the CUDA kernel supports at most ", kCudaMaxJoints,
                " joints, got ", J);
    TORCH_CHECK((N + 31) / 32 < (int64_t(1) << 31), "modi_ext::fk: too many samples for the CUDA kernel: ", N);
  }
  return {N, J, check_parents(parents, J)};
}

// fk: the inputs above and the root tensor itself.
inline Call check_forward_inputs(const Backend& be, const at::Tensor& local_quats, const at::Tensor& offsets,
                                 at::IntArrayRef parents, const at::Tensor& root_positions) {
  TORCH_CHECK(root_positions.defined(), "modi_ext::fk: root_positions is undefined");
  Call c = check_inputs(be, local_quats, offsets, parents, root_positions.sizes());
  check_like_quats(root_positions, "root_positions", local_quats);
  return c;
}

// fk_backward: the forward's inputs (no root), the forward's rotations and the gradients of its two outputs (the
// rotations' may be absent).
inline Call check_backward_inputs(const Backend& be, const at::Tensor& grad_positions,
                                  const std::optional<at::Tensor>& grad_global_quats, const at::Tensor& local_quats,
                                  const at::Tensor& global_quats, const at::Tensor& offsets,
                                  at::IntArrayRef parents) {
  Call c = check_inputs(be, local_quats, offsets, parents, root_shape_of(local_quats));
  TORCH_CHECK(global_quats.defined() && global_quats.sizes() == local_quats.sizes(),
              "modi_ext::fk_backward: global_quats must have the shape of local_quats");
  check_like_quats(global_quats, "global_quats", local_quats);
  const std::vector<int64_t> pos_shape = positions_shape_of(local_quats);
  TORCH_CHECK(grad_positions.defined() && grad_positions.sizes() == at::IntArrayRef(pos_shape),
              "modi_ext::fk_backward: grad_positions must have shape ", at::IntArrayRef(pos_shape), ", got ",
              grad_positions.defined() ? grad_positions.sizes() : at::IntArrayRef{});
  TORCH_CHECK(grad_positions.device() == local_quats.device() &&
                  grad_positions.scalar_type() == local_quats.scalar_type(),
              "modi_ext::fk_backward: grad_positions must be a ", local_quats.scalar_type(), " tensor on ",
              local_quats.device());
  if (grad_global_quats.has_value() && grad_global_quats->defined()) {
    TORCH_CHECK(grad_global_quats->device() == local_quats.device() &&
                    grad_global_quats->scalar_type() == local_quats.scalar_type() &&
                    grad_global_quats->sizes() == local_quats.sizes(),
                "modi_ext::fk_backward: grad_global_quats must be a ", local_quats.scalar_type(), " tensor on ",
                local_quats.device(), " of shape ", local_quats.sizes());
  }
  return c;
}

}  // namespace fk
}  // namespace modi_ext
