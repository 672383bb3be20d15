"""modi_ext CUDA kernels: every op against the dense reference, gradcheck, opcheck, half precision, device-side index
checks, determinism and CUDA-graph capture of a training step.

The oracle is always the pure-torch reference evaluated in float64 on the CPU from the very same (rounded) inputs,
so nothing here compares the kernels with themselves.  The whole module is skipped, with the reason, on machines
without a CUDA device or without the CUDA part of the extension.

    pytest tests/modi_ext/runtime/test_cuda_ops.py -q                                   # on a GPU machine
    compute-sanitizer --tool memcheck python -m pytest tests/modi_ext/runtime/test_cuda_ops.py -q -k "not subprocess"
"""
from __future__ import annotations

import random
import re
import subprocess
import sys
import textwrap

import pytest
import torch

import modi_ext
from modi_ext import HAS_EXT
from modi_ext.fk import fk, fk_reference
from modi_ext.runtime import kernels, payload
from modi_ext.skeletal import ops, reference
from modi_ext.csr import csr_from_lists


def _has_cuda_kernels() -> bool:
    if not HAS_EXT or not hasattr(torch.ops.modi_ext, "skeletal_conv"):
        return False
    try:
        return all(torch._C._dispatch_has_kernel_for_dispatch_key(f"modi_ext::{op}", "CUDA")
                   for op in ("skeletal_conv", "skeletal_down", "skeletal_up", "skeletal_backward", "fk",
                              "fk_backward"))
    except RuntimeError:
        return False


pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device: the CUDA kernels need a GPU"),
    pytest.mark.skipif(torch.cuda.is_available() and not _has_cuda_kernels(),
                       reason="modi_ext was built without its CUDA kernels (MODI_EXT_CUDA=0 or no nvcc at build time)"),
]

DEV = "cuda"
KINDS = ("conv", "down", "up")
MODS = ("plain", "style", "style_demod", "demod")


@pytest.fixture(autouse=True)
def _force_ext(monkeypatch):
    monkeypatch.setenv("MODI_EXT_IMPL", "ext")


# ------------------------------------------------------------------------------------------------ topology helpers
def random_tree(n: int, rng: random.Random) -> list[int]:
    """Topologically sorted tree: mostly chains (limbs) with random branch points."""
    return [-1] + [j - 1 if rng.random() < 0.6 else rng.randrange(j) for j in range(1, n)]


def neighbor_lists(parents: list[int], distance: int) -> list[list[int]]:
    """Entities within `distance` edges in the undirected tree, including self, sorted."""
    n = len(parents)
    adj: list[list[int]] = [[] for _ in range(n)]
    for j, p in enumerate(parents):
        if p >= 0:
            adj[j].append(p)
            adj[p].append(j)
    out = []
    for s in range(n):
        seen, frontier = {s}, [s]
        for _ in range(distance):
            frontier = [m for v in frontier for m in adj[v] if m not in seen]
            seen.update(frontier)
        out.append(sorted(seen))
    return out


def random_pooling(n_fine: int, rng: random.Random, overlap: bool = True) -> list[list[int]]:
    """Coarse -> fine map covering every fine entity; with `overlap` some fine entities belong to two groups."""
    groups, i = [], 0
    while i < n_fine:
        size = rng.choice([1, 2, 2, 3])
        groups.append(list(range(i, min(n_fine, i + size))))
        i += size
    if overlap:
        for g in groups[1:]:
            if rng.random() < 0.3:
                g.insert(0, g[0] - 1)  # also read the last member of the previous group
    return groups


class Case:
    """One random problem for a skeletal op: topology, shapes and float64 CPU inputs (rounded to `dtype`)."""

    def __init__(self, kind: str, seed: int, U: int = 3, padding: str = "zeros", mod: str = "plain",
                 bias: bool = True, dtype: torch.dtype = torch.float32, B: int | None = None, T: int | None = None,
                 cin: int | None = None, cout: int | None = None, n_ent: int | None = None):
        rng = random.Random(seed)
        g = torch.Generator().manual_seed(seed)
        self.kind, self.U, self.padding, self.dtype = kind, U, padding, dtype
        self.style_on = mod in ("style", "style_demod")
        self.demod = mod in ("demod", "style_demod")
        h = U // 2
        n = n_ent or rng.randint(2, 12)
        if kind == "conv":
            lists = neighbor_lists(random_tree(n, rng), rng.choice([1, 2]))
            self.n_in, self.n_out, rows = n, n, n
        else:
            lists = random_pooling(n, rng)
            rows = len(lists)
            self.n_in, self.n_out = (n, rows) if kind == "down" else (rows, n)
        topo = csr_from_lists(lists, n_in=n, name="lists")
        self.lists = lists
        self.index, self.offsets = topo.index, topo.offsets
        nnz = topo.index.numel()
        self.B = B or rng.randint(1, 3)
        self.cin = cin or rng.choice([1, 3, 8, 33])
        self.cout = cout or rng.choice([1, 5, 16, 40, 70])
        lo = 2 if kind == "down" else 1
        if padding == "reflect":
            lo = max(lo, h + 1 if kind != "up" else h // 2 + 1)
        self.T = T or rng.randint(max(lo, 1), 19)
        if kind == "up":
            w_shape = (self.cin, nnz, self.cout, U)
            fan = self.cin * U
        else:
            w_shape = (self.cout, nnz, self.cin, U)
            fan = max(len(r) for r in lists) * self.cin * U
        rnd = lambda *s: torch.randn(*s, generator=g, dtype=torch.float64).to(dtype).double()  # noqa: E731
        self.x = rnd(self.B, self.cin, self.n_in, self.T)
        self.w = rnd(*w_shape) / fan ** 0.5
        self.w = self.w.to(dtype).double()
        self.b = rnd(self.cout) if bias else None
        self.s = (1.0 + 0.5 * rnd(self.B, self.cin)).to(dtype).double() if self.style_on else None
        t_out = {"conv": self.T, "down": self.T // 2, "up": 2 * self.T}[kind]
        self.out_shape = (self.B, self.cout, self.n_out, t_out)
        self.gy = rnd(*self.out_shape)

    def leaves(self, device: str, dtype: torch.dtype, requires_grad: bool = False):
        """(x, w, b, s) on `device` in `dtype` (None where absent)."""
        out = []
        for t in (self.x, self.w, self.b, self.s):
            out.append(None if t is None else t.to(device=device, dtype=dtype).requires_grad_(requires_grad))
        return out

    def topo(self, device: str):
        return self.index.to(device), self.offsets.to(device)

    def run_ops(self, x, w, b, s):
        """modi_ext.skeletal.ops (the public wrapper; the extension path on CUDA tensors)."""
        idx, off = self.topo(x.device.type)
        kw = dict(style=s, demodulate=self.demod, padding_mode=self.padding)
        if self.kind == "conv":
            return ops.skeletal_conv(x, w, b, idx, off, **kw)
        if self.kind == "down":
            return ops.skeletal_down(x, w, b, idx, off, **kw)
        return ops.skeletal_up(x, w, b, idx, off, self.n_out, **kw)

    def run_direct(self, x, w, b, s):
        """torch.ops.modi_ext.* directly (any dtype; the demodulation scale is formed in fp32, then rounded)."""
        idx, off = self.topo(x.device.type)
        scale = None
        if self.demod:
            rows = self.n_out
            scale = ops.demod_scale(w.float(), idx, off, None if s is None else s.float(), self.kind == "up", rows,
                                    x.shape[0]).to(x.dtype)
        if self.kind == "conv":
            return torch.ops.modi_ext.skeletal_conv(x, w, b, idx, off, s, scale, self.padding)
        if self.kind == "down":
            return torch.ops.modi_ext.skeletal_down(x, w, b, idx, off, s, scale, self.padding)
        return torch.ops.modi_ext.skeletal_up(x, w, b, idx, off, self.n_out, s, scale, self.padding)

    def run_ref(self, x, w, b, s):
        """The dense reference (the oracle)."""
        idx, off = self.topo(x.device.type)
        if self.kind == "conv":
            return reference.skeletal_conv(x, w, b, idx, off, s, self.demod, self.padding)
        if self.kind == "down":
            return reference.skeletal_down(x, w, b, idx, off, s, self.demod, self.padding)
        return reference.skeletal_up(x, w, b, idx, off, self.n_out, s, self.demod, self.padding)

    def ref_grads(self):
        """Reference output and gradients of <y, gy> w.r.t. (x, w, b, s), float64 on the CPU."""
        leaves = self.leaves("cpu", torch.float64, requires_grad=True)
        y = self.run_ref(*leaves)
        present = [t for t in leaves if t is not None]
        grads = torch.autograd.grad(y, present, self.gy)
        it = iter(grads)
        return y.detach(), [None if t is None else next(it) for t in leaves]

    def ext_grads(self, dtype: torch.dtype, direct: bool = False):
        leaves = self.leaves(DEV, dtype, requires_grad=True)
        y = (self.run_direct if direct else self.run_ops)(*leaves)
        present = [t for t in leaves if t is not None]
        grads = torch.autograd.grad(y, present, self.gy.to(DEV, dtype))
        it = iter(grads)
        return y.detach(), [None if t is None else next(it) for t in leaves]


# fp32 tolerances per gradient, relative to max(1, max |reference|): the weight, bias and style gradients are
# reductions over batch x time (and entities), and with demodulation the style gradient nearly cancels.
GRAD_TOL = {"x": 5e-5, "weight": 1e-4, "bias": 1e-4, "style": 3e-4}


def assert_near(got: torch.Tensor, want: torch.Tensor, tol: float, what: str = "") -> None:
    """max |got - want| <= tol * max(1, max |want|), compared in float64 on the CPU."""
    got = got.detach().to("cpu", torch.float64)
    want = want.detach().to("cpu", torch.float64)
    assert got.shape == want.shape, f"{what}: shape {tuple(got.shape)} != {tuple(want.shape)}"
    assert torch.isfinite(got).all(), f"{what}: non-finite values"
    err = (got - want).abs().max().item() if want.numel() else 0.0
    scale = max(1.0, want.abs().max().item() if want.numel() else 0.0)
    assert err <= tol * scale, f"{what}: max abs error {err:.3g} > {tol:.1g} x {scale:.3g}"


# ------------------------------------------------------------------------------------------------ skeletal: fp32
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("U", [1, 3, 5])
@pytest.mark.parametrize("padding", ["zeros", "reflect"])
@pytest.mark.parametrize("mod", MODS)
@pytest.mark.parametrize("bias", [True, False])
def test_forward_matches_reference(kind, U, padding, mod, bias):
    for seed in range(3):
        c = Case(kind, seed=1000 * U + seed, U=U, padding=padding, mod=mod, bias=bias)
        want = c.run_ref(*c.leaves("cpu", torch.float64))
        got = c.run_ops(*c.leaves(DEV, torch.float32))
        assert got.is_cuda and got.dtype == torch.float32
        assert_near(got, want, 2e-5, f"{kind} seed {seed}")


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("U", [1, 3, 5])
@pytest.mark.parametrize("padding", ["zeros", "reflect"])
@pytest.mark.parametrize("mod", MODS)
def test_backward_matches_reference(kind, U, padding, mod):
    for seed in range(2):
        c = Case(kind, seed=2000 * U + seed, U=U, padding=padding, mod=mod, bias=seed == 0)
        y_ref, g_ref = c.ref_grads()
        y, g = c.ext_grads(torch.float32)
        assert_near(y, y_ref, 2e-5, "output")
        for name, a, b in zip(("x", "weight", "bias", "style"), g, g_ref):
            assert (a is None) == (b is None), name
            if a is not None:
                assert_near(a, b, GRAD_TOL[name], f"d/d{name} ({kind}, seed {seed})")


@pytest.mark.parametrize("kind", KINDS)
def test_large_batch_and_channels(kind):
    # Enough batch x time for the weight gradient to split its reduction, > 64 channels (several tiles) and
    # a long sequence (many column tiles), on a 25-entity level like MoDi's finest.  (No style: the reference would
    # build 16 per-sample dense weights in float64.)
    c = Case(kind, seed=7, U=3, padding="zeros", mod="plain", B=16, T=64, cin=40, cout=72, n_ent=25)
    y_ref, g_ref = c.ref_grads()
    y, g = c.ext_grads(torch.float32)
    assert_near(y, y_ref, 2e-5, "output")
    for name, a, b in zip(("x", "weight", "bias"), g, g_ref):
        assert_near(a, b, 2 * GRAD_TOL[name], f"d/d{name}")


@pytest.mark.parametrize("kind", KINDS)
def test_random_skeletons(kind):
    # Random trees with 2-40 joints, neighbor distance 1-2 / random overlapping pooling maps, every option.
    rng = random.Random(kind)
    for seed in range(8):
        n = rng.randint(2, 40)
        U = rng.choice([1, 3, 5])
        c = Case(kind, seed=31 * seed + 5, U=U, padding=rng.choice(["zeros", "reflect"]), mod=rng.choice(MODS),
                 bias=rng.random() < 0.5, n_ent=n)
        y_ref, g_ref = c.ref_grads()
        y, g = c.ext_grads(torch.float32)
        assert_near(y, y_ref, 2e-5, f"output n={n}")
        for name, a, b in zip(("x", "weight", "bias", "style"), g, g_ref):
            if b is not None:
                assert_near(a, b, GRAD_TOL[name], f"d/d{name} n={n}")


def test_modi_hierarchy_levels():
    # The Bandai 22-joint skeleton's real pooling hierarchy (modi.core.skeleton_graph): every level's conv and both scalers.
    topology = pytest.importorskip("modi.core.skeleton_graph")

    class _Skeleton:
        parents = [-1, 0, 1, 2, 3, 4, 3, 6, 7, 8, 3, 10, 11, 12, 1, 14, 15, 16, 1, 18, 19, 20]
        names = [f"j{i}" for i in range(22)]

    h = topology.build_hierarchy(_Skeleton(), feet=[16, 20], neighbor_distance=1)
    g = torch.Generator().manual_seed(0)
    cin, cout, T = 16, 24, 8
    rnd = lambda *s: torch.randn(*s, generator=g, dtype=torch.float64)  # noqa: E731
    cu = lambda t: t.float().cuda()  # noqa: E731
    for lv, level in enumerate(h.levels):
        e = level.n_entities
        topo = csr_from_lists([list(r) for r in level.neighbors], n_in=e)
        idx, off = topo.index, topo.offsets
        x, w = rnd(2, cin, e, T), rnd(cout, idx.numel(), cin, 3) * 0.2
        ref = reference.skeletal_conv(x, w, None, idx, off, None, True, "zeros")
        got = ops.skeletal_conv(cu(x), cu(w), None, idx.cuda(), off.cuda(), demodulate=True)
        assert_near(got, ref, 2e-5, f"level {lv} conv")
        if lv + 1 == len(h.levels):
            continue
        topo = csr_from_lists([list(r) for r in h.pooling[lv]], n_in=e)
        idx, off = topo.index, topo.offsets
        rows = off.numel() - 1
        x, w = rnd(2, cin, e, T), rnd(cout, idx.numel(), cin, 3) * 0.2
        ref = reference.skeletal_down(x, w, None, idx, off, None, True, "zeros")
        got = ops.skeletal_down(cu(x), cu(w), None, idx.cuda(), off.cuda(), demodulate=True)
        assert_near(got, ref, 2e-5, f"level {lv} down")
        x, w = rnd(2, cin, rows, T), rnd(cin, idx.numel(), cout, 3) * 0.2
        ref = reference.skeletal_up(x, w, None, idx, off, e, None, True, "zeros")
        got = ops.skeletal_up(cu(x), cu(w), None, idx.cuda(), off.cuda(), e, demodulate=True)
        assert_near(got, ref, 2e-5, f"level {lv} up")


# ------------------------------------------------------------------------------------------------ skeletal: fp64
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("padding", ["zeros", "reflect"])
@pytest.mark.parametrize("mod", MODS)
def test_gradcheck_float64(kind, padding, mod):
    c = Case(kind, seed=3, U=3, padding=padding, mod=mod, B=2, T=6, cin=3, cout=2, n_ent=5)
    x, w, b, s = c.leaves(DEV, torch.float64, requires_grad=True)
    if s is None:
        assert torch.autograd.gradcheck(lambda x_, w_, b_: c.run_ops(x_, w_, b_, None), (x, w, b))
    else:
        assert torch.autograd.gradcheck(lambda x_, w_, b_, s_: c.run_ops(x_, w_, b_, s_), (x, w, b, s))


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("padding", ["zeros", "reflect"])
@pytest.mark.parametrize("mod", ["plain", "style_demod"])
def test_gradgradcheck_float64(kind, padding, mod):
    """Second order (R1, path length, WGAN-GP) through modi_ext.skeletal.gradfix on the CUDA kernels."""
    c = Case(kind, seed=5, U=3, padding=padding, mod=mod, B=2, T=6, cin=2, cout=2, n_ent=5)
    x, w, b, s = c.leaves(DEV, torch.float64, requires_grad=True)
    if s is None:
        assert torch.autograd.gradgradcheck(lambda x_, w_, b_: c.run_ops(x_, w_, b_, None), (x, w, b))
    else:
        assert torch.autograd.gradgradcheck(lambda x_, w_, b_, s_: c.run_ops(x_, w_, b_, s_), (x, w, b, s),
                                            fast_mode=True)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("requires_grad", [False, True])
def test_opcheck(kind, requires_grad):
    c = Case(kind, seed=4, U=3, padding="reflect", mod="style_demod", B=2, T=6, cin=3, cout=4, n_ent=6)
    x, w, b, s = c.leaves(DEV, torch.float32, requires_grad=requires_grad)
    idx, off = c.topo(DEV)
    scale = ops.demod_scale(w.detach(), idx, off, s.detach(), kind == "up", c.n_out, c.B)
    scale.requires_grad_(requires_grad)
    if kind == "up":
        torch.library.opcheck(torch.ops.modi_ext.skeletal_up.default, (x, w, b, idx, off, c.n_out, s, scale,
                                                                       "reflect"))
    else:
        op = torch.ops.modi_ext.skeletal_conv if kind == "conv" else torch.ops.modi_ext.skeletal_down
        torch.library.opcheck(op.default, (x, w, b, idx, off, s, scale, "reflect"))


def test_backward_is_deterministic():
    # No atomics anywhere: two backward passes give bit-identical gradients.  (The demodulation sums per output
    # entity are a one-hot matmul, modi_ext.demod.dense.segment_sum; they used index_add, whose CUDA atomics made this
    # premise false.)
    for kind in KINDS:
        c = Case(kind, seed=9, mod="style_demod", B=16, T=32, cin=32, cout=32, n_ent=20)
        _, g1 = c.ext_grads(torch.float32)
        _, g2 = c.ext_grads(torch.float32)
        for a, b in zip(g1, g2):
            assert torch.equal(a, b), kind


# ------------------------------------------------------------------------------------------------ half precision
@pytest.mark.parametrize("dtype,tol", [(torch.bfloat16, 3e-2), (torch.float16, 4e-3)])
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("mod", ["plain", "style_demod"])
@pytest.mark.parametrize("padding", ["zeros", "reflect"])
def test_half_precision(dtype, tol, kind, mod, padding):
    # Inputs rounded to the half type; the float64 reference sees the same rounded values, so the error left is the
    # output rounding (and the demodulation scale's), with fp32 accumulation inside the kernels.
    c = Case(kind, seed=11, U=3, padding=padding, mod=mod, dtype=dtype, B=4, T=16, cin=24, cout=40, n_ent=14)
    y_ref, g_ref = c.ref_grads()
    y, g = c.ext_grads(dtype, direct=True)
    assert y.dtype == dtype
    assert_near(y, y_ref, tol, "output")
    for name, a, b in zip(("x", "weight", "bias", "style"), g, g_ref):
        if b is not None:
            assert a.dtype == dtype
            assert_near(a, b, 2 * tol, f"d/d{name}")


# ------------------------------------------------------------------------------------------------ bad input
def test_bad_arguments_name_the_argument():
    c = Case("conv", seed=1, B=2, T=8, cin=4, cout=4, n_ent=5)
    x, w, b, _ = c.leaves(DEV, torch.float32)
    idx, off = c.topo(DEV)
    op = torch.ops.modi_ext.skeletal_conv
    with pytest.raises(RuntimeError, match="weight is on"):
        op(x, w.cpu(), b, idx, off, None, None, "zeros")
    with pytest.raises(RuntimeError, match="bias has dtype"):
        op(x, w, b.double(), idx, off, None, None, "zeros")
    with pytest.raises(RuntimeError, match="index is on"):
        op(x, w, b, idx.cpu(), off, None, None, "zeros")
    with pytest.raises(RuntimeError, match="x must be contiguous"):
        op(x.transpose(2, 3).contiguous().transpose(2, 3), w, b, idx, off, None, None, "zeros")
    with pytest.raises(RuntimeError, match="padding_mode"):
        op(x, w, b, idx, off, None, None, "circular")
    with pytest.raises(RuntimeError, match="style must be"):
        op(x, w, b, idx, off, torch.ones(3, 4, device=DEV), None, "zeros")
    with pytest.raises(ValueError, match="weight is on"):
        ops.skeletal_conv(x, w.cpu(), b, idx, off)


def _run_subprocess(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("dtype", payload.DTYPES, ids=str)
def test_shared_payload_matches_the_reference(dtype):
    """modi_ext.runtime.payload -- the list that launches every kernel instantiation (proven on the CPU emulator by
    tests/modi_ext/runtime/test_cuda_emulated.py) and that validate's sanitizer steps run -- on the CUDA kernels vs float64."""
    res = payload.run(kernels.KERNELS, DEV, (dtype,))
    assert res["ran"] and not res["errors"], res["errors"]


# The assert each bad map must trip: its own message (csrc/skeletal/cuda.cu topology_kernel), as CUDA prints it
# ("... Assertion `<message>` failed."), not merely some stderr that mentions modi_ext.
DEVICE_ASSERTS = {"index_out_of_range": "modi_ext: index holds an entity out of range",
                  "empty_row": "modi_ext: offsets: an output entity has no neighbors"}


@pytest.mark.parametrize("bad", sorted(DEVICE_ASSERTS))
def test_subprocess_bad_index_is_a_device_assert(bad):
    # CUDA indices are validated on the device (no host sync): a bad map must stop the kernel with a device-side
    # assert (which poisons the CUDA context, hence the subprocess) instead of reading out of bounds.
    code = f"""
        import torch, modi_ext
        x = torch.randn(2, 3, 4, 8, device="cuda")
        if "{bad}" == "index_out_of_range":
            idx = torch.tensor([0, 1, 9, 2, 3], device="cuda"); off = torch.tensor([0, 2, 3, 4, 5], device="cuda")
        else:
            idx = torch.tensor([0, 1, 2, 3], device="cuda"); off = torch.tensor([0, 2, 2, 3, 4], device="cuda")
        w = torch.randn(5, idx.numel(), 3, 3, device="cuda")
        y = torch.ops.modi_ext.skeletal_conv(x, w, None, idx, off, None, None, "zeros")
        torch.cuda.synchronize()
        print("NO ERROR")
    """
    r = _run_subprocess(code)
    assert r.returncode != 0 and "NO ERROR" not in r.stdout, r.stdout + r.stderr
    assert re.search(r"Assertion `" + re.escape(DEVICE_ASSERTS[bad]) + r"` failed", r.stderr), r.stderr[-2000:]
    assert "device-side assert triggered" in r.stderr, r.stderr[-2000:]


# ------------------------------------------------------------------------------------------------ FK
def fk_inputs(parents, lead, dtype=torch.float32, seed=0, unit=True):
    g = torch.Generator().manual_seed(seed)
    J = len(parents)
    q = torch.randn(*lead, J, 4, generator=g, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    if not unit:  # off the unit sphere (the gradients must be exact there too) but well conditioned on long chains
        q = q * (1.0 + 0.2 * torch.rand(*lead, J, 1, generator=g, dtype=torch.float64) - 0.1)
    off = torch.randn(J, 3, generator=g, dtype=torch.float64) * 10.0
    root = torch.randn(*lead, 3, generator=g, dtype=torch.float64) * 50.0
    # round to dtype once so the float64 oracle sees the same values
    return [t.to(dtype).double() for t in (q, off, root)]


def _fk_grads(fn, q, off, root, parents, gpos, grot, rotations: bool):
    q, off, root = (t.clone().requires_grad_() for t in (q, off, root))
    pos, rot = fn(q, off, parents, root)
    loss = (pos * gpos).sum() + ((rot * grot).sum() if rotations else 0.0)
    grads = torch.autograd.grad(loss, (q, off, root), allow_unused=True, materialize_grads=True)  # J=1: no offsets
    return (pos.detach(), rot.detach()), grads


@pytest.mark.parametrize("n_joints", [1, 2, 7, 22, 60, 300])
@pytest.mark.parametrize("rotations", [False, True])
def test_fk_matches_reference(n_joints, rotations):
    # 22 joints: shared-memory state (64-thread blocks); 60: 32-thread blocks; 300: the global-workspace path.
    rng = random.Random(n_joints)
    parents = random_tree(n_joints, rng) if n_joints != 22 else [-1, 0, 1, 2, 3, 4, 3, 6, 7, 8, 3, 10, 11, 12, 1,
                                                                   14, 15, 16, 1, 18, 19, 20]
    lead = (5, 67) if n_joints < 100 else (3, 7)  # not a multiple of the warp size
    q, off, root = fk_inputs(parents, lead, seed=n_joints)
    g = torch.Generator().manual_seed(1)
    gpos = torch.randn(*lead, n_joints, 3, generator=g, dtype=torch.float64)
    grot = torch.randn(*lead, n_joints, 4, generator=g, dtype=torch.float64)
    ref = lambda a, b, p, c: fk_reference(a, b, p, c, return_rotations=True)  # noqa: E731
    (pos_r, rot_r), grads_r = _fk_grads(ref, q, off, root, parents, gpos, grot, rotations)
    ext = lambda a, b, p, c: fk(a, b, p, c, return_rotations=True)  # noqa: E731
    cu = [t.float().cuda() for t in (q, off, root)]
    (pos, rot), grads = _fk_grads(ext, *cu, parents, gpos.float().cuda(), grot.float().cuda(), rotations)
    assert_near(pos, pos_r, 2e-6, "positions")
    assert_near(rot, rot_r, 2e-6, "rotations")
    for name, a, b in zip(("local_quats", "offsets", "root"), grads, grads_r):
        assert_near(a, b, 1e-5, f"d/d{name}")


@pytest.mark.parametrize("n_joints", [1, 4, 22, 60])
def test_fk_gradcheck_float64(n_joints):
    parents = random_tree(n_joints, random.Random(n_joints))
    q, off, root = fk_inputs(parents, (2, 3), torch.float64, seed=2, unit=False)
    q, off, root = (t.cuda().requires_grad_() for t in (q, off / 10, root))
    assert torch.autograd.gradcheck(lambda a, b, c: fk(a, b, parents, c, return_rotations=True), (q, off, root))


@pytest.mark.parametrize("requires_grad", [False, True])
def test_fk_opcheck(requires_grad):
    for n_joints in (3, 22):
        parents = random_tree(n_joints, random.Random(5))
        q, off, root = (t.float().cuda().requires_grad_(requires_grad)
                        for t in fk_inputs(parents, (2, 3), seed=5))
        torch.library.opcheck(torch.ops.modi_ext.fk.default, (q, off, parents, root))


@pytest.mark.parametrize("dtype,tol", [(torch.bfloat16, 2e-2), (torch.float16, 3e-3)])
def test_fk_half_precision(dtype, tol):
    parents = [-1, 0, 1, 2, 3, 4, 3, 6, 7, 8, 3, 10, 11, 12, 1, 14, 15, 16, 1, 18, 19, 20]
    q, off, root = fk_inputs(parents, (4, 33), dtype, seed=3)
    off, root = off / 10, root / 50  # keep positions in the half types' comfortable range
    off, root = off.to(dtype).double(), root.to(dtype).double()
    g = torch.Generator().manual_seed(2)
    gpos = torch.randn(4, 33, 22, 3, generator=g, dtype=torch.float64).to(dtype).double()
    ref = lambda a, b, p, c: fk_reference(a, b, p, c, return_rotations=True)  # noqa: E731
    direct = lambda a, b, p, c: torch.ops.modi_ext.fk(a, b, list(p), c)  # noqa: E731
    (pos_r, rot_r), grads_r = _fk_grads(ref, q, off, root, parents, gpos, None, False)
    cu = [t.to("cuda", dtype) for t in (q, off, root)]
    (pos, rot), grads = _fk_grads(direct, *cu, parents, gpos.to("cuda", dtype), None, False)
    assert pos.dtype == dtype and rot.dtype == dtype
    assert_near(pos, pos_r, tol, "positions")
    assert_near(rot, rot_r, tol, "rotations")
    for name, a, b in zip(("local_quats", "offsets", "root"), grads, grads_r):
        assert_near(a, b, 2 * tol, f"d/d{name}")


def test_fk_bad_arguments():
    q, off, root = (t.float().cuda() for t in fk_inputs([-1, 0, 1], (2,)))
    op = torch.ops.modi_ext.fk
    with pytest.raises(RuntimeError, match="offsets is on"):
        op(q, off.cpu(), [-1, 0, 1], root)
    with pytest.raises(RuntimeError, match=r"parents\[2\] = 5 is out of range"):
        op(q, off, [-1, 0, 5], root)
    with pytest.raises(RuntimeError, match="root_positions has dtype"):
        op(q, off, [-1, 0, 1], root.double())


# ------------------------------------------------------------------------------------------------ CUDA graphs
def test_cuda_graph_capture_of_a_training_step():
    # A generator-like fwd + bwd step (modulated up-scaler, reflect-padded conv, down-scaler, FK) captured once and
    # replayed on new inputs must equal eager execution: no op may synchronise with the host or read a device
    # tensor on the host.
    from modi_ext.layers import ForwardKinematics
    from modi_ext.layers import ModulatedSkeletalConv, SkeletalConv, SkeletalDownsample

    torch.manual_seed(0)
    rng = random.Random(0)
    parents = random_tree(12, rng)
    neigh = neighbor_lists(parents, 1)
    pool = random_pooling(12, rng)
    up = ModulatedSkeletalConv(8, 16, 32, pool, 3, mode="up").to(DEV)
    conv = SkeletalConv(16, 16, neigh, 3, padding_mode="reflect").to(DEV)
    down = SkeletalDownsample(16, 8, pool, 3).to(DEV)
    fkm = ForwardKinematics(parents, torch.randn(12, 3)).to(DEV)
    params = [*up.parameters(), *conv.parameters(), *down.parameters()]
    B, T = 4, 8
    x = torch.randn(B, 8, len(pool), T, device=DEV, requires_grad=True)
    w = torch.randn(B, 32, device=DEV)
    q = torch.randn(B, 2 * T, 12, 4, device=DEV, requires_grad=True)
    root = torch.randn(B, 2 * T, 3, device=DEV)
    gy = torch.randn(B, 8, len(pool), T, device=DEV)

    def step():
        y = down(conv(up(x, w)))
        pos = fkm(q / q.norm(dim=-1, keepdim=True), root)
        loss = (y * gy).sum() + pos.square().mean()
        return (loss.detach(), *torch.autograd.grad(loss, [x, q, *params]))

    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(3):
            step()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        static_out = step()
    for trial in range(3):
        with torch.no_grad():
            x.copy_(torch.randn_like(x))
            w.copy_(torch.randn_like(w))
            q.copy_(torch.randn_like(q))
        graph.replay()
        eager = step()
        for a, b in zip(static_out, eager):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=f"trial {trial}")


def test_layers_match_cpu_path():
    # The same module gives the same fp32 output on the GPU (CUDA kernels) and the CPU (C++ kernels or reference).
    from modi_ext.layers import ModulatedSkeletalConv, SkeletalConv, SkeletalDownsample, SkeletalUpsample

    torch.manual_seed(1)
    rng = random.Random(1)
    neigh = neighbor_lists(random_tree(15, rng), 2)
    pool = random_pooling(15, rng)
    mods = [
        (SkeletalConv(12, 20, neigh, 5, padding_mode="reflect"), (torch.randn(3, 12, 15, 16),)),
        (SkeletalDownsample(12, 20, pool, 3), (torch.randn(3, 12, 15, 16),)),
        (SkeletalUpsample(12, 20, pool, 3), (torch.randn(3, 12, len(pool), 8),)),
        (ModulatedSkeletalConv(12, 20, 16, neigh, 3, mode="same"), (torch.randn(3, 12, 15, 16), torch.randn(3, 16))),
        (ModulatedSkeletalConv(12, 20, 16, pool, 3, mode="up"), (torch.randn(3, 12, len(pool), 8),
                                                                 torch.randn(3, 16))),
    ]
    for m, inputs in mods:
        want = m(*inputs)
        got = m.to(DEV)(*(t.to(DEV) for t in inputs))
        torch.testing.assert_close(got.cpu(), want, rtol=1e-5, atol=1e-5)


# ------------------------------------------------------------------------------------------------ dispatch (issue 20)
def test_public_ops_validate_the_csr_on_the_host():
    # A malformed map given to the public ops is a ValueError before any launch -- no device-side assert, so the
    # CUDA context stays usable for the good call that follows.
    c = Case("conv", seed=1, B=2, T=8, cin=4, cout=4, n_ent=5)
    x, w, b, _ = c.leaves(DEV, torch.float32)
    idx, off = c.topo(DEV)
    bad = idx.clone()
    bad[0] = 99
    with pytest.raises(ValueError, match="out of range"):
        ops.skeletal_conv(x, w, b, bad, off)
    bad_off = off.clone()
    bad_off[1] = bad_off[2] + 1
    with pytest.raises(ValueError, match="offsets"):
        ops.skeletal_conv(x, w, b, idx, bad_off)
    y = ops.skeletal_conv(x, w, b, idx, off)
    torch.cuda.synchronize()
    assert_near(y, c.run_ref(*c.leaves("cpu", torch.float64)), 1e-4, "after a refused map")


def test_auto_dispatch_self_checks_and_times_on_cuda(monkeypatch):
    import modi_ext
    from modi_ext.runtime import dispatch

    monkeypatch.setenv("MODI_EXT_IMPL", "auto")
    dispatch.reset()
    c = Case("conv", seed=4, mod="style_demod", B=16, T=64, cin=32, cout=32, n_ent=25)
    for _ in range(3):
        y = c.run_ops(*c.leaves(DEV, torch.float32))
    assert_near(y, c.run_ref(*c.leaves("cpu", torch.float64)), 1e-4, "auto")
    rows = modi_ext.dispatch_report()
    checks = [r for r in rows if r["kind"] == "selfcheck"]
    assert checks and all(r["ok"] for r in checks), checks
    auto = [r for r in rows if r["kind"] == "auto"]
    assert len(auto) == 1 and auto[0]["choice"] == ("ext" if auto[0]["ext_ms"] <= auto[0]["dense_ms"] else "dense")


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_autocast_runs_the_modulated_layers(monkeypatch, dtype):
    from modi_ext.layers import ModulatedSkeletalConv

    torch.manual_seed(0)
    m = ModulatedSkeletalConv(8, 16, 32, neighbor_lists(random_tree(10, random.Random(0)), 1)).to(DEV)
    x, w = torch.randn(4, 8, 10, 16, device=DEV, requires_grad=True), torch.randn(4, 32, device=DEV)
    want = m(x, w)
    with torch.autocast("cuda", dtype=dtype):
        y = m(x, w)
    assert y.dtype == dtype and torch.isfinite(y).all()
    assert_near(y.float(), want, 5e-2, "autocast")
    (g,) = torch.autograd.grad(y.float().sum(), x)
    assert torch.isfinite(g).all()


def test_fp16_demodulation_of_a_zero_row_is_finite():
    c = Case("conv", seed=3, mod="style_demod", dtype=torch.float16, B=2, T=8, cin=8, cout=6, n_ent=6)
    x, w, b, s = c.leaves(DEV, torch.float16)
    w = w.clone()
    w[0] = 0
    y = ops.skeletal_conv(x, w, None, *c.topo(DEV), style=s, demodulate=True)
    assert torch.isfinite(y).all() and (y[:, 0] == 0).all()


def test_fk_double_backward_gradgradcheck():
    rng = random.Random(5)
    parents = random_tree(6, rng)
    q, off, root = fk_inputs(parents, (2, 3), torch.float64)
    leaves = [t.to(DEV).requires_grad_() for t in (q, off, root)]
    torch.autograd.gradgradcheck(lambda a, o, r: fk(a, o, parents, r, impl="ext"), leaves)


# ------------------------------------------------------------------------------------------------ demodulation
@pytest.mark.parametrize("up", [False, True])
@pytest.mark.parametrize("styled", [False, True])
def test_demod_kernel_gradcheck_and_opcheck(up, styled):
    """csrc/demod/cuda.cu: the public op on CUDA runs the kernel, gradcheck in float64 (first order on the kernel,
    second order through the torch form), and opcheck of both C++ ops."""
    from modi_ext.demod import ops as demod

    c = [c for c in payload.DEMOD_CASES if c.up == up and c.styled == styled][0]
    p = payload.demod_inputs(c, torch.float64)
    w = p["w"].to(DEV).requires_grad_()
    s = p["s"].to(DEV).requires_grad_() if styled else None
    idx, off, n_out, batch = p["index"].to(DEV), p["offsets"].to(DEV), p["n_out"], c.B
    d = demod.demod_scale(w, idx, off, s, up, n_out, batch)
    assert any(r["kind"] == "path" and r["op"] == "demod_scale" and r["path"] == "ext" and r["device"].startswith(DEV)
               for r in modi_ext.dispatch_report())
    leaves = (w,) + ((s,) if styled else ())
    fn = lambda *t: demod.demod_scale(t[0], idx, off, t[1] if styled else None, up, n_out, batch)  # noqa: E731
    assert torch.autograd.gradcheck(fn, leaves)
    assert torch.autograd.gradgradcheck(fn, leaves)
    torch.library.opcheck(torch.ops.modi_ext.demod_scale.default, (w.detach(), s.detach() if styled else None, idx,
                                                                     off, up, n_out, 1e-8))
    raw = torch.ops.modi_ext.demod_scale(w.detach(), s.detach() if styled else None, idx, off, up, n_out, 1e-8)
    torch.library.opcheck(torch.ops.modi_ext.demod_scale_backward.default,
                          (torch.randn_like(raw), raw, w.detach(), s.detach() if styled else None, idx, off, up,
                           n_out, [True, True]))
