"""modi_ext dispatch: the dense path, per-device kernel availability, first-use self-check, auto timing, and the
CUDA-path defects of issue 20 that can be shown on the CPU (autocast, fp16 demodulation, FK double backward, host
CSR validation, deterministic demodulation sums, torch.compile without a traced probe)."""
from __future__ import annotations

import types
import warnings

import pytest
import torch

import modi_ext
from modi_ext import HAS_EXT
from modi_ext.demod.reference import demod_coefficients
from modi_ext.fk import fk, fk_reference
from modi_ext.layers import ModulatedSkeletalConv
from modi_ext.runtime import dispatch, selfcheck
from modi_ext.skeletal import checks, dense, ops, reference
from modi_ext.csr import csr_from_lists

pytestmark = pytest.mark.usefixtures("one_torch_thread")
needs_ext = pytest.mark.skipif(not HAS_EXT, reason="modi_ext C++ extension not built")

NEIGHBORS = [[0, 1], [0, 1, 2, 4], [1, 2, 3], [2, 3], [1, 4]]
POOLING = [[0, 1], [1, 2, 3], [4]]
PARENTS = [-1, 0, 1, 2, 1, 4]


@pytest.fixture(autouse=True)
def _fresh_dispatch(monkeypatch):
    monkeypatch.delenv("MODI_EXT_IMPL", raising=False)
    monkeypatch.delenv("MODI_EXT_SELFCHECK", raising=False)
    dispatch.reset()
    yield
    dispatch.reset()


def problem(kind: str, dtype=torch.float64, seed=0, style=True, demod=True, padding="zeros", B=2, T=8):
    g = torch.Generator().manual_seed(seed)
    lists = NEIGHBORS if kind == "conv" else POOLING
    topo = csr_from_lists(lists, n_in=5)
    cin, cout = 3, 4
    if kind == "up":
        x = torch.randn(B, cin, topo.n_out, T, generator=g, dtype=dtype)
        w = torch.randn(cin, topo.nnz, cout, 3, generator=g, dtype=dtype) * 0.4
    else:
        x = torch.randn(B, cin, 5, T, generator=g, dtype=dtype)
        w = torch.randn(cout, topo.nnz, cin, 3, generator=g, dtype=dtype) * 0.4
    b = torch.randn(cout, generator=g, dtype=dtype)
    s = (1 + 0.3 * torch.randn(B, cin, generator=g, dtype=dtype)) if style else None
    return dict(kind=kind, x=x, w=w, b=b, s=s, idx=topo.index, off=topo.offsets, demod=demod, padding=padding)


def call(mod, p, x=None, w=None, b=None, s=None):
    x = p["x"] if x is None else x
    w = p["w"] if w is None else w
    b = p["b"] if b is None else b
    s = p["s"] if s is None else s
    if mod is ops:
        kw = dict(style=s, demodulate=p["demod"], padding_mode=p["padding"])
        if p["kind"] == "up":
            return ops.skeletal_up(x, w, b, p["idx"], p["off"], 5, **kw)
        return (ops.skeletal_conv if p["kind"] == "conv" else ops.skeletal_down)(x, w, b, p["idx"], p["off"], **kw)
    if p["kind"] == "up":
        return mod.skeletal_up(x, w, b, p["idx"], p["off"], 5, s, p["demod"], p["padding"])
    fn = mod.skeletal_conv if p["kind"] == "conv" else mod.skeletal_down
    return fn(x, w, b, p["idx"], p["off"], s, p["demod"], p["padding"])


def wrong_kernel(name: str):
    """A kernel that runs but is off by a little: what a miscompiled or mis-targeted GPU build might do."""
    real = dispatch.KERNELS[name]
    return lambda *a: real(*a) * 1.01 + 1e-3


def forbid_kernels(monkeypatch):
    for name in ("skeletal_conv", "skeletal_down", "skeletal_up", "fk"):
        monkeypatch.setitem(dispatch.KERNELS, name, lambda *a, n=name: pytest.fail(f"kernel {n} was called"))


# ------------------------------------------------------------------------------------------------ the dense path
@pytest.mark.parametrize("kind", ["conv", "down", "up"])
@pytest.mark.parametrize("style,demod", [(False, False), (True, False), (True, True), (False, True)])
@pytest.mark.parametrize("padding", ["zeros", "reflect"])
def test_dense_matches_reference(kind, style, demod, padding):
    p = problem(kind, style=style, demod=demod, padding=padding)
    torch.testing.assert_close(call(dense, p), call(reference, p), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("kind", ["conv", "down", "up"])
def test_dense_gradgradcheck(kind):
    p = problem(kind, B=1, T=6)
    leaves = [p[k].clone().requires_grad_() for k in ("x", "w", "b", "s")]
    torch.autograd.gradgradcheck(lambda x, w, b, s: call(dense, p, x, w, b, s), leaves)


@pytest.mark.parametrize("kind", ["conv", "down", "up"])
def test_impl_dense_calls_no_kernel_and_matches(monkeypatch, kind):
    monkeypatch.setenv("MODI_EXT_IMPL", "dense")
    forbid_kernels(monkeypatch)
    p = problem(kind)
    torch.testing.assert_close(call(ops, p), call(reference, p), rtol=1e-12, atol=1e-12)


def _largest_tensor_made(fn) -> int:
    """numel of the largest tensor any aten op produces while ``fn`` runs."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class Sizes(TorchDispatchMode):
        top = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            out = func(*args, **(kwargs or {}))
            for t in out if isinstance(out, (tuple, list)) else (out,):
                if isinstance(t, torch.Tensor):
                    Sizes.top = max(Sizes.top, t.numel())
            return out

    with Sizes():
        fn()
    return Sizes.top


@pytest.mark.parametrize("kind", ["conv", "up"])
def test_dense_builds_no_per_sample_weight(kind):
    # one shared weight for the whole batch: nothing the size of B x (dense weight) is ever formed (the grouped
    # reference forms exactly that, which shows the measurement can tell them apart)
    p = problem(kind, B=7, T=2)
    per_sample = 7 * 3 * 4 * 5 * (5 if kind == "conv" else 3) * 3  # B * Cout * Cin * E_out * E_in * U
    assert _largest_tensor_made(lambda: call(dense, p)) < per_sample / 2  # activations, the shared weight
    assert _largest_tensor_made(lambda: call(reference, p)) >= per_sample


# ------------------------------------------------------------------------------------------------ per-device builds
def test_cuda_tensor_on_a_build_without_cuda_kernels_routes_to_dense():
    # torch here is CPU-only, so this build has no CUDA kernels: the routing of a CUDA tensor is decided per device
    fake_cuda = types.SimpleNamespace(device=torch.device("cuda", 0), dtype=torch.float32)
    assert not dispatch.kernels_built("cuda")
    assert dispatch.route("skeletal_conv", fake_cuda) == "dense"
    assert dispatch.route("fk", fake_cuda, family="fk") == "dense"
    if HAS_EXT:
        assert dispatch.kernels_built("cpu")
        assert modi_ext.impl_choice() == "ext"  # the device-blind answer the ops used to follow


@needs_ext
def test_forced_ext_on_a_device_without_kernels_is_one_clear_error(monkeypatch):
    monkeypatch.setenv("MODI_EXT_IMPL", "ext")
    fake_cuda = types.SimpleNamespace(device=torch.device("cuda", 0), dtype=torch.float32)
    with pytest.raises(RuntimeError, match="no CUDA kernels for skeletal_conv"):
        dispatch.route("skeletal_conv", fake_cuda)


@needs_ext
@pytest.mark.parametrize("kind", ["conv", "down", "up"])
def test_public_ops_follow_the_per_device_answer(monkeypatch, kind):
    # simulate a build whose CPU part lacks the kernels: the public ops must take the dense path, not crash
    monkeypatch.setitem(dispatch._built, ("cpu", "skeletal"), False)
    monkeypatch.setitem(dispatch._built, ("cpu", "fk"), False)
    forbid_kernels(monkeypatch)
    p = problem(kind)
    torch.testing.assert_close(call(ops, p), call(reference, p), rtol=1e-12, atol=1e-12)
    q, off, root = fk_inputs()
    torch.testing.assert_close(fk(q, off, PARENTS, root), fk_reference(q, off, PARENTS, root))


@needs_ext
def test_kernel_probe_runs_once_per_device_type(monkeypatch):
    calls = []
    real = torch._C._dispatch_has_kernel_for_dispatch_key
    monkeypatch.setattr(torch._C, "_dispatch_has_kernel_for_dispatch_key",
                        lambda op, key: calls.append((op, key)) or real(op, key))
    p = problem("conv")
    q, off, root = fk_inputs()
    for _ in range(3):
        call(ops, p)
        fk(q, off, PARENTS, root)
    ops_probed = sorted({op for op, _ in calls})
    assert len(calls) == len(ops_probed) == 8, calls  # 4 skeletal + 2 FK + 2 demod ops, each probed exactly once
    assert {key for _, key in calls} == {"CPU"}


@needs_ext
def test_fk_compiles_fullgraph_with_the_probe_not_yet_cached():
    # the probe used to run per call and dynamo traced it (a graph break on CUDA); now it is a cached constant
    torch._dynamo.reset()
    dispatch.reset()
    q, off, root = fk_inputs()

    def f(q, root):
        return fk(q, off, PARENTS, root)

    out = torch.compile(f, fullgraph=True, backend="eager")(q, root)
    torch.testing.assert_close(out, fk_reference(q, off, PARENTS, root))
    assert dispatch._built[("cpu", "fk")] is True


@needs_ext
def test_modulated_layer_compiles_fullgraph_with_fresh_dispatch():
    torch._dynamo.reset()
    torch.manual_seed(0)
    m = ModulatedSkeletalConv(3, 4, 6, NEIGHBORS, mode="same", demodulate=True)
    x, w = torch.randn(2, 3, 5, 8), torch.randn(2, 6)
    y = torch.compile(m, fullgraph=True, backend="eager")(x, w)
    torch.testing.assert_close(y, m(x, w))
    assert any(r["kind"] == "selfcheck" and r["ok"] for r in modi_ext.dispatch_report())


# ------------------------------------------------------------------------------------------------ self-check
@needs_ext
@pytest.mark.parametrize("name,kind", [("skeletal_conv", "conv"), ("skeletal_down", "down"), ("skeletal_up", "up")])
def test_selfcheck_catches_a_wrong_kernel_and_routes_to_dense(monkeypatch, name, kind):
    monkeypatch.setitem(dispatch.KERNELS, name, wrong_kernel(name))
    p = problem(kind, dtype=torch.float32)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        y1 = call(ops, p)
        y2 = call(ops, p)
    msgs = [str(w.message) for w in rec if "self-check" in str(w.message)]
    assert len(msgs) == 1 and name in msgs[0] and "forward error" in msgs[0], msgs
    want = call(reference, p)
    torch.testing.assert_close(y1, want, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(y2, want, rtol=1e-5, atol=1e-5)
    rows = [r for r in modi_ext.dispatch_report() if r["kind"] == "selfcheck"]
    assert rows == [dict(rows[0], device="cpu", dtype="float32", ok=False)] and name in rows[0]["errors"]
    # another dtype is checked on its own
    with pytest.warns(RuntimeWarning, match="float64"):
        call(ops, problem(kind, dtype=torch.float64))
    assert dispatch._checked[("cpu", "torch.float64")]["ok"] is False  # the wrong kernel is wrong in fp64 too


@needs_ext
def test_selfcheck_modes(monkeypatch):
    monkeypatch.setitem(dispatch.KERNELS, "skeletal_conv", wrong_kernel("skeletal_conv"))
    p = problem("conv", dtype=torch.float32)
    monkeypatch.setenv("MODI_EXT_SELFCHECK", "strict")
    with pytest.raises(RuntimeError, match="skeletal_conv.*MODI_EXT_SELFCHECK=strict"):
        call(ops, p)
    with pytest.raises(RuntimeError, match="self-check failed"):  # stays refused, not only the first time
        call(ops, p)
    monkeypatch.setenv("MODI_EXT_SELFCHECK", "0")  # no check: the wrong kernel is used (the check is what protects)
    assert not torch.allclose(call(ops, p), call(reference, p), rtol=1e-5, atol=1e-5)
    monkeypatch.setenv("MODI_EXT_SELFCHECK", "sometimes")
    with pytest.raises(ValueError, match="MODI_EXT_SELFCHECK"):
        call(ops, p)


@needs_ext
def test_selfcheck_catches_a_raising_kernel_and_wrong_fk(monkeypatch):
    def boom(*a):
        raise RuntimeError("no kernel image is available for execution on the device")

    monkeypatch.setitem(dispatch.KERNELS, "skeletal_up", boom)
    real_fk = dispatch.KERNELS["fk"]
    monkeypatch.setitem(dispatch.KERNELS, "fk", lambda *a: tuple(t * 1.001 for t in real_fk(*a)))
    res = selfcheck.run("cpu", torch.float32)
    assert not res["ok"] and set(res["errors"]) == {"skeletal_up", "fk"}
    assert "no kernel image" in res["errors"]["skeletal_up"]
    q, off, root = fk_inputs(torch.float32)
    with pytest.warns(RuntimeWarning, match="fk: forward error"):
        out = fk(q, off, PARENTS, root)
    torch.testing.assert_close(out, fk_reference(q, off, PARENTS, root))  # routed to the reference


@needs_ext
def test_selfcheck_covers_what_training_runs(monkeypatch):
    """Kernels wrong only where MoDi's training goes -- a weight gradient wrong only on wide layers (cin > 32: the
    64-row tiles and split-K of the CUDA kernels, B x T > 256) and an FK offsets gradient wrong only when it is
    asked for -- fail the first-use self-check: one warning naming the case, and the calls go to dense."""
    from modi_ext.runtime import payload

    real_bwd, real_fkb = dispatch.KERNELS["skeletal_backward"], dispatch.KERNELS["fk_backward"]

    def bwd(*a):
        gx, gw, gb, gs, gd = real_bwd(*a)
        return gx, (gw * 1.01 if a[2].shape[1] > 32 and gw.numel() else gw), gb, gs, gd

    def fkb(*a):
        gq, groot, goff = real_fkb(*a)
        return gq, groot, (goff * 1.01 if a[6] else goff)

    assert any(c.cin > 32 and c.columns > 256 for c in payload.SKELETAL_CASES)  # the case that finds it
    monkeypatch.setitem(dispatch.KERNELS, "skeletal_backward", bwd)
    monkeypatch.setitem(dispatch.KERNELS, "fk_backward", fkb)
    p = problem("conv", dtype=torch.float32)
    q, off, root = fk_inputs(torch.float32)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        y = call(ops, p)
        call(ops, p)
        pos = fk(q, off, PARENTS, root)
    msgs = [str(w.message) for w in rec if "self-check" in str(w.message)]
    assert len(msgs) == 1, msgs
    assert "skeletal_conv: backward error" in msgs[0] and "(conv.wide)" in msgs[0], msgs[0]
    assert "skeletal_up: backward error" in msgs[0] and "fk: backward error" in msgs[0], msgs[0]
    assert dispatch.route("skeletal_conv", p["x"]) == "dense"
    torch.testing.assert_close(y, call(reference, p), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(pos, fk_reference(q, off, PARENTS, root))


@needs_ext
@pytest.mark.parametrize("which", ["forward", "backward"])
def test_selfcheck_covers_the_demodulation_coefficients(monkeypatch, which):
    from modi_ext.runtime import selfcheck

    if which == "forward":
        real = dispatch.KERNELS["demod_scale"]
        monkeypatch.setitem(dispatch.KERNELS, "demod_scale", lambda *a: real(*a) * 1.01)
    else:
        real = dispatch.KERNELS["demod_scale_backward"]
        monkeypatch.setitem(dispatch.KERNELS, "demod_scale_backward", lambda *a: tuple(t * 1.01 for t in real(*a)))
    res = selfcheck.run("cpu", torch.float32)
    assert not res["ok"] and set(res["errors"]) == {"demod_scale"}
    assert f"{which} error" in res["errors"]["demod_scale"], res["errors"]


def test_one_selfcheck_key_per_device(monkeypatch):
    """'cuda' and 'cuda:0' (the current device) are one cache entry; validate and routing share it."""
    from modi_ext.runtime import kernels

    calls = []

    def fake_run(device, dtype, lib="modi_ext"):
        calls.append((device, dtype))
        return {"ok": True, "errors": {}, "max_error": {}}

    monkeypatch.setattr(dispatch, "SELFCHECK", fake_run)
    index = torch.cuda.current_device() if torch.cuda.is_available() else 0
    assert kernels.device_key("cuda") == kernels.device_key(f"cuda:{index}") == f"cuda:{index}"
    assert kernels.device_key(torch.device("cpu")) == "cpu"
    for dev in ("cuda", f"cuda:{index}", torch.device("cuda")):
        assert dispatch.kernels_trusted(dev, "torch.float32")
    assert calls == [(f"cuda:{index}", torch.float32)]
    rows = [r for r in modi_ext.dispatch_report() if r["kind"] == "selfcheck"]
    assert [r["device"] for r in rows] == [f"cuda:{index}"]


@needs_ext
def test_selfcheck_with_nothing_to_check_is_not_ok():
    """A device with no kernels registered is not 'ok': nothing was checked (issue 33)."""
    from modi_ext.runtime import selfcheck

    res = selfcheck.run("meta", torch.float32, lib="modi_ext_nonexistent")
    assert not res["ok"] and "nothing was checked" in res["errors"]["build"] and res["cases"] == 0


@needs_ext
@pytest.mark.parametrize("context", ["no_grad", "inference_mode"])
def test_selfcheck_passes_when_first_use_is_inside_no_grad(context):
    p = problem("conv", dtype=torch.float32)
    with getattr(torch, context)():
        call(ops, p)
    assert dispatch._checked[("cpu", "torch.float32")]["ok"], dispatch._checked


@needs_ext
def test_forced_ext_skips_the_selfcheck(monkeypatch):
    monkeypatch.setenv("MODI_EXT_IMPL", "ext")
    monkeypatch.setitem(dispatch.KERNELS, "skeletal_conv", wrong_kernel("skeletal_conv"))
    p = problem("conv", dtype=torch.float32)
    assert not torch.allclose(call(ops, p), call(reference, p), rtol=1e-5, atol=1e-5)
    assert not dispatch._checked


# ------------------------------------------------------------------------------------------------ auto timing
class FakeTimer:
    def __init__(self, ms: dict[str, float]):
        self.ms, self.calls = {"ref": 99.0, **ms}, []  # the reference slowest unless a test says otherwise

    def __call__(self, name, fn, device):
        fn()
        self.calls.append(name)
        return self.ms[name] / 1e3


@needs_ext
@pytest.mark.parametrize("ext_ms,dense_ms,want", [(5.0, 1.0, "dense"), (1.0, 5.0, "ext")])
def test_auto_keeps_the_faster_path_once_per_signature(monkeypatch, ext_ms, dense_ms, want):
    monkeypatch.setattr(dispatch, "MEASURE_DEVICES", {"cuda", "cpu"})
    timer = FakeTimer({"ext": ext_ms, "dense": dense_ms})
    monkeypatch.setattr(dispatch, "TIMER", timer)
    used = []
    for name in ("skeletal_conv", "skeletal_down"):
        real = dispatch.KERNELS[name]
        monkeypatch.setitem(dispatch.KERNELS, name, lambda *a, r=real, n=name: used.append(n) or r(*a))
    p = problem("conv", dtype=torch.float32)
    for _ in range(3):
        y = call(ops, p)
    torch.testing.assert_close(y, call(reference, p), rtol=1e-5, atol=1e-5)
    assert timer.calls.count("ext") == timer.calls.count("dense") == dispatch.AUTO_REPS  # measured once
    n_bench = len(used)
    call(ops, p)
    assert len(used) == n_bench + (1 if want == "ext" else 0)
    call(ops, problem("conv", dtype=torch.float32, T=16))  # a new shape signature: measured again
    assert timer.calls.count("ext") == 2 * dispatch.AUTO_REPS
    x = p["x"].clone().requires_grad_()  # training calls (forward + backward) are their own signature
    call(ops, p, x=x).sum().backward()
    assert timer.calls.count("ext") == 3 * dispatch.AUTO_REPS
    rows = [r for r in modi_ext.dispatch_report() if r["kind"] == "auto"]
    assert len(rows) == 3 and {r["choice"] for r in rows} == {want}
    assert rows[0]["ext_ms"] == pytest.approx(ext_ms) and rows[0]["dense_ms"] == pytest.approx(dense_ms)
    assert "fwd_bwd" in rows[2]["signature"] and "fwd_bwd" not in rows[0]["signature"]
    assert rows[0]["ref_ms"] == pytest.approx(99.0) and "error" not in rows[0]


@needs_ext
@pytest.mark.parametrize("grad", [False, True])
def test_auto_takes_the_reference_where_it_is_fastest(monkeypatch, grad):
    """The reference (one cuDNN conv on CUDA) is a candidate too: it runs, and its result is the op's."""
    monkeypatch.setattr(dispatch, "MEASURE_DEVICES", {"cuda", "cpu"})
    monkeypatch.setattr(dispatch, "TIMER", FakeTimer({"ext": 3.0, "dense": 2.0, "ref": 1.0}))
    p = problem("conv", dtype=torch.float32)
    x = p["x"].clone().requires_grad_(grad)
    y = call(ops, p, x=x)
    torch.testing.assert_close(y, call(reference, p), rtol=1e-5, atol=1e-5)
    if grad:
        y.sum().backward()
        assert x.grad is not None
    (row,) = [r for r in modi_ext.dispatch_report() if r["kind"] == "auto"]
    assert row["choice"] == "ref" and row["ref_ms"] == pytest.approx(1.0)
    paths = [r for r in modi_ext.dispatch_report() if r["kind"] == "path" and r["op"] == "skeletal_conv"]
    assert [(r["path"], r["calls"]) for r in paths] == [("ref", 1)]  # the timing runs are not counted


def test_auto_signature_holds_the_tf32_switches(monkeypatch):
    x = torch.zeros(2, 3)
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", True)
    on = dispatch._signature(x, (x,), (1,), False)
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", False)
    assert dispatch._signature(x, (x,), (1,), False) != on


@needs_ext
def test_auto_on_cpu_is_the_kernels_without_timing(monkeypatch):
    timer = FakeTimer({"ext": 9.0, "dense": 1.0})
    monkeypatch.setattr(dispatch, "TIMER", timer)
    assert dispatch.route("skeletal_conv", torch.zeros(1), rerun=lambda path, x: x, inputs=(torch.zeros(1),)) == "ext"
    assert timer.calls == []


@needs_ext
def test_auto_prefers_dense_when_the_kernel_cannot_run_the_shape(monkeypatch):
    monkeypatch.setattr(dispatch, "MEASURE_DEVICES", {"cpu"})
    monkeypatch.setattr(dispatch, "TIMER", FakeTimer({"ext": 1.0, "dense": 2.0}))

    def rerun(path, x):
        if path == "ext":
            raise RuntimeError("too many resources requested for launch")
        return x

    x = torch.zeros(1)
    assert dispatch.route("skeletal_conv", x, rerun=rerun, inputs=(x,)) == "dense"
    assert "too many resources" in [r for r in modi_ext.dispatch_report() if r["kind"] == "auto"][0]["error"]


# ------------------------------------------------------------------------------------------------ autocast
@pytest.mark.parametrize("impl", ["auto", "dense", "ref"])
@pytest.mark.parametrize("mode", ["same", "up", "down"])
def test_autocast_bf16_runs_the_modulated_layers(monkeypatch, impl, mode):
    # EqualLinear's style comes out bf16 under autocast while x and the conv weight stay fp32: this used to be a
    # TypeError in the argument checks
    if impl == "auto" and not HAS_EXT:
        pytest.skip("extension not built")
    monkeypatch.setenv("MODI_EXT_IMPL", impl)
    torch.manual_seed(3)
    topo = NEIGHBORS if mode == "same" else POOLING
    m = ModulatedSkeletalConv(3, 4, 6, topo, mode=mode, demodulate=True)
    n_in = 3 if mode == "up" else 5
    x = torch.randn(2, 3, n_in, 8, requires_grad=True)
    w = torch.randn(2, 6)
    want = m(x, w)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert m.affine(w).dtype == torch.bfloat16
        y = m(x, w)
    # issue 52: the output follows torch's autocast rule for convolutions (bf16: the dense path, on every impl)
    assert y.dtype == torch.bfloat16 and torch.isfinite(y).all()
    torch.testing.assert_close(y.float(), want, rtol=5e-2, atol=5e-2)  # inputs, style and output rounded to bf16
    (gx,) = torch.autograd.grad(y.sum(), x)
    assert torch.isfinite(gx).all()
    with torch.autocast("cpu", dtype=torch.bfloat16):  # a bf16 activation from an earlier autocast op
        y16 = m(x.to(torch.bfloat16), w)
    assert y16.dtype == torch.bfloat16
    torch.testing.assert_close(y16.float(), want, rtol=5e-2, atol=5e-2)


# ------------------------------------------------------------------------------------------------ fp16 demodulation
@pytest.mark.parametrize("up", [False, True])
def test_fp16_demod_of_a_zero_row_is_finite(up):
    p = problem("up" if up else "conv", dtype=torch.float16)
    w = p["w"].clone()
    if up:
        w[:, :, 0] = 0  # output channel 0 receives nothing
    else:
        w[0] = 0
    n_out = 5 if up else 5
    d = ops.demod_scale(w, p["idx"], p["off"], p["s"], up, n_out, 2)
    assert d.dtype == torch.float16 and torch.isfinite(d).all()
    torch.testing.assert_close(d[:, 0].float(), torch.full_like(d[:, 0].float(), 1e4), rtol=1e-3, atol=0)
    for mod in (dense, reference):  # the half math of both dense paths: zero row -> zero output, never NaN
        y = call(mod, p, w=w, b=torch.zeros_like(p["b"]))
        assert y.dtype == torch.float16 and torch.isfinite(y).all(), mod.__name__
        assert (y[:, 0] == 0).all(), mod.__name__
        y64 = call(reference, p, x=p["x"].double(), w=w.double(), b=torch.zeros(4, dtype=torch.float64),
                   s=p["s"].double())
        torch.testing.assert_close(y.double(), y64, rtol=2e-2, atol=2e-2)


# ------------------------------------------------------------------------------------------------ FK double backward
def fk_inputs(dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(2, 3, len(PARENTS), 4, generator=g, dtype=torch.float64)
    q = (q / q.norm(dim=-1, keepdim=True)).to(dtype)
    off = torch.randn(len(PARENTS), 3, generator=g, dtype=torch.float64).to(dtype)
    root = torch.randn(2, 3, 3, generator=g, dtype=torch.float64).to(dtype)
    return q, off, root


@needs_ext
def test_fk_kernel_double_backward_gradgradcheck():
    q, off, root = fk_inputs()
    leaves = [t.clone().requires_grad_() for t in (q, off, root)]

    def f(q, off, root):
        pos, rot = fk(q, off, PARENTS, root, return_rotations=True, impl="ext")
        return pos, rot

    torch.autograd.gradgradcheck(f, leaves)


@needs_ext
def test_fk_kernel_second_order_matches_reference():
    q, off, root = fk_inputs(seed=2)
    results = []
    for impl in ("ext", "ref"):
        qq, rr = q.clone().requires_grad_(), root.clone().requires_grad_()
        pos = fk(qq, off, PARENTS, rr, impl=impl)
        (gq,) = torch.autograd.grad(pos.pow(2).sum(), qq, create_graph=True)
        results.append(torch.autograd.grad(gq.pow(2).sum(), (qq, rr), allow_unused=True, materialize_grads=True))
    for a, b in zip(*results):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)
    assert results[0][0].abs().max() > 0  # a first-order-only backward would give zero here


# ------------------------------------------------------------------------------------------------ CSR validation
@pytest.mark.parametrize("mutate,match", [
    (lambda idx, off: idx.__setitem__(2, 7), "out of range"),
    (lambda idx, off: idx.__setitem__(0, -1), "out of range"),
    (lambda idx, off: off.__setitem__(2, 1), "not monotone"),
    (lambda idx, off: off.__setitem__(2, off[1]), "has no neighbors"),
    (lambda idx, off: off.__setitem__(-1, 3), "offsets must run from 0"),
])
@pytest.mark.parametrize("impl", ["auto", "dense", "ref"])
def test_malformed_csr_is_a_clear_error(monkeypatch, mutate, match, impl):
    if impl == "auto" and not HAS_EXT:
        pytest.skip("extension not built")
    monkeypatch.setenv("MODI_EXT_IMPL", impl)
    p = problem("conv")
    p["idx"], p["off"] = p["idx"].clone(), p["off"].clone()
    mutate(p["idx"], p["off"])
    with pytest.raises(ValueError, match=match):
        call(ops, p)


def test_csr_validation_is_cached_per_index_tensor(monkeypatch):
    seen = []
    real = checks._check_csr_values
    monkeypatch.setattr(checks, "_check_csr_values", lambda *a: seen.append(1) or real(*a))
    p = problem("conv")
    idx, off = p["idx"].clone(), p["off"].clone()
    p["idx"], p["off"] = idx, off
    for _ in range(4):
        call(ops, p)
    assert len(seen) == 1
    idx[3] = 9  # an in-place write bumps the version counter: validated again, and refused
    with pytest.raises(ValueError, match="out of range"):
        call(ops, p)
    assert len(seen) == 2
    p["idx"] = idx.clone()  # a new tensor with the same values is validated on its own
    p["idx"][3] = 1
    call(ops, p)
    assert len(seen) == 3


# ------------------------------------------------------------------------------------------------ determinism
@pytest.mark.parametrize("up", [False, True])
def test_demod_sums_are_deterministic_and_unchanged(monkeypatch, up):
    # index_add is nondeterministic on CUDA (atomics); the per-entity sums must not use it
    p = problem("up" if up else "conv")

    def no_index_add(*a, **k):
        raise AssertionError("index_add used for the demodulation sums")

    w, idx, off, s = p["w"], p["idx"], p["off"], p["s"]
    monkeypatch.setattr(torch.Tensor, "index_add", no_index_add)
    d = ops.demod_scale(w, idx, off, s, up, 5 if up else off.numel() - 1, 2, impl="dense")  # the torch form
    monkeypatch.undo()
    # the value it had before (the dense reference's coefficients)
    if up:
        dw = reference.to_dense(w, idx, off, 5)  # (Ci, Co, Ec, Ef, U)
        want = torch.rsqrt((dw.unsqueeze(0) * s.view(2, -1, 1, 1, 1, 1)).pow(2).sum((1, 3, 5)) + 1e-8)
    else:
        want = demod_coefficients(reference.to_dense(w, idx, off, 5), s)
    torch.testing.assert_close(d, want, rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------------------------------------ environment
def test_unknown_impl_is_rejected(monkeypatch):
    monkeypatch.setenv("MODI_EXT_IMPL", "fastest")
    with pytest.raises(ValueError, match="MODI_EXT_IMPL must be 'auto', 'ext', 'dense' or 'ref'"):
        call(ops, problem("conv"))


# ------------------------------------------------------------------------------------------------ validate command
def test_validate_without_a_gpu_says_so_and_fails(tmp_path):
    import subprocess
    import sys

    if torch.cuda.is_available():
        pytest.skip("a GPU is visible here")
    out = tmp_path / "r.json"
    r = subprocess.run([sys.executable, "-m", "modi_ext.validate", "--json", str(out)], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2
    assert ("no GPU is visible" in r.stderr or "CPU-only build" in r.stderr) and r.stderr.count("\n") == 1, r.stderr
    assert not out.exists()


def test_validate_dry_run_lists_every_step_within_budget(capsys):
    from modi_ext import validate

    assert validate.main(["--dry-run"]) == 0
    text = capsys.readouterr().out
    for name in ("dispatch", "cuda_tests", "sanitizer_racecheck", "sanitizer_synccheck", "sanitizer_initcheck",
                 "compare_fp32", "compare_bf16", "train_step"):
        assert name in text
    assert "--device cuda" in text and "test_cuda_ops.py" in text and "--preset paper" in text
    steps = validate.plan(__import__("pathlib").Path("/nonexistent"))
    assert sum(s.timeout_s for s in steps) <= validate.DEFAULT_BUDGET_S <= 10 * 60
    assert all(s.needs or s.tool or s.name == "dispatch" for s in steps)


def test_validate_step_runner_statuses(tmp_path):
    import sys

    from modi_ext import validate

    ok = validate.Step("ok", [sys.executable, "-c", "print('hi')"], 30)
    assert validate.run_step(ok, 30)["status"] == "pass"
    bad = validate.Step("bad", [sys.executable, "-c", "raise SystemExit(3)"], 30)
    res = validate.run_step(bad, 30)
    assert (res["status"], res["rc"]) == ("fail", 3)
    slow = validate.Step("slow", [sys.executable, "-c", "import time; print('started', flush=True); time.sleep(60)"],
                         30)
    res = validate.run_step(slow, 6)
    assert res["status"] == "timeout" and res["seconds"] < 30 and "started" in res["tail"]
    missing = validate.Step("m", ["true"], 30, needs=[tmp_path / "absent.py"])
    assert validate.run_step(missing, 30)["status"] == "skipped"
    tool = validate.Step("t", ["x"], 30, tool="no-such-tool-modi")
    assert "not on PATH" in validate.run_step(tool, 30)["reason"]
    result = tmp_path / "res.json"
    writes = validate.Step("w", [sys.executable, "-c", f"open({str(result)!r}, 'w').write('{{\"a\": 1}}')"], 30,
                           result_json=result)
    assert validate.run_step(writes, 30)["result"] == {"a": 1}
    assert validate.gpu_slug("NVIDIA H200") == "nvidia_h200"
    assert validate.gpu_slug("NVIDIA H100 80GB HBM3") == "nvidia_h100_80gb_hbm3"


@needs_ext
def test_validate_payloads_run_on_cpu(tmp_path):
    from modi_ext import validate

    assert validate.main(["--payload", "kernels", "--device", "cpu", "--out", str(tmp_path / "k.json")]) == 0
    import json

    res = json.loads((tmp_path / "k.json").read_text())
    assert res["errors"] == {}
    assert {r.split(".")[0] for r in res["ran"]} == {"conv", "down", "up", "fk", "demod"}
    assert {r.rsplit(".", 1)[1] for r in res["ran"]} == {"float32", "float64"}  # the CPU kernels' dtypes


@pytest.mark.parametrize("impl", ["ref", "dense", "ext"])
def test_the_report_records_the_path_each_op_took(monkeypatch, impl):
    """Per op, device and dtype, ``dispatch_report()`` counts the calls of each path (issue 40)."""
    if impl == "ext" and not HAS_EXT:
        pytest.skip("modi_ext C++ extension not built")
    monkeypatch.setenv("MODI_EXT_IMPL", impl)
    conv = ModulatedSkeletalConv(4, 4, 6, [[0, 1], [0, 1, 2], [1, 2]], kernel_size=3)
    x, w = torch.randn(2, 4, 3, 8), torch.randn(2, 6)
    for _ in range(3):
        conv(x, w)
    q = torch.nn.functional.normalize(torch.randn(2, 3, 4), dim=-1)
    fk(q, torch.randn(3, 3), [-1, 0, 1], torch.zeros(2, 3))
    rows = [r for r in modi_ext.dispatch_report() if r["kind"] == "path"]
    conv_rows = [r for r in rows if r["op"] != "fk" and r["op"] != "demod_scale"]
    assert conv_rows and {r["path"] for r in conv_rows} == {impl}, rows
    assert all(r["device"] == "cpu" and r["dtype"] == "float32" for r in rows), rows
    assert sum(r["calls"] for r in conv_rows) == 3, rows
    fk_rows = [r for r in rows if r["op"] == "fk"]
    assert [(r["path"], r["calls"]) for r in fk_rows] == [(impl, 1)], rows


def test_dispatch_report_names_the_tensor_core_choice(monkeypatch):
    """The CUDA tensor-core switch as the C++ op reads it: bf16 when asked, float32 (TF32) only while cuDNN's TF32
    switch is on."""
    monkeypatch.delenv("MODI_EXT_CUDA_MMA", raising=False)
    (row,) = [r for r in modi_ext.dispatch_report() if r["kind"] == "tensor_cores"]
    assert row["requested"] is False and row["bf16"] is False and row["float32_tf32"] is False
    monkeypatch.setenv("MODI_EXT_CUDA_MMA", "1")
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", False)
    (row,) = [r for r in modi_ext.dispatch_report() if r["kind"] == "tensor_cores"]
    assert row["bf16"] is True and row["float32_tf32"] is False
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", True)
    (row,) = [r for r in modi_ext.dispatch_report() if r["kind"] == "tensor_cores"]
    assert row["bf16"] is True and row["float32_tf32"] is True
