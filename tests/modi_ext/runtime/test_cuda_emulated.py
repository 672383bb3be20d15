"""The CUDA kernels (csrc/<op>/cuda.cu), run on the CPU by the CUDA emulator (csrc/emu), against the dense reference.

``modi_ext._C_emu`` is csrc/<op>/cuda.cu compiled as host C++ (``-DMODI_EXT_EMULATE_CUDA``): every CUDA thread is a
fiber, ``__syncthreads()`` a real barrier, warp shuffles a warp barrier with an exchange; shared memory and every
tensor the host code allocates are NaN (integers: their max value) until written; shared arrays are bounds-checked.
Each case runs under two thread/block schedules (index order and a seeded permutation) and the two results must be
bitwise equal (the kernels have no atomics, so any difference is a race) and match the float64 reference.

What this proves without a GPU: the kernels' index math, padding/blur adjoints, tiling, split-K bookkeeping,
barrier placement and the host code's launch geometry; that the shared payload (modi_ext.runtime.payload: validate's
sanitizer steps, the GPU tests and the self-check) launches every instantiation the emulator registered; and that
injected defects are caught -- through NaN poison (a dropped barrier, an off-by-one) and through the tolerance alone
(a finite wrong scale).  Global memory bounds: tests/modi_ext/runtime/test_cuda_emulated_asan.py.  What it does not: real
concurrency (memory-model races between warps that happen to be ordered here), speed, register/occupancy limits.

Tolerances, relative to the largest reference magnitude: fp64 1e-9, fp32 5e-5, fp16 5e-3, bf16 3e-2 (inputs are
rounded to the dtype first; the kernels accumulate half types in fp32, so the error is output rounding plus a few
ulps of the fp32 sums).
"""
from __future__ import annotations

import contextlib
import itertools
import os
import random
import re
import time
import zlib
from pathlib import Path

import pytest
import torch

from modi_ext.act import fused_leaky_relu
from modi_ext.demod.reference import DEMOD_EPS
from modi_ext.fk import fk_reference
from modi_ext.skeletal import reference
from modi_ext.csr import csr_from_lists

try:
    from modi_ext import _C_emu as EMU

    EMU_ERROR = None
except ImportError as exc:  # a build problem must fail the suite, not skip it
    EMU, EMU_ERROR = None, str(exc)

pytestmark = [pytest.mark.cuda_emulated, pytest.mark.usefixtures("one_torch_thread")]

REPO = Path(__file__).resolve().parents[3]
SEEDS = (0, 0x5EED)  # schedule seeds: index order, then a permutation of threads within phases and of blocks
TOL = {torch.float64: 1e-9, torch.float32: 5e-5, torch.float16: 5e-3, torch.bfloat16: 3e-2}
DTYPES = (torch.float64, torch.float32, torch.float16, torch.bfloat16)
KINDS = ("conv", "down", "up")
MODS = ("none", "style", "style_demod", "demod")
KIND_ID = {"conv": 0, "down": 1, "up": 2}


def ops(lib: str = "modi_ext_emu"):
    return getattr(torch.ops, lib)


DEFAULT_SMS = 108  # the emulator's multiprocessor count outside a test that sets another


@pytest.fixture(scope="module", autouse=True)
def emu():
    """The emulated module, built and clean, for every test of a module of the emulated suite (the other modules
    import this fixture); afterwards no schedule seed, defect or SM count of a test is left behind."""
    if EMU is None:
        pytest.fail(f"modi_ext._C_emu (the emulated CUDA kernels) is not built: {EMU_ERROR}. "
                    "Build it with `python3 setup.py build_ext --inplace` (MODI_EXT_EMU must not be 0).")
    assert EMU.injected_defect() == "", "the emulated module must start with no run-time defect"
    yield EMU
    EMU.set_schedule_seed(0)
    EMU.set_injected_defect("")
    EMU.set_sm_count(DEFAULT_SMS)


@contextlib.contextmanager
def sm_count(n: int):
    """The emulator's multiprocessor count (the launch plans read it), ``n`` for the block only."""
    EMU.set_sm_count(n)
    try:
        yield
    finally:
        EMU.set_sm_count(DEFAULT_SMS)


@contextlib.contextmanager
def injected(defect: str):
    """A run-time test defect of the emulated module (csrc/emu/cuda_emu.h), on for the block only."""
    EMU.set_injected_defect(defect)
    try:
        yield
    finally:
        EMU.set_injected_defect("")


# ------------------------------------------------------------------------------------------------ helpers
def schedules(fn):
    """fn() under every schedule seed; the results must be bitwise equal. Returns the first."""
    outs = []
    for s in SEEDS:
        EMU.set_schedule_seed(s)
        outs.append(fn())
    EMU.set_schedule_seed(0)
    first = outs[0]
    for o in outs:
        for a in o:
            if a is not None and a.is_floating_point():
                assert torch.isfinite(a).all(), "non-finite values (a read of unwritten memory?)"
    for o in outs[1:]:
        for a, b in zip(first, o):
            if a is not None and a.numel():
                assert torch.equal(a, b), "the result depends on the thread schedule (a race or a missing barrier)"
    return first


def random_tree(n: int, rng: random.Random) -> list[int]:
    return [-1] + [j - 1 if rng.random() < 0.5 else rng.randrange(j) for j in range(1, n)]


def tree_neighbors(parents: list[int]) -> list[list[int]]:
    """Self + parent + children (MoDi's released neighbourhood), in a shuffled-but-fixed order per row."""
    rows = [[j] + ([p] if p >= 0 else []) for j, p in enumerate(parents)]
    for j, p in enumerate(parents):
        if p >= 0:
            rows[p].append(j)
    return rows


def pooling(n_fine: int, rng: random.Random, unread: bool) -> list[list[int]]:
    """Coarse -> fine groups; with `unread`, some fine entities belong to no group (nothing reads them)."""
    fine = list(range(n_fine))
    skip = set(rng.sample(fine[1:], k=max(1, n_fine // 4))) if unread and n_fine > 2 else set()
    groups, cur = [], []
    for f in fine:
        if f in skip:
            continue
        cur.append(f)
        if len(cur) >= rng.choice([1, 2, 3]):
            groups.append(cur)
            cur = []
    if cur:
        groups.append(cur)
    for g in groups[1:]:  # overlapping groups: a fine entity read by two coarse ones
        if rng.random() < 0.3 and g[0] - 1 not in skip and g[0] > 0:
            g.insert(0, g[0] - 1)
    return groups


class Problem:
    """Random inputs of one skeletal op in float64, already rounded to `dtype`."""

    def __init__(self, kind, mod="none", padding="zeros", U=3, bias=True, dtype=torch.float32, seed=0, B=2,
                 cin=3, cout=5, T=None, n=None, unread=False, single=False, act=False):
        rng = random.Random(seed)
        self.act = act
        g = torch.Generator().manual_seed(seed)
        self.kind, self.padding, self.dtype, self.U = kind, padding, dtype, U
        h = U // 2
        n = n or rng.randint(3, 7)
        if single:  # one output entity
            lists = [[0]] if kind == "conv" else [list(range(n))]
            n = 1 if kind == "conv" else n
        elif kind == "conv":
            lists = tree_neighbors(random_tree(n, rng))
        else:
            lists = pooling(n, rng, unread)
        topo = csr_from_lists(lists, n_in=n)
        self.index, self.offsets = topo.index, topo.offsets
        rows = len(lists)
        self.n_in, self.n_out = {"conv": (n, n), "down": (n, rows), "up": (rows, n)}[kind]
        if T is None:
            T = rng.randint(2 * h + 2, 36)  # rows longer than a warp (32) in about half the cases
        self.T = T
        self.t_out = {"conv": T, "down": T // 2, "up": 2 * T}[kind]
        nnz = self.index.numel()
        w_shape = (cin, nnz, cout, U) if kind == "up" else (cout, nnz, cin, U)

        def rnd(*shape, scale=1.0):
            return (torch.randn(*shape, generator=g, dtype=torch.float64) * scale).to(dtype).double()

        self.x = rnd(B, cin, self.n_in, T)
        self.w = rnd(*w_shape, scale=(cin * U * 2) ** -0.5)
        self.b = rnd(cout) if bias else None
        self.s = (1.0 + 0.5 * rnd(B, cin)).to(dtype).double() if "style" in mod else None
        self.demod = "demod" in mod
        self.d = self.demod_coefficients().to(dtype).double() if self.demod else None
        self.gy = rnd(B, cout, self.n_out, self.t_out)
        if act:  # within rounding of a kink either slope is right: no gradient flows there
            pre = self.pre(self.x, self.w, self.b, self.s, self.d)
            self.gy = torch.where(pre.abs() < 64 * torch.finfo(dtype).eps * pre.abs().max(), 0.0, self.gy)

    def demod_coefficients(self) -> torch.Tensor:
        """d[b, o, j] from the masked dense weight, independently of modi_ext.skeletal.ops (the reference's formula)."""
        n_dense = self.n_out if self.kind == "up" else self.n_in
        dense = reference.to_dense(self.w, self.index, self.offsets, n_dense)
        s = self.s if self.s is not None else torch.ones(1, dense.shape[0 if self.kind == "up" else 1],
                                                         dtype=torch.float64)
        if self.kind == "up":  # dense (Ci, Co, Ec, Ef, U): output entity Ef, input channel axis 0
            a = torch.einsum("bi,iocfu->bof", s.pow(2), dense.pow(2))
        else:  # dense (Co, Ci, Eo, Ei, U)
            a = torch.einsum("bi,oijnu->boj", s.pow(2), dense.pow(2))
        a = a.expand(self.x.shape[0], -1, -1)
        return torch.rsqrt(a + DEMOD_EPS)

    def ref(self, x, w, b, s, d):
        """y = d * A_W(x * s) + b (then the bias activation, with act), float64."""
        y = self.pre(x, w, b, s, d)
        return fused_leaky_relu(y, None) if self.act else y

    def pre(self, x, w, b, s, d):
        """y = d * A_W(x * s) + b, float64 (d and s independent inputs, as the kernels take them)."""
        args = (self.index, self.offsets)
        if self.kind == "up":
            y = reference.skeletal_up(x, w, None, *args, self.n_out, s, False, self.padding)
        else:
            f = reference.skeletal_conv if self.kind == "conv" else reference.skeletal_down
            y = f(x, w, None, *args, s, False, self.padding)
        if d is not None:
            y = y * d.unsqueeze(-1)
        return y + b.view(1, -1, 1, 1) if b is not None else y

    def cast(self, t):
        return None if t is None else t.to(self.dtype).contiguous()

    def forward(self, lib="modi_ext_emu"):
        o = ops(lib)
        a = [self.cast(t) for t in (self.x, self.w, self.b)]
        st, d = self.cast(self.s), self.cast(self.d)
        if self.kind == "up":
            return o.skeletal_up(*a, self.index, self.offsets, self.n_out, st, d, self.padding, self.act)
        f = o.skeletal_conv if self.kind == "conv" else o.skeletal_down
        return f(*a, self.index, self.offsets, st, d, self.padding, self.act)

    def backward(self, out, mask=(True, True, True, True), x=None, w=None, lib="modi_ext_emu"):
        x = self.cast(self.x) if x is None else x
        w = self.cast(self.w) if w is None else w
        return ops(lib).skeletal_backward(self.cast(self.gy), out, x, w, self.cast(self.b), self.index,
                                          self.offsets, self.cast(self.s), self.cast(self.d), self.padding,
                                          KIND_ID[self.kind], self.n_out, list(mask), self.act)


def close(got, want, dtype, what):
    assert got.shape == want.shape, f"{what}: shape {tuple(got.shape)} != {tuple(want.shape)}"
    got = got.double()
    assert torch.isfinite(got).all(), f"{what}: non-finite values (a read of unwritten memory?)"
    scale = max(want.abs().max().item(), 1e-3)
    err = (got - want).abs().max().item()
    assert err <= TOL[dtype] * scale, f"{what}: max error {err:.3g} > {TOL[dtype]:g} x {scale:.3g} ({dtype})"


def check_problem(p: Problem, backward=True, lib="modi_ext_emu"):
    """Forward and first-order backward of the kernels against the float64 reference, under both schedules."""
    y = schedules(lambda: (p.forward(lib),))[0]
    want = p.ref(p.x, p.w, p.b, p.s, p.d)
    close(y, want, p.dtype, f"{p.kind} forward")
    if p.demod and p.dtype == torch.float64 and not p.act:  # the coefficients are the reference's own demodulation
        if p.kind == "up":
            full = reference.skeletal_up(p.x, p.w, p.b, p.index, p.offsets, p.n_out, p.s, True, p.padding)
        else:
            f = reference.skeletal_conv if p.kind == "conv" else reference.skeletal_down
            full = f(p.x, p.w, p.b, p.index, p.offsets, p.s, True, p.padding)
        close(y, full, p.dtype, f"{p.kind} forward vs reference demodulate=True")
    if not backward:
        return
    leaves = [t.clone().requires_grad_(True) if t is not None else None for t in (p.x, p.w, p.b, p.s, p.d)]
    want_y = p.ref(*leaves)
    need = [t for t in leaves if t is not None]
    grads = dict(zip([i for i, t in enumerate(leaves) if t is not None],
                     torch.autograd.grad(want_y, need, p.gy)))
    got = schedules(lambda: p.backward(y, lib=lib))
    for i, name in enumerate(("x", "weight", "bias", "style", "scale")):
        if i in grads:
            close(got[i], grads[i], p.dtype, f"{p.kind} grad {name}")
        else:
            assert got[i].numel() == 0, f"{p.kind}: grad {name} returned for an absent input"


# ------------------------------------------------------------------------------------------------ skeletal ops
@pytest.mark.parametrize("padding", ("zeros", "reflect"))
@pytest.mark.parametrize("mod", MODS)
@pytest.mark.parametrize("kind", KINDS)
def test_every_option_fp32(kind, mod, padding):
    """conv/down/up x modulation x padding x U in {1, 3, 5} x bias, forward and first-order backward."""
    for k, (U, bias) in enumerate(itertools.product((1, 3, 5), (False, True))):
        seed = zlib.crc32(f"{kind}/{mod}/{padding}/{U}/{bias}".encode()) % 10_000
        p = Problem(kind, mod, padding, U, bias, torch.float32, seed=seed, unread=k % 2 == 1)
        check_problem(p)


@pytest.mark.parametrize("dtype", DTYPES, ids=str)
@pytest.mark.parametrize("kind", KINDS)
def test_dtypes(kind, dtype):
    """Every dtype: modulated + demodulated and plain, both paddings, narrow (BM = 32) tiles."""
    for k, (mod, padding) in enumerate((("style_demod", "reflect"), ("none", "zeros"), ("style", "zeros"))):
        check_problem(Problem(kind, mod, padding, U=3, bias=k != 1, dtype=dtype, seed=11 + k, unread=True))


@pytest.mark.parametrize("dtype", DTYPES, ids=str)
@pytest.mark.parametrize("mod", MODS)
@pytest.mark.parametrize("kind", KINDS)
def test_bias_activation_epilogue(kind, mod, dtype):
    """act: the bias activation in the GEMM epilogue and its backward prologue (every gradient, the scale's from the
    pre-activation recovered off y), against the float64 reference followed by modi_ext.act."""
    seed = zlib.crc32(f"act/{kind}/{mod}/{dtype}".encode()) % 10_000
    check_problem(Problem(kind, mod, "zeros", 3, True, dtype, seed=seed, unread=kind != "conv", act=True))


@pytest.mark.parametrize("dtype", DTYPES, ids=str)
@pytest.mark.parametrize("kind", KINDS)
def test_multi_tile_split_k(kind, dtype):
    """64-row tiles, several output-channel / column / reduction tiles, B*T > 256 (split-K weight gradient)."""
    T = {"conv": 100, "down": 200, "up": 100}[kind]
    p = Problem(kind, "style_demod", "reflect", U=3, bias=True, dtype=dtype, seed=5, B=3, cin=34, cout=70, T=T, n=4)
    check_problem(p)


@pytest.mark.parametrize("sms", (1, 1000))
def test_split_k_by_multiprocessor_count(sms):
    """The weight-gradient split follows the SM count the host code sees: none with 1 SM; 27 splits with a ragged
    last one (B*T = 1800, chunks of 68) with 1000 SMs (csrc/skeletal/launch_plan.h)."""
    p = Problem("conv", "style", "zeros", U=3, bias=False, seed=9, B=2, cin=4, cout=6, T=900, n=3)
    with sm_count(sms):
        before = sum(n for k, n in EMU.launch_counts().items() if k.startswith("split_reduce_kernel"))
        check_problem(p)
        after = sum(n for k, n in EMU.launch_counts().items() if k.startswith("split_reduce_kernel"))
    assert (after > before) == (sms > 1)


@pytest.mark.parametrize("kind", KINDS)
def test_single_entity_csr(kind):
    for dtype in (torch.float32, torch.float16):
        check_problem(Problem(kind, "style_demod", "zeros", U=5, dtype=dtype, seed=3, single=True, n=4))


def test_topology_is_built_once_per_layer_and_again_after_an_in_place_edit():
    """The device CSR of a layer's maps is cached (cuda.cu TopologyCache): calls on the same maps launch no topology
    kernel; an in-place edit of the index (a new version) rebuilds it, and the results follow the edited map."""
    def builds():
        return EMU.launch_counts().get("topology_kernel", 0)

    p = Problem("conv", "style", "zeros", 3, True, torch.float64, seed=23)
    check_problem(p)
    before = builds()
    for _ in range(3):
        p.backward(p.forward())
    assert builds() == before
    rows = [p.index[int(a):int(b)].flip(0) for a, b in zip(p.offsets[:-1], p.offsets[1:])]
    assert any(len(r) > 1 for r in rows)
    p.index.copy_(torch.cat(rows))  # the same shape and storage, another map: a new version
    check_problem(p)
    assert builds() == before + 1


def test_unread_fine_entities_get_bias_and_no_gradient():
    """A pooling map that leaves fine entities unread: up writes bias there, down's input gradient is zero."""
    p = Problem("up", "style", "zeros", U=3, seed=8, unread=True, n=8)
    unread = sorted(set(range(p.n_out)) - set(p.index.tolist()))
    assert unread, "the pooling map must leave a fine entity unread"
    y = schedules(lambda: (p.forward(),))[0]
    assert torch.equal(y[:, :, unread], p.cast(p.b).view(1, -1, 1, 1).expand_as(y[:, :, unread]))
    q = Problem("down", "none", "zeros", U=3, seed=8, unread=True, n=8)
    gx = schedules(lambda: q.backward(q.forward()))[0]
    cold = sorted(set(range(q.n_in)) - set(q.index.tolist()))
    assert cold and torch.equal(gx[:, :, cold], torch.zeros_like(gx[:, :, cold]))


@pytest.mark.parametrize("dtype", (torch.float64, torch.float32, torch.bfloat16), ids=str)
@pytest.mark.parametrize("kind", KINDS)
def test_gradfix_partial_backwards(kind, dtype):
    """The two partial backwards modi_ext.skeletal.gradfix builds second-order gradients from: the input gradient
    with no x values (gradfix passes a shape-only tensor: NaN here, so a read of it shows) and the weight gradient with
    no weight values, each against the reference's gradient of the unmodulated op."""
    p = Problem(kind, "none", "reflect", U=3, bias=False, dtype=dtype, seed=21, B=2, cin=6, cout=9, T=70)
    xl = p.x.clone().requires_grad_(True)
    wl = p.w.clone().requires_grad_(True)
    gx_ref, gw_ref = torch.autograd.grad(p.ref(xl, wl, None, None, None), (xl, wl), p.gy)
    gy = p.cast(p.gy)
    nan_x = torch.full_like(p.cast(p.x), float("nan"))
    nan_w = torch.full_like(p.cast(p.w), float("nan"))
    gx = schedules(lambda: p.backward(gy, (True, False, False, False), x=nan_x))[0]
    gw = schedules(lambda: p.backward(gy, (False, True, False, False), w=nan_w))[1]
    close(gx, gx_ref, dtype, f"{kind} grad_input (gradfix)")
    close(gw, gw_ref, dtype, f"{kind} grad_weight (gradfix)")


# ------------------------------------------------------------------------------------------------ errors
def test_malformed_csr_is_a_device_assert_reported_as_an_error():
    """On a GPU this is a device-side assert that poisons the context; the emulator names it."""
    p = Problem("conv", seed=1, n=4)
    bad = p.index.clone()
    bad[1] = 99
    with pytest.raises(RuntimeError, match=r"topology_kernel.*index holds an entity out of range"):
        ops().skeletal_conv(p.cast(p.x), p.cast(p.w), None, bad, p.offsets, None, None, "zeros")


def test_rejects_cuda_like_misuse():
    p = Problem("conv", seed=1)
    with pytest.raises(RuntimeError, match="padding_mode"):
        ops().skeletal_conv(p.cast(p.x), p.cast(p.w), None, p.index, p.offsets, None, None, "circular")


# ------------------------------------------------------------------------------------------------ FK
# Launch plans of fk/cuda.cu's plan_launch (48 KB of shared walk state): float J <= 13 -> 128 threads,
# <= 27 -> 64, <= 54 -> 32, else the global workspace; double halves the limits.
FK_PLANS = {"smem128": (8, 4), "smem64": (20, 10), "smem32": (40, 20), "global": (60, 30)}


def fk_problem(J: int, N: int, dtype, seed: int):
    rng = random.Random(seed)
    g = torch.Generator().manual_seed(seed)
    parents = random_tree(J, rng)
    q = torch.randn(N, J, 4, generator=g, dtype=torch.float64)
    q = (q / q.norm(dim=-1, keepdim=True)).to(dtype).double()
    off = torch.randn(J, 3, generator=g, dtype=torch.float64).to(dtype).double()
    root = torch.randn(N, 3, generator=g, dtype=torch.float64).to(dtype).double()
    return parents, q, off, root, g


@pytest.mark.parametrize("dtype", DTYPES, ids=str)
@pytest.mark.parametrize("plan", sorted(FK_PLANS))
def test_fk_launch_plans(plan, dtype):
    J = FK_PLANS[plan][1 if dtype == torch.float64 else 0]
    N = 70  # a partial block and a partial warp
    parents, q, off, root, g = fk_problem(J, N, dtype, seed=J)
    cast = lambda t: t.to(dtype).contiguous()  # noqa: E731
    pos, gq = schedules(lambda: ops().fk(cast(q), cast(off), parents, cast(root)))
    ql, ol, rl = (t.clone().requires_grad_(True) for t in (q, off, root))
    want_pos, want_gq = fk_reference(ql, ol, parents, rl, return_rotations=True)
    close(pos, want_pos.detach(), dtype, f"fk positions ({plan})")
    close(gq, want_gq.detach(), dtype, f"fk rotations ({plan})")
    gp = torch.randn(N, J, 3, generator=g, dtype=torch.float64).to(dtype).double()
    gg = torch.randn(N, J, 4, generator=g, dtype=torch.float64).to(dtype).double()
    for with_rot, off_grad in ((True, True), (False, False), (False, True)):
        outs = (want_pos, want_gq) if with_rot else (want_pos,)
        seeds = (gp, gg) if with_rot else (gp,)
        want = torch.autograd.grad(outs, (ql, rl, ol), seeds, retain_graph=True)
        got = schedules(lambda: ops().fk_backward(cast(gp), cast(gg) if with_rot else None, cast(q), gq,
                                                  cast(off), parents, off_grad))
        close(got[0], want[0], dtype, f"fk grad local_quats ({plan})")
        close(got[1], want[1], dtype, f"fk grad root ({plan})")
        if off_grad:
            close(got[2], want[2], dtype, f"fk grad offsets ({plan})")
        else:
            assert torch.equal(got[2], torch.zeros_like(got[2]))


# ------------------------------------------------------------------------------------------------ emulator checks
def test_emulated_ops_are_cpu_only_and_in_their_own_namespace():
    assert EMU.LIBRARY == "modi_ext_emu" and EMU.injected_defect() == ""
    for op in ("skeletal_conv", "skeletal_down", "skeletal_up", "skeletal_backward", "fk", "fk_backward"):
        name = f"modi_ext_emu::{op}"
        assert torch._C._dispatch_has_kernel_for_dispatch_key(name, "CPU")
        assert not torch._C._dispatch_has_kernel_for_dispatch_key(name, "CUDA")


@pytest.mark.parametrize("case, message", [
    ("divergent_barrier", r"__syncthreads\(\) at line \d+ reached by 16 of 32 threads; 16 exited"),
    ("shared_oob", r"thread \(31, 0, 0\): shared array `s`: index 32 out of range \[0, 32\)"),
    ("warp_exits", r"warp 0 waits forever in a warp intrinsic .* only lanes 0xffff arrived"),
    ("dynamic_overflow", r"a write outside the 28 bytes of dynamic shared memory"),
])
def test_emulator_reports_rule_violations(case, message):
    """What a GPU would not report (or would report as a hang / corruption) is a RuntimeError naming the rule."""
    threads = 8 if case == "dynamic_overflow" else 32
    with pytest.raises(RuntimeError, match=message):
        ops().emu_selftest(case, threads)


def test_emulator_poisons_shared_memory_and_permutes_threads():
    assert torch.isnan(ops().emu_selftest("unwritten_shared", 32)[:32]).all()
    det = torch.are_deterministic_algorithms_enabled()
    assert torch.isnan(ops().emu_selftest("poisoned_empty", 16)).all()  # outputs / workspaces of the host code
    assert (ops().emu_selftest("poisoned_empty_int", 16) == torch.iinfo(torch.int32).max).all()
    assert torch.are_deterministic_algorithms_enabled() == det, "the poison scope must restore torch's state"
    results = set()
    for seed in (0,) + SEEDS + (1, 2, 3):
        EMU.set_schedule_seed(seed)
        results.add(tuple(ops().emu_selftest("race", 16)[:16].tolist()))
    EMU.set_schedule_seed(0)
    assert len(results) >= 3, "a missing barrier must change the result under different schedules"


def test_emulator_warp_intrinsics_and_atomics():
    n = 64
    EMU.set_schedule_seed(SEEDS[1])
    out = ops().emu_selftest("intrinsics", n)
    EMU.set_schedule_seed(0)
    lane = torch.arange(n) % 32
    ballot = sum(1 << k for k in range(0, 32, 3))
    want = torch.stack([lane ^ 5, torch.where(lane >= 3, lane - 3, lane), torch.where(lane + 3 < 32, lane + 3, lane),
                        torch.full((n,), 7), torch.full((n,), ballot & 0xFFFF), torch.full((n,), ballot >> 16),
                        torch.full((n,), 1), torch.full((n,), sum(range(32)))], 1).float()
    assert torch.equal(out[:8 * n].view(n, 8), want)
    assert out[8 * n].item() == n  # one atomicAdd per thread


# ------------------------------------------------------------------------------------------------ demodulation
@pytest.mark.parametrize("dtype", DTYPES, ids=str)
@pytest.mark.parametrize("case", ["conv.plain", "conv.style", "up.plain", "up.style"])
def test_demod_kernels(case, dtype):
    """csrc/demod/cuda.cu against the float64 torch form, forward and both gradients, schedule-independent."""
    from modi_ext.runtime import payload

    (c,) = [c for c in payload.DEMOD_CASES if c.name == f"demod.{case}"]
    p = payload.demod_inputs(c, dtype)
    out = schedules(lambda: (lambda d, g: (d,) + tuple(g))(*payload._demod_call(payload_table(), c, p, "cpu", dtype)))
    want_d, want_g = payload.demod_oracle(c, p)
    close(out[0], want_d, dtype, f"{case} d")
    for got, want, name in zip(out[1:], want_g, ("weight", "style")):
        close(got, want, dtype, f"{case} grad {name}")


def test_demod_kernels_read_no_map_values_on_the_host_and_skip_bad_entries():
    """No host read of index/offsets (a sync on a GPU): an out-of-range up index is skipped on the device, so its
    pair adds nothing, rather than read through."""
    from modi_ext.runtime import payload

    c = [c for c in payload.DEMOD_CASES if c.name == "demod.up.style"][0]
    p = payload.demod_inputs(c, torch.float64)
    bad = p["index"].clone()
    bad[0] = 99
    d = ops().demod_scale(p["w"], p["s"], bad, p["offsets"], True, p["n_out"], DEMOD_EPS)
    w = p["w"].clone()
    w[:, 0] = 0  # the skipped pair
    want = ops().demod_scale(w, p["s"], p["index"], p["offsets"], True, p["n_out"], DEMOD_EPS)
    assert torch.equal(d, want)


@pytest.mark.parametrize("defect", ["off_by_one", "wrong_scale"])
def test_demod_planted_faults_are_caught(defect):
    """off_by_one drops the last tap of every squared-weight sum (forward and both gradients); wrong_scale scales
    the weight gradient by 1 + 2^-9.  Both stay finite: the float64 comparison catches them, and so does the
    self-check, which then names the demod op."""
    from modi_ext.runtime import payload, selfcheck

    c = [c for c in payload.DEMOD_CASES if c.name == "demod.conv.style"][0]
    assert max(payload.run_case(payload_table(), c, "cpu", torch.float32)) < payload.TOL[torch.float32]
    with injected(defect):
        fwd, bwd = payload.run_case(payload_table(), c, "cpu", torch.float32)
        assert max(fwd, bwd / payload.GRAD_FACTOR) > payload.TOL[torch.float32], (fwd, bwd)
        res = selfcheck.run("cpu", torch.float32, lib="modi_ext_emu")
    assert not res["ok"] and "demod_scale" in res["errors"], res["errors"]


def test_bias_activation_planted_fault_is_caught():
    """wrong_slope: the activation's backward prologue scales the negative side's slope by 1 + 2^-9 -- finite, so only
    the float64 comparison sees it, in the suite's check and in the self-check (its act=True cases)."""
    from modi_ext.runtime import selfcheck

    p = Problem("conv", "style_demod", "zeros", 3, True, torch.float32, seed=17, act=True)
    check_problem(p)
    with injected("wrong_slope"):
        with pytest.raises(AssertionError, match="grad"):
            check_problem(p)
        res = selfcheck.run("cpu", torch.float32, lib="modi_ext_emu")
    assert not res["ok"] and "skeletal_conv" in res["errors"], res["errors"]


def payload_table():
    from modi_ext.runtime import kernels

    return kernels.kernel_table("modi_ext_emu")


# ------------------------------------------------------------------------------------------------ injected defects
@pytest.mark.parametrize("defect", ("drop_sync", "off_by_one"))
def test_injected_defect_is_caught(defect):
    """The harness can fail: each injected defect (the emulated module's run-time switch) fails check_problem, while
    the clean kernels pass the same case.  drop_sync: the first __syncthreads() of row_gemm_kernel is gone, so
    threads read the shared stage before the others stored it (NaN); off_by_one: one column of the staged operand
    is never written (NaN) and the others are shifted."""
    p = Problem("conv", "style", "reflect", U=3, seed=4, B=2, cin=5, cout=6, T=40)
    check_problem(p, backward=False)  # the clean kernels pass the same case
    with injected(defect), pytest.raises(AssertionError, match="non-finite"):
        check_problem(p, backward=False)
    check_problem(p, backward=False)  # and again once the defect is off


def test_injected_finite_wrong_value_is_caught_by_the_tolerance():
    """wrong_scale (a run-time defect): style_finish_kernel scales the style gradient by 1 + 2^-9.  Every value stays
    finite -- no NaN poison to trip over -- so only the tolerance against the float64 reference can see it: the
    suite's check does, and so does the first-use self-check (which then refuses the kernels)."""
    from modi_ext.runtime import selfcheck

    p = Problem("conv", "style", "reflect", U=3, seed=4, B=2, cin=5, cout=6, T=40)
    check_problem(p)  # the clean kernels pass the same case
    with pytest.raises(ValueError, match="unknown defect"):
        EMU.set_injected_defect("no_such_defect")
    with injected("wrong_scale"):
        assert EMU.injected_defect() == "wrong_scale"
        got = p.backward(p.forward())
        assert all(bool(torch.isfinite(t).all()) for t in got if t.numel()), "the defect must stay finite"
        with pytest.raises(AssertionError, match=r"conv grad style: max error .* > 5e-05"):
            check_problem(p)
        res = selfcheck.run("cpu", torch.float32, lib="modi_ext_emu")
    assert not res["ok"] and "backward error" in res["errors"]["skeletal_conv"], res
    assert EMU.injected_defect() == ""
    check_problem(p)


# ------------------------------------------------------------------------------------------------ build defects
def _setup_helpers(*names):
    """Functions / constants of setup.py, read from its source (importing it would run setup())."""
    import ast

    ns: dict = {}
    for node in ast.parse((REPO / "setup.py").read_text()).body:
        targets = [t.id for t in getattr(node, "targets", []) if isinstance(t, ast.Name)]
        if getattr(node, "name", None) in names or set(targets) & set(names):
            exec(compile(ast.Module([node], []), "setup.py", "exec"), ns)
    missing = [n for n in names if n not in ns]
    assert not missing, f"setup.py lacks {missing}"
    return ns


def test_setup_defaults_the_cuda_arch_list_without_a_visible_gpu(monkeypatch):
    """A CUDA build where no GPU is visible: torch's arch detection raises IndexError; setup.py must default the
    list (and keep a user's list, and let torch detect the visible GPUs otherwise)."""
    from torch.utils import cpp_extension

    ns = _setup_helpers("_default_cuda_arch_list", "DEFAULT_CUDA_ARCH_LIST")
    pick = ns["_default_cuda_arch_list"]
    assert pick(None, False) == "8.0;9.0+PTX" and pick("", False) == "8.0;9.0+PTX"
    assert pick("8.6", False) is None and pick(None, True) is None
    if torch.cuda.device_count() == 0:
        monkeypatch.delenv("TORCH_CUDA_ARCH_LIST", raising=False)
        with pytest.raises(IndexError):  # the defect the default avoids
            cpp_extension._get_cuda_arch_flags()
    monkeypatch.setenv("TORCH_CUDA_ARCH_LIST", pick(None, False))
    flags = cpp_extension._get_cuda_arch_flags()
    assert {"-gencode=arch=compute_80,code=sm_80", "-gencode=arch=compute_90,code=sm_90",
            "-gencode=arch=compute_90,code=compute_90"} <= set(flags)


def test_cuda_compile_check_uses_the_flags_of_setup_py():
    """.ci/cuda_compile_check (run in CI with nvcc) must compile what setup.py builds: torch's nvcc flags, the arch
    flags, setup.py's own nvcc flags, and no -w.  Runs the script's flag computation, not nvcc."""
    import subprocess
    import sys

    from torch.utils import cpp_extension

    text = (REPO / ".ci" / "cuda_compile_check").read_text()
    assert not re.search(r"(^|\s)-w(\s|$)", text), "warnings must stay visible"
    script = re.search(r"python3 - <<'EOF'\n(.*?)\nEOF", text, re.S)
    assert script, "the check must derive its flags from setup.py"
    env = {k: v for k, v in os.environ.items() if k != "TORCH_CUDA_ARCH_LIST"}
    flags = subprocess.run([sys.executable, "-c", script.group(1)], cwd=REPO, env=env, check=True,
                           capture_output=True, text=True).stdout.split()
    ours = _setup_helpers("_nvcc_flags")["_nvcc_flags"](["-O3"])
    for f in cpp_extension.COMMON_NVCC_FLAGS + ours + ["-gencode=arch=compute_90,code=compute_90", "-std=c++20"]:
        assert f in flags, f"{f} missing from the compile check's nvcc flags"


# ------------------------------------------------------------------------------------------------ coverage
def _global_kernels() -> set[str]:
    names = set()
    for src in [*(REPO / "csrc").glob("*/*.cu"), *(REPO / "csrc").glob("*/*.cuh")]:
        names.update(re.findall(r"__global__\s+void\s+(?:__launch_bounds__\([^)]*\)\s+)?(\w+)", src.read_text()))
    return names


EMU_TYPES = {torch.float64: "double", torch.float32: "float", torch.float16: "c10::Half",
             torch.bfloat16: "c10::BFloat16"}


# Opt-in kernels (off unless a switch turns them on, so neither the payload nor the self-check launches them) and
# their instantiations: the tensor-core GEMMs, MODI_EXT_CUDA_MMA=1 (test_cuda_emulated_mma*.py run them): bf16, and
# float32 on TF32 -- the row / transposed GEMM with and without the blur, the weight gradient with and without it.
OPT_IN_KERNELS = {"mma_gemm_kernel", "mma_wgrad_kernel"}
OPT_IN = ({f"mma_gemm_kernel<{t}, {tr}, {blur}>" for t in ("c10::BFloat16", "float")
           for tr, blur in itertools.product(("false", "true"), repeat=2)}
          | {f"mma_wgrad_kernel<{t}, {blur}>" for t in ("c10::BFloat16", "float") for blur in ("false", "true")})


def _expected_instantiations(dtypes=DTYPES) -> set[str]:
    """The kernel instantiations of the default paths of csrc/<op>/cuda.cu, written out: 24 per dtype plus the
    topology kernel (OPT_IN aside)."""
    want = {"topology_kernel"}
    for t in (EMU_TYPES[d] for d in dtypes):
        for k, bm, flag in itertools.product(("row_gemm_kernel", "tr_gemm_kernel", "wgrad_kernel"), (32, 64),
                                             ("false", "true")):
            want.add(f"{k}<{t}, {bm}, {flag}>")
        for k in ("split_reduce_kernel", "style_finish_kernel", "scale_grad_kernel", "act_backward_kernel",
                  "fk_offsets_reduce_kernel",
                  "demod_forward_kernel", "demod_style_grad_kernel", "demod_weight_grad_kernel"):
            want.add(f"{k}<{t}>")
        for k, flag in itertools.product(("fk_forward_kernel", "fk_backward_kernel"), ("false", "true")):
            want.add(f"{k}<{t}, {flag}>")
    return want


def _cuda_instantiations(names) -> set[str]:
    """The entries of ``names`` that are csrc/<op>/cuda.cu kernels (not the emulator's own self-test kernels)."""
    kernels = _global_kernels()
    return {k for k in names if re.match(r"\w+", k).group(0) in kernels}


def _launched_since(before: dict) -> set[str]:
    after = EMU.launch_counts()
    return _cuda_instantiations(k for k, n in after.items() if n > before.get(k, 0))


def test_the_emulator_registers_every_instantiation():
    """Each instantiation some host code can launch registers itself at load time (cuda_emu.h KernelRegistration):
    the registry is exactly the list written out here (97 default-path ones and the opt-in tensor-core GEMMs' 12,
    109 today) -- the yardstick of the payload test below."""
    registered = _cuda_instantiations(EMU.registered_kernels())
    want = _expected_instantiations() | OPT_IN
    assert registered == want, sorted(registered ^ want)
    assert len(registered) == 1 + 24 * len(DTYPES) + len(OPT_IN)
    assert {"divergent_barrier_kernel", "race_kernel"} <= set(EMU.registered_kernels())  # self-test kernels too


def test_the_shared_payload_launches_every_instantiation():
    """modi_ext.runtime.payload (what validate's sanitizer steps, the GPU tests and the self-check run) launches every
    kernel instantiation the emulator registered but the opt-in ones (OPT_IN: their switches are off), in
    fp32/fp64/fp16/bf16, and matches the float64 oracle."""
    from modi_ext.runtime import kernels, payload

    before = EMU.launch_counts()
    res = payload.run(kernels.kernel_table("modi_ext_emu"), "cpu", payload.DTYPES)
    assert not res["errors"], res["errors"]
    launched = _launched_since(before)
    registered = _cuda_instantiations(EMU.registered_kernels()) - OPT_IN
    assert launched == registered, f"never launched by the payload: {sorted(registered - launched)}"
    assert len(launched) == 97


@pytest.mark.parametrize("dtype", DTYPES, ids=str)
def test_selfcheck_launches_every_instantiation_of_its_dtype(dtype):
    """The first-use self-check (modi_ext.runtime.selfcheck, the payload against the float64 oracle) on the emulated
    kernels: it passes, and it launched all 24 instantiations of its dtype and the topology kernel -- the 64-row
    tiles, split-K, FK offsets gradients on every plan and the demodulation coefficients that training runs
    included.  Its first-use time on this
    CPU is printed (-s), not asserted (the machine may be shared)."""
    from modi_ext.runtime import selfcheck

    before = EMU.launch_counts()
    t0 = time.perf_counter()
    res = selfcheck.run("cpu", dtype, lib="modi_ext_emu")
    seconds = time.perf_counter() - t0
    assert res["ok"], res["errors"]
    assert set(res["max_error"]) == {"skeletal_conv", "skeletal_down", "skeletal_up", "fk", "demod_scale"}
    assert _launched_since(before) == _expected_instantiations((dtype,))
    print(f"\nself-check {dtype} on the emulated kernels: {seconds:.2f} s, {res['cases']} cases")


def test_every_kernel_instantiation_ran(request):
    """Runs last: every __global__ kernel of csrc/*/cuda.cu but the opt-in ones, in every dtype and tile/blur
    variant, was run above."""
    defined = {n for n in dir(request.module) if n.startswith("test_")}
    selected = {i.originalname for i in request.session.items if i.module is request.module}
    if not defined <= selected:
        pytest.skip("the launch counts are accumulated over the whole module; run all of it for this check")
    counts = EMU.launch_counts()
    ran = {re.match(r"\w+", k).group(0) for k in counts}
    default = _global_kernels() - OPT_IN_KERNELS  # the opt-in ones: test_cuda_emulated_mma.py
    assert default <= ran, f"kernels never executed: {sorted(default - ran)}"
    missing = sorted(_expected_instantiations() - set(counts))
    assert not missing, f"kernel instantiations never executed: {missing}"
