"""One shape list that launches every CUDA kernel instantiation, with its float64 oracle.

Shared by ``validate``'s sanitizer steps (``--payload kernels``), the GPU tests (``tests/modi_ext/runtime/test_cuda_ops.py``),
the first-use self-check (``modi_ext.runtime.selfcheck``) and the CPU proof of coverage
(``tests/modi_ext/runtime/test_cuda_emulated.py`` runs it on the emulated kernels and compares the instantiations launched with
all the emulator registered).

What each case reaches, per dtype (the kernels' template arguments are the dtype, the tile height BM and the
blur/adjoint flag; FK's are the dtype and where the walk state lives):

* ``narrow`` (cin 3, cout 5, B x T = 16, 5 entities): the 32-row tiles of the row / transposed / weight-gradient
  GEMMs, one weight-gradient split;
* ``wide`` (cin 34, cout 36, B x T = 260 >= 2 x 64, 3 entities): the 64-row tiles and the split-K weight gradient
  (``split_reduce_kernel``; csrc/skeletal/launch_plan.h);
* both modulated, demodulated and biased, every gradient asked for: ``style_finish_kernel`` and
  ``scale_grad_kernel``; conv / down and up: the plain and the blur (adjoint) variants;
* FK, one joint count per launch plan of ``csrc/fk/cuda.cu`` (walk state in shared memory for 128 / 64 / 32 threads,
  else a global workspace; each at a plan boundary), 40 samples (a partial block and a partial warp), rotation
  and offsets gradients: ``fk_offsets_reduce_kernel`` and the warp-shuffle offsets reduction;
* the demodulation coefficients (``csrc/demod/cuda.cu``), conv / down and up maps, with a style and without, both
  gradients: its forward, style-gradient and weight-gradient kernels.

Everything calls the raw ops of a kernel table (``modi_ext.runtime.kernels.kernel_table``), never autograd, so the same
list runs on ``torch.ops.modi_ext`` (CPU or CUDA) and on the emulator's ``torch.ops.modi_ext_emu``.
"""
from __future__ import annotations

import random
from dataclasses import dataclass
from typing import Callable, Mapping

import torch

from modi_ext.act import fused_leaky_relu
from modi_ext.demod import dense as demod_dense
from modi_ext.demod.reference import DEMOD_EPS
from modi_ext.fk.reference import fk_reference
from modi_ext.skeletal import reference
from modi_ext.csr import csr_from_lists

__all__ = ["SkeletalCase", "FkCase", "DemodCase", "SKELETAL_CASES", "FK_PLANS", "DEMOD_CASES", "fk_cases", "DTYPES",
           "TOL", "run_case", "run", "fk_plan"]

DTYPES = (torch.float32, torch.float64, torch.float16, torch.bfloat16)
# error allowed relative to max(1, max |reference|); gradients get 4x (reductions over batch x time)
TOL = {torch.float64: 1e-9, torch.float32: 1e-4, torch.bfloat16: 5e-2, torch.float16: 8e-3}
GRAD_FACTOR = 4.0
KIND_ID = {"conv": 0, "down": 1, "up": 2}
NEIGHBORS = [[0, 1], [0, 1, 2], [1, 2, 3, 4], [2, 3], [2, 4]]  # conv: 5 entities
POOLING = [[0, 1], [1, 2], [3, 4]]  # down / up: 5 fine <-> 3 coarse, fine entity 1 in two groups


@dataclass(frozen=True)
class SkeletalCase:
    name: str
    kind: str  # conv | down | up
    B: int
    cin: int
    cout: int
    T: int  # input frames
    U: int = 3
    padding: str = "reflect"
    lists: tuple = ()  # the CSR map: conv neighbours, or down / up coarse -> fine groups
    n_in: int = 5  # entities the map reads (conv: all of them; down / up: the fine ones)
    act: bool = False  # the bias activation in the epilogue (modi_ext.act)

    @property
    def columns(self) -> int:
        """B x T of the weight-gradient reduction (split in runs of >= 64 columns: csrc/skeletal/launch_plan.h)."""
        return self.B * (self.T // 2 if self.kind == "down" else self.T)


def _lists(kind: str, small: bool) -> tuple[tuple, int]:
    if kind == "conv":
        lists = [[0, 1], [0, 1, 2], [1, 2]] if small else NEIGHBORS
    else:
        lists = [[0, 1], [1, 2]] if small else POOLING
    return tuple(tuple(r) for r in lists), (3 if small else 5)


def _cases() -> tuple[SkeletalCase, ...]:
    out = []
    for kind in ("conv", "down", "up"):
        pad = "zeros" if kind == "down" else "reflect"
        lists, n_in = _lists(kind, small=False)
        out.append(SkeletalCase(f"{kind}.narrow", kind, B=2, cin=3, cout=5, T=16 if kind == "down" else 8,
                                padding=pad, lists=lists, n_in=n_in, act=True))
        # Few entities, one sample, U = 1: the tile height and the split depend on none of them, and the emulator's
        # cost (the self-check's first use on the CPU) is blocks x threads.
        lists, n_in = _lists(kind, small=True)
        out.append(SkeletalCase(f"{kind}.wide", kind, B=1, cin=34, cout=36, T=520 if kind == "down" else 260, U=1,
                                padding=pad, lists=lists, n_in=n_in))
    return tuple(out)


SKELETAL_CASES = _cases()


@dataclass(frozen=True)
class FkCase:
    name: str
    J: int
    N: int = 40  # a partial warp, and a partial block of the 128- and 64-thread plans


FK_SMEM_BUDGET = 48 * 1024  # csrc/fk/cuda.cu kSmemBudget
FK_PLANS = ("smem128", "smem64", "smem32", "global")


def fk_plan(J: int, acc_bytes: int) -> str:
    """The launch plan ``csrc/fk/cuda.cu``'s ``plan_launch`` picks for J joints (accumulator of ``acc_bytes``)."""
    fixed = J * 3 * acc_bytes + J * 2
    for t in (128, 64, 32):
        if fixed + t * J * 7 * acc_bytes <= FK_SMEM_BUDGET:
            return f"smem{t}"
    return "global"


def fk_cases(dtype: torch.dtype) -> tuple[FkCase, ...]:
    """One case per FK launch plan for ``dtype``, each at a plan boundary: the largest J of the 128-thread plan
    (its 48 KB edge), the smallest J of each later plan (fp32: 13, 14, 28, 55 joints; fp64: 6, 7, 14, 28)."""
    acc = 8 if dtype == torch.float64 else 4
    first: dict[str, int] = {}
    last: dict[str, int] = {}
    J = 1
    while "global" not in first:
        plan = fk_plan(J, acc)
        first.setdefault(plan, J)
        last[plan] = J
        J += 1
    joints = {"smem128": last["smem128"], **{p: first[p] for p in FK_PLANS[1:]}}
    return tuple(FkCase(f"fk.{p}", joints[p]) for p in FK_PLANS)


@dataclass(frozen=True)
class DemodCase:
    name: str
    up: bool
    styled: bool
    B: int = 3
    cin: int = 4
    cout: int = 6
    U: int = 3


# every grid a partial block of 128 threads (3 x 6 x 5 = 90 coefficients; 6 x 11 x 4 x 3 weight entries)
DEMOD_CASES = tuple(DemodCase(f"demod.{'up' if up else 'conv'}.{'style' if styled else 'plain'}", up, styled)
                    for up in (False, True) for styled in (False, True))


# ------------------------------------------------------------------------------------------------ inputs and oracle
def _rnd(g: torch.Generator, dtype: torch.dtype, *shape: int, scale: float = 1.0, shift: float = 0.0):
    """float64 values already rounded to ``dtype`` (so the oracle sees exactly what the kernel sees)."""
    return (shift + scale * torch.randn(*shape, generator=g, dtype=torch.float64)).to(dtype).double()


def skeletal_inputs(case: SkeletalCase, dtype: torch.dtype, seed: int = 1234) -> dict:
    g = torch.Generator().manual_seed(seed)
    topo = csr_from_lists([list(r) for r in case.lists], n_in=case.n_in)
    rows, nnz = topo.n_out, topo.nnz
    if case.kind == "up":
        n_in, n_out, t_out = rows, case.n_in, 2 * case.T
        w = _rnd(g, dtype, case.cin, nnz, case.cout, case.U, scale=(case.cout * case.U) ** -0.5)
    else:
        n_in, n_out = case.n_in, rows
        t_out = case.T // 2 if case.kind == "down" else case.T
        w = _rnd(g, dtype, case.cout, nnz, case.cin, case.U, scale=(2 * case.cin * case.U) ** -0.5)
    x = _rnd(g, dtype, case.B, case.cin, n_in, case.T)
    b = _rnd(g, dtype, case.cout)
    s = _rnd(g, dtype, case.B, case.cin, scale=0.3, shift=1.0)
    dense_n = n_out if case.kind == "up" else n_in
    dense = reference.to_dense(w, topo.index, topo.offsets, dense_n)
    if case.kind == "up":  # dense (Ci, Co, Ec, Ef, U): demodulate the output entity Ef over input channels
        a = torch.einsum("bi,iocfu->bof", s.pow(2), dense.pow(2))
    else:  # dense (Co, Ci, Eo, Ei, U)
        a = torch.einsum("bi,oijnu->boj", s.pow(2), dense.pow(2))
    d = torch.rsqrt(a + DEMOD_EPS).to(dtype).double()
    gy = _rnd(g, dtype, case.B, case.cout, n_out, t_out)
    p = dict(x=x, w=w, b=b, s=s, d=d, gy=gy, index=topo.index, offsets=topo.offsets, n_out=n_out)
    if case.act:  # where the pre-activation is within rounding of 0 either slope is right: no gradient flows there
        pre = _skeletal_pre(case, p)
        tol = 64 * torch.finfo(dtype).eps * max(1.0, float(pre.abs().max()))
        p["gy"] = torch.where(pre.abs() < tol, 0.0, gy)
    return p


def _skeletal_pre(case: SkeletalCase, p: dict, leaves: tuple | None = None) -> torch.Tensor:
    """``d * A_W(x * s) + b`` in float64 (the pre-activation; ``y`` itself without ``act``)."""
    x, w, b, s, d = leaves if leaves is not None else (p[k] for k in ("x", "w", "b", "s", "d"))
    args = (p["index"], p["offsets"])
    if case.kind == "up":
        z = reference.skeletal_up(x, w, None, *args, p["n_out"], s, False, case.padding)
    else:
        f = reference.skeletal_conv if case.kind == "conv" else reference.skeletal_down
        z = f(x, w, None, *args, s, False, case.padding)
    return z * d.unsqueeze(-1) + b.view(1, -1, 1, 1)


def skeletal_oracle(case: SkeletalCase, p: dict) -> tuple[torch.Tensor, tuple]:
    """``y = d * A_W(x * s) + b`` (then the bias activation, with ``case.act``) in float64 (d and s independent
    inputs, as the kernels take them) and the gradients of ``<gy, y>`` w.r.t. (x, w, b, s, d)."""
    leaves = [p[k].clone().requires_grad_() for k in ("x", "w", "b", "s", "d")]
    y = _skeletal_pre(case, p, tuple(leaves))
    if case.act:
        y = fused_leaky_relu(y, None)
    grads = torch.autograd.grad(y, leaves, p["gy"])
    return y.detach(), tuple(gr.detach() for gr in grads)


def fk_inputs(case: FkCase, dtype: torch.dtype, seed: int = 99) -> dict:
    rng = random.Random(seed + case.J)
    g = torch.Generator().manual_seed(seed + case.J)
    parents = [-1] + [j - 1 if rng.random() < 0.5 else rng.randrange(j) for j in range(1, case.J)]
    q = torch.randn(case.N, case.J, 4, generator=g, dtype=torch.float64)
    q = (q / q.norm(dim=-1, keepdim=True)).to(dtype).double()
    return dict(parents=parents, q=q, off=_rnd(g, dtype, case.J, 3), root=_rnd(g, dtype, case.N, 3),
                gp=_rnd(g, dtype, case.N, case.J, 3), gg=_rnd(g, dtype, case.N, case.J, 4))


def demod_inputs(case: DemodCase, dtype: torch.dtype, seed: int = 7) -> dict:
    g = torch.Generator().manual_seed(seed)
    topo = csr_from_lists(POOLING if case.up else NEIGHBORS, n_in=5)
    n_out = 5 if case.up else topo.n_out
    shape = (case.cin, topo.nnz, case.cout, case.U) if case.up else (case.cout, topo.nnz, case.cin, case.U)
    w = _rnd(g, dtype, *shape, scale=0.5)
    s = _rnd(g, dtype, case.B, case.cin, scale=0.3, shift=1.0) if case.styled else None
    gd = _rnd(g, dtype, case.B if case.styled else 1, case.cout, n_out)
    return dict(w=w, s=s, gd=gd, index=topo.index, offsets=topo.offsets, n_out=n_out)


def demod_oracle(case: DemodCase, p: dict) -> tuple[torch.Tensor, tuple]:
    """The torch form in float64 and the gradients of ``<gd, d>`` w.r.t. (w, s)."""
    w = p["w"].clone().requires_grad_()
    s = p["s"].clone().requires_grad_() if case.styled else None
    d = demod_dense.demod_scale(w, p["index"], p["offsets"], s, case.up, p["n_out"], p["gd"].shape[0])
    leaves = [w] + ([s] if s is not None else [])
    grads = torch.autograd.grad(d, leaves, p["gd"])
    return d.detach(), tuple(gr.detach() for gr in grads)


def fk_oracle(p: dict) -> tuple[tuple, tuple]:
    q, off, root = (p[k].clone().requires_grad_() for k in ("q", "off", "root"))
    pos, rot = fk_reference(q, off, p["parents"], root, return_rotations=True)
    grads = torch.autograd.grad([pos, rot], [q, root, off], [p["gp"], p["gg"]])
    return (pos.detach(), rot.detach()), tuple(gr.detach() for gr in grads)


# ------------------------------------------------------------------------------------------------ running
def rel_error(got: torch.Tensor, want: torch.Tensor) -> float:
    """max |got - want| / max(1, max |want|); inf for a wrong shape or any non-finite value."""
    got = got.detach().to("cpu", torch.float64)
    if got.shape != want.shape or not bool(torch.isfinite(got).all()):
        return float("inf")
    return float((got - want).abs().max()) / max(1.0, float(want.abs().max()))


def _skeletal_call(table: Mapping[str, Callable], case: SkeletalCase, p: dict, device: str, dtype: torch.dtype):
    dev = lambda t: t.to(device=device, dtype=dtype).contiguous()  # noqa: E731
    x, w, b, s, d, gy = (dev(p[k]) for k in ("x", "w", "b", "s", "d", "gy"))
    idx, off = p["index"].to(device), p["offsets"].to(device)
    if case.kind == "up":
        y = table["skeletal_up"](x, w, b, idx, off, p["n_out"], s, d, case.padding, case.act)
    else:
        y = table[f"skeletal_{case.kind}"](x, w, b, idx, off, s, d, case.padding, case.act)
    grads = table["skeletal_backward"](gy, y, x, w, b, idx, off, s, d, case.padding, KIND_ID[case.kind], p["n_out"],
                                       [True, True, True, True], case.act)
    return y, tuple(grads)


def _fk_call(table: Mapping[str, Callable], p: dict, device: str, dtype: torch.dtype):
    dev = lambda t: t.to(device=device, dtype=dtype).contiguous()  # noqa: E731
    q, off, root = dev(p["q"]), dev(p["off"]), dev(p["root"])
    pos, rot = table["fk"](q, off, list(p["parents"]), root)
    grads = table["fk_backward"](dev(p["gp"]), dev(p["gg"]), q, rot.contiguous(), off, list(p["parents"]), True)
    return (pos, rot), tuple(grads)


def _demod_call(table: Mapping[str, Callable], case: DemodCase, p: dict, device: str, dtype: torch.dtype):
    dev = lambda t: t.to(device=device, dtype=dtype).contiguous() if t is not None else None  # noqa: E731
    w, s = dev(p["w"]), dev(p["s"])
    idx, off = p["index"].to(device), p["offsets"].to(device)
    d = table["demod_scale"](w, s, idx, off, case.up, p["n_out"], DEMOD_EPS)
    gw, gs = table["demod_scale_backward"](dev(p["gd"]), d, w, s, idx, off, case.up, p["n_out"], [True, True])
    return d, (gw, gs) if case.styled else (gw,)


def run_case(table: Mapping[str, Callable], case: SkeletalCase | FkCase | DemodCase, device: str, dtype: torch.dtype,
             check: bool = True) -> tuple[float, float]:
    """Run one case on the kernels (forward, then the backward with every gradient); with ``check``, return its
    (forward error, gradient error) against the float64 oracle, else (0, 0)."""
    if isinstance(case, DemodCase):
        p = demod_inputs(case, dtype)
        d, grads = _demod_call(table, case, p, device, dtype)
        if not check:
            return 0.0, 0.0
        want_d, want_g = demod_oracle(case, p)
        return rel_error(d, want_d), max(rel_error(a, r) for a, r in zip(grads, want_g))
    if isinstance(case, SkeletalCase):
        p = skeletal_inputs(case, dtype)
        y, grads = _skeletal_call(table, case, p, device, dtype)
        if not check:
            return 0.0, 0.0
        want_y, want_g = skeletal_oracle(case, p)
        return rel_error(y, want_y), max(rel_error(a, r) for a, r in zip(grads, want_g))
    p = fk_inputs(case, dtype)
    outs, grads = _fk_call(table, p, device, dtype)
    if not check:
        return 0.0, 0.0
    want_o, want_g = fk_oracle(p)
    return (max(rel_error(a, r) for a, r in zip(outs, want_o)),
            max(rel_error(a, r) for a, r in zip(grads, want_g)))


def cases(dtype: torch.dtype, families: tuple[str, ...] = ("skeletal", "fk", "demod")) -> list:
    return ((list(SKELETAL_CASES) if "skeletal" in families else [])
            + (list(fk_cases(dtype)) if "fk" in families else [])
            + (list(DEMOD_CASES) if "demod" in families else []))


def run(table: Mapping[str, Callable], device: str, dtypes=DTYPES, check: bool = True) -> dict:
    """Every case in every dtype.  ``{"ran": [...], "errors": {case.dtype: message}}``; an empty ``errors`` means
    every result matched the oracle within ``TOL`` (forward) and ``GRAD_FACTOR x TOL`` (gradients)."""
    ran, errors = [], {}
    for dtype in dtypes:
        tol = TOL[dtype]
        for case in cases(dtype):
            label = f"{case.name}.{str(dtype).replace('torch.', '')}"
            fwd, bwd = run_case(table, case, device, dtype, check)
            ran.append(label)
            if fwd > tol:
                errors[label] = f"forward error {fwd:.3g} > {tol:.1g}"
            elif bwd > GRAD_FACTOR * tol:
                errors[label] = f"backward error {bwd:.3g} > {GRAD_FACTOR * tol:.1g}"
    return {"ran": ran, "errors": errors}
