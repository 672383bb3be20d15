"""First-use self-check of the kernels on one (device, dtype): a tiny random problem per kernel vs the reference.

A kernel that is wrong on some GPU (a miscompile, an architecture the build did not target, a driver issue) must
never silently train a model: ``modi_ext.dispatch`` runs ``run(device, dtype)`` once per (device, dtype) before the
kernels get a real call and routes that pair to the dense path if anything here disagrees with the float64 CPU
reference.  Each problem is a few thousand multiply-adds (forward and backward): milliseconds, once per process.
"""
from __future__ import annotations

import torch

from modi_ext import reference
from modi_ext.topology_tensors import csr_from_lists

# error allowed relative to max(1, max |reference|); gradients get 4x (reductions over batch x time)
TOL = {torch.float64: 1e-9, torch.float32: 1e-4, torch.bfloat16: 5e-2, torch.float16: 8e-3}
_NEIGHBORS = [[0, 1], [0, 1, 2], [1, 2, 3, 4], [2, 3], [2, 4]]
_POOLING = [[0, 1], [1, 2], [3, 4]]  # overlapping: fine entity 1 belongs to two coarse ones
_PARENTS = [-1, 0, 1, 1, 3]


def _error(got: torch.Tensor, want: torch.Tensor) -> float:
    got = got.detach().to("cpu", torch.float64)
    if got.shape != want.shape:
        return float("inf")
    if not bool(torch.isfinite(got).all()):
        return float("inf")
    return float((got - want).abs().max()) / max(1.0, float(want.abs().max()))


def _rounded(g: torch.Generator, dtype: torch.dtype, *shape: int, scale: float = 1.0, shift: float = 0.0):
    return (shift + scale * torch.randn(*shape, generator=g, dtype=torch.float64)).to(dtype).double()


def _skeletal(kind: str, device: str, dtype: torch.dtype) -> tuple[float, float]:
    """(forward error, gradient error) of one modulated, demodulated, biased call with its backward."""
    from modi_ext import ops  # late: ops imports the dispatcher that imports this module

    g = torch.Generator().manual_seed(1234)
    lists, n_in = (_NEIGHBORS, 5) if kind == "conv" else (_POOLING, 5)
    topo = csr_from_lists(lists, n_in=n_in)
    b, cin, cout, t, u = 2, 3, 5, 8, 3
    nnz = topo.nnz
    n_rows = topo.n_out
    if kind == "up":
        x = _rounded(g, dtype, b, cin, n_rows, t)
        w = _rounded(g, dtype, cin, nnz, cout, u, scale=0.3)
        n_out, pad = n_in, "reflect"
    else:
        x = _rounded(g, dtype, b, cin, n_in, t)
        w = _rounded(g, dtype, cout, nnz, cin, u, scale=0.3)
        n_out, pad = n_rows, ("reflect" if kind == "conv" else "zeros")
    bias = _rounded(g, dtype, cout)
    s = _rounded(g, dtype, b, cin, scale=0.3, shift=1.0)
    ref_leaves = [v.clone().requires_grad_() for v in (x, w, bias, s)]
    fn = {"conv": reference.skeletal_conv, "down": reference.skeletal_down}.get(kind)
    if fn is None:
        y_ref = reference.skeletal_up(ref_leaves[0], ref_leaves[1], ref_leaves[2], topo.index, topo.offsets, n_out,
                                      ref_leaves[3], True, pad)
    else:
        y_ref = fn(ref_leaves[0], ref_leaves[1], ref_leaves[2], topo.index, topo.offsets, ref_leaves[3], True, pad)
    gy = _rounded(g, dtype, *y_ref.shape)
    g_ref = torch.autograd.grad(y_ref, ref_leaves, gy)
    leaves = [v.to(device=device, dtype=dtype).requires_grad_() for v in (x, w, bias, s)]
    idx, off = topo.index.to(device), topo.offsets.to(device)
    kind_id = {"conv": ops._KIND_CONV, "down": ops._KIND_DOWN, "up": ops._KIND_UP}[kind]
    y = ops._run(kind_id, "ext", leaves[0], leaves[1], leaves[2], idx, off, n_out, leaves[3], True, pad)
    fwd = _error(y, y_ref.detach())
    grads = torch.autograd.grad(y, leaves, gy.to(device=device, dtype=dtype), allow_unused=True)
    bwd = max((_error(a, r) if a is not None else float("inf")) for a, r in zip(grads, g_ref))
    return fwd, bwd


def _fk(device: str, dtype: torch.dtype) -> tuple[float, float]:
    from modi_ext import dispatch
    from modi_ext.fk import fk_reference

    g = torch.Generator().manual_seed(99)
    q = torch.randn(2, 3, len(_PARENTS), 4, generator=g, dtype=torch.float64)
    q = (q / q.norm(dim=-1, keepdim=True)).to(dtype).double()
    off = _rounded(g, dtype, len(_PARENTS), 3)
    root = _rounded(g, dtype, 2, 3, 3)
    rq, rr = q.clone().requires_grad_(), root.clone().requires_grad_()
    p_ref, r_ref = fk_reference(rq, off, _PARENTS, rr, True)
    gp, gr = _rounded(g, dtype, *p_ref.shape), _rounded(g, dtype, *r_ref.shape)
    g_ref = torch.autograd.grad([p_ref, r_ref], [rq, rr], [gp, gr])
    dq, dr = (v.to(device=device, dtype=dtype).requires_grad_() for v in (q, root))
    pos, rot = dispatch.KERNELS["fk"](dq, off.to(device=device, dtype=dtype), list(_PARENTS), dr)
    fwd = max(_error(pos, p_ref.detach()), _error(rot, r_ref.detach()))
    grads = torch.autograd.grad([pos, rot], [dq, dr], [gp.to(device, dtype), gr.to(device, dtype)])
    return fwd, max(_error(a, r) for a, r in zip(grads, g_ref))


def run(device: str, dtype: torch.dtype) -> dict:
    """``{"ok", "errors": {op: message}, "max_error": {op: relative error}}`` for every kernel on (device, dtype)."""
    from modi_ext import dispatch

    tol = TOL.get(dtype, 1e-4)
    dev_type = torch.device(device).type
    checks = {}
    if dispatch.kernels_built(dev_type, "skeletal"):
        checks = {f"skeletal_{k}": (lambda k=k: _skeletal(k, device, dtype)) for k in ("conv", "down", "up")}
    if dispatch.kernels_built(dev_type, "fk"):
        checks["fk"] = lambda: _fk(device, dtype)
    errors: dict[str, str] = {}
    worst: dict[str, float] = {}
    # first use may come inside no_grad / inference_mode / autocast: the check needs none of them
    with torch.inference_mode(False), torch.enable_grad(), torch.autocast(torch.device(device).type, enabled=False):
        for op, check in checks.items():
            try:
                fwd, bwd = check()
            except Exception as exc:  # noqa: BLE001 - a kernel that raises has failed its check
                errors[op] = f"raised {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
                continue
            worst[op] = max(fwd, bwd)
            if fwd > tol:
                errors[op] = f"forward error {fwd:.3g} > {tol:.1g}"
            elif bwd > 4 * tol:
                errors[op] = f"backward error {bwd:.3g} > {4 * tol:.1g}"
    return {"ok": not errors, "errors": errors, "max_error": worst}
