#pragma once
// Batched forward kinematics (modi_ext::fk): local unit quaternions (w, x, y, z) per joint,
// rest offsets, a topologically sorted parent list and the root translation -> global joint
// positions and global rotations. Semantics (shared with modi.core.kinematics and modi_ext.fk.reference.fk_reference):
//   Q[0] = q[0], P[0] = root;   for j > 0, p = parents[j]:
//   Q[j] = Q[p] (x) q[j],       P[j] = P[p] + rotate(Q[p], offsets[j])
// where rotate(Q, v) = v + 2w (u x v) + 2u x (u x v) with Q = (w, u); no normalisation is applied.
#include <ATen/ATen.h>

#include <tuple>

namespace modi_ext {

// Forward: returns (positions (..., J, 3), global_quats (..., J, 4)).
std::tuple<at::Tensor, at::Tensor> fk_cpu(const at::Tensor& local_quats, const at::Tensor& offsets,
                                          at::IntArrayRef parents, const at::Tensor& root_positions);

// Backward: returns (grad_local_quats, grad_root_positions, grad_offsets). grad_offsets is zeros when
// offsets_grad is false. grad_global_quats may be undefined (no gradient flows into the rotations output).
std::tuple<at::Tensor, at::Tensor, at::Tensor> fk_backward_cpu(
    const at::Tensor& grad_positions, const std::optional<at::Tensor>& grad_global_quats,
    const at::Tensor& local_quats, const at::Tensor& global_quats, const at::Tensor& offsets,
    at::IntArrayRef parents, bool offsets_grad);

}  // namespace modi_ext
