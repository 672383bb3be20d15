"""Issue 51, item 4: the MoDi training step as one CUDA graph per step kind, proven without a GPU.

The capture is a backend (``modi.models.modi.graphs``). On the CPU, ``graphs.OpTape`` stands in for a CUDA graph: a
capture records the step's ATen ops and undoes them (a capture does not run), a replay runs them again against the
same tensors with every non-tensor argument as it was at capture. A host value baked into the step, or a buffer that
is not refilled before a replay, so makes graphed training differ from eager, as on a GPU; the planted faults below
show that it does. The CPU runs the same ops either way, so graphed equals eager bit for bit.

Schedule of the tiny config (``d_reg_every`` 3, ``g_reg_every`` 2): 0 r1+path, 1 plain, 2 path, 3 r1, 4 path, 5 plain,
6 r1+path, ... With one warm-up step per kind the graphs are captured at steps 4 (path), 5 (plain), 6 (r1+path) and
9 (r1): steps 4-9, one whole cycle, are replays.
"""
from __future__ import annotations

import warnings

import pytest
import torch
from test_modi_training import full_state  # every weight and optimiser state of a trainer

from modi.errors import UserError
from modi.models.modi.config import make_config
from modi.models.modi.graphs import GRAPH_MODES, GraphCaptureError, GraphFallbackWarning, OpTape
from modi.models.modi.sampling import load_checkpoint
from modi.models.modi.training import Trainer, prepare_data, write_procedural_data

TINY = {"model.channels": (8, 8, 8, 6, 6), "model.latent_dim": 16, "model.n_mlp": 2, "data.n_frames": 16,
        "data.stride": 8, "train.batch": 4, "train.sample_every": 0, "train.ckpt_every": 0, "train.log_every": 1000,
        "train.d_reg_every": 3, "train.g_reg_every": 2, "train.snapshot_every": 0}
N = 10  # steps of a run: every kind captured, steps 4-9 replayed
SAVE_AT = 5



@pytest.fixture(scope="module", autouse=True)
def one_thread_for_the_module():
    """One torch thread for the module-scoped runs too (``one_torch_thread`` is per test, set up after them): the
    runs compared bit for bit must split their reductions alike, and tiny models run fastest on one thread."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def tiny_cfg(**kw):
    return make_config("small", [], **{**TINY, **kw})


@pytest.fixture(scope="module")
def proc_data(tmp_path_factory):
    folder = write_procedural_data(tmp_path_factory.mktemp("proc") / "data", n_clips=6, frames=40, seed=1)
    return prepare_data(folder, tiny_cfg(), cache=False)


def make_trainer(data, run_dir, cfg=None, warmup: int = 1, **kw) -> Trainer:
    kw = {"progress": False, "tensorboard": False, "write_samples": False, "log": lambda m: None, **kw}
    tr = Trainer(cfg or tiny_cfg(), data, run_dir, **kw)
    if tr.graphs is not None:
        tr.graphs.warmup = warmup
    return tr


def run(tr: Trainer, steps: int, save_at: int | None = None) -> list[dict[str, float]]:
    out = []
    for _ in range(steps):
        out.append(tr.train_step())
        if tr.step == save_at:
            tr.save_checkpoint()
    return out


@pytest.fixture(scope="module")
def eager(proc_data, tmp_path_factory):
    tr = make_trainer(proc_data, tmp_path_factory.mktemp("eager"), cuda_graphs="off")
    losses = run(tr, N)
    return losses, full_state(tr)


@pytest.fixture(scope="module")
def graphed(proc_data, tmp_path_factory):
    tr = make_trainer(proc_data, tmp_path_factory.mktemp("graphed"), cuda_graphs="on", graph_backend=OpTape())
    losses = run(tr, N, save_at=SAVE_AT)
    return tr, losses


def assert_same_state(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    assert [k for k in a if not torch.equal(a[k], b[k])] == []


# --------------------------------------------------------------------------------------------- equality
def test_a_graphed_cycle_equals_eager(eager, graphed):
    tr, losses = graphed
    rec = tr.graphs_record()
    assert rec["ran"] == "on" and rec["fallback"] is None
    assert rec["captured"] == ["path", "plain", "r1", "r1+path"]
    assert rec["replays"] == {"path": 2, "plain": 2, "r1+path": 1, "r1": 1}  # steps 4-9
    assert losses == eager[0]  # every loss of every step, bit for bit
    assert_same_state(full_state(tr), eager[1])  # G, D, G_ema, both optimisers' states, the mean path length


def test_static_buffers_are_refilled_and_outputs_copied_out(graphed):
    tr, losses = graphed
    # replays of one graph see other windows and latents: their losses differ (path: steps 4, 8; plain: 5, 7)
    assert losses[4]["d"] != losses[8]["d"] and losses[5]["d"] != losses[7]["d"]
    assert torch.equal(tr._index_buffer, tr._device_indices(N - 1))  # the last step's windows
    # what a step returns is a copy, never the graph's output buffers (the next replay rewrites those)
    kind = tr._step_kind()
    out = tr.run_step()
    assert all(out[k].data_ptr() != v.data_ptr() for k, v in tr.graphs.graphs[kind].outputs.items())


class _BakedEma(Trainer):
    """A planted fault: the EMA weight filled inside the step, so a graph keeps its capture's value."""

    def _prepare_step(self):
        if self.graphs is not None:
            self._index_buffer.copy_(self._device_indices())

    def _step_body(self):
        self._ema_weight.fill_(1.0 - self._ema_decay())
        return super()._step_body()


class _SlicedIndices(Trainer):
    """A planted fault: the real batch read through a slice of the epoch's order, so a graph keeps its windows."""

    def _real_batch(self):
        return self.windows[self._device_indices()]


PLAIN = {"train.d_reg_every": 1000, "train.g_reg_every": 1000}  # plain steps after step 0: warmed at 1, captured
# at 2, replayed at 3


@pytest.fixture(scope="module")
def plain_eager(proc_data, tmp_path_factory):
    tr = make_trainer(proc_data, tmp_path_factory.mktemp("plain"), cfg=tiny_cfg(**PLAIN), cuda_graphs="off")
    run(tr, 4)
    return full_state(tr)


@pytest.mark.parametrize("cls", [_BakedEma, _SlicedIndices], ids=["ema_weight_baked", "batch_slice_baked"])
def test_the_stand_in_catches_a_host_value_baked_into_the_graph(proc_data, plain_eager, tmp_path, cls):
    tr = cls(tiny_cfg(**PLAIN), proc_data, tmp_path, progress=False, tensorboard=False, write_samples=False,
             cuda_graphs="on", graph_backend=OpTape())
    tr.graphs.warmup = 1
    run(tr, 4)
    assert tr.graphs.replays == {"plain": 2}
    mine = full_state(tr)
    assert [k for k, v in plain_eager.items() if not torch.equal(v, mine[k])], "the planted fault went unnoticed"


# --------------------------------------------------------------------------------------------- fallback
class _HostRead(Trainer):
    """A step that reads a device value on the host after all of its updates (harmless when eager)."""

    def _step_body(self):
        out = super()._step_body()
        float(self._skip_run)
        return out


def test_a_failed_capture_falls_back_to_eager_with_one_warning(proc_data, eager, tmp_path):
    tr = _HostRead(tiny_cfg(), proc_data, tmp_path, progress=False, tensorboard=False, write_samples=False,
                   cuda_graphs="on", graph_backend=OpTape())
    tr.graphs.warmup = 1
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        losses = run(tr, 6)  # the capture at step 4 fails; steps 4 and 5 run eagerly
    ours = [w for w in seen if issubclass(w.category, GraphFallbackWarning)]
    assert len(ours) == 1 and "\n" not in str(ours[0].message)
    assert GraphCaptureError.__name__ in str(ours[0].message) and "training continues eagerly" in str(ours[0].message)
    rec = tr.graphs_record()
    assert rec["ran"] == "fell back" and rec["captured"] == [] and rec["reason"].startswith("path step")
    # the failed capture ran half a step on the CPU stand-in and undid it: nothing is lost or taken twice
    assert losses == eager[0][:6]


# --------------------------------------------------------------------------------------------- resume
def test_resume_under_graphs_equals_eager(proc_data, eager, graphed, tmp_path):
    tr, _ = graphed
    ckpt = tr.run_dir / "checkpoint.pt"
    st = load_checkpoint(ckpt)
    assert st["step"] == SAVE_AT and st["cuda_graphs"]["asked"] == "on" and st["cuda_graphs"]["ran"] == "on"
    again = make_trainer(proc_data, tmp_path, cuda_graphs="on", graph_backend=OpTape(), resume=ckpt)
    losses = run(again, N - SAVE_AT)
    assert again.graphs.replays  # captured again after the load (7: plain)
    assert losses == eager[0][SAVE_AT:]
    assert_same_state(full_state(again), eager[1])
    again.load_state(ckpt)  # new optimiser state tensors: every kind warms up and is captured again
    assert again.graphs.graphs == {} and again.graphs.warm == {} and again.step == SAVE_AT


# --------------------------------------------------------------------------------------------- modes
def test_modes_on_the_cpu(proc_data, tmp_path):
    with pytest.raises(UserError, match="choose one of auto, on, off"):
        make_trainer(proc_data, tmp_path, cuda_graphs="yes")
    auto = make_trainer(proc_data, tmp_path)  # the default
    assert auto.cuda_graphs == "auto" and auto.graphs is None
    assert auto.graphs_summary() == "CUDA graphs off (needs a CUDA device; this run is on cpu)"
    off = make_trainer(proc_data, tmp_path, cuda_graphs="off")
    assert off.graphs is None and off.graphs_record() == {"asked": "off", "ran": "off", "reason": "off"}
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        on = make_trainer(proc_data, tmp_path, cuda_graphs="on")
    assert on.graphs is None and on.graphs_record()["ran"] == "off"
    ours = [str(w.message) for w in seen if issubclass(w.category, GraphFallbackWarning)]
    assert ours == ["modi train: CUDA graphs need a CUDA device; this run is on cpu and trains eagerly"]


def test_bf16_autocast_keeps_no_cast_cache_under_graphs(proc_data, tmp_path):
    tr = make_trainer(proc_data, tmp_path, cuda_graphs="on", graph_backend=OpTape(), precision="bf16")
    ctx = tr._autocast()
    assert ctx.fast_dtype == torch.bfloat16 and ctx._cache_enabled is False
    assert make_trainer(proc_data, tmp_path, precision="bf16")._autocast()._cache_enabled is not False


def test_no_graphs_with_ddp(proc_data, tmp_path):
    import torch.distributed as dist  # only this test makes a process group

    if dist.is_initialized():
        pytest.skip("a process group is already set up in this process")
    dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'pg'}", rank=0, world_size=1)
    try:
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            tr = make_trainer(proc_data, tmp_path, cuda_graphs="on", graph_backend=OpTape())
        assert tr.graphs is None
        ours = [str(w.message) for w in seen if issubclass(w.category, GraphFallbackWarning)]
        assert ours == ["modi train: CUDA graphs run in one process only; this run has 1 (DDP) and trains eagerly"]
        assert tr.graphs_record()["reason"] == "one process only; this run has 1"
    finally:
        dist.destroy_process_group()


def test_api_and_cli_take_the_modes(tmp_path, capsys):
    from modi.api import train_modi
    from modi.cli import build_parser
    from modi.cli.commands.train import _one_line

    with pytest.raises(UserError, match="cuda_graphs 'fast': choose one of auto, on, off"):
        train_modi("procedural", tmp_path / "run", cuda_graphs="fast")
    assert not (tmp_path / "run").exists()  # refused before any work
    parser = build_parser()
    assert parser.parse_args(["train", "d", "--out", str(tmp_path / "o")]).cuda_graphs == "auto"
    for mode in GRAPH_MODES:
        assert parser.parse_args(["train", "d", "--out", str(tmp_path / "o"), "--cuda-graphs", mode]).cuda_graphs == mode
    # the command prints a graph notice as its one line, and leaves other warnings to Python
    others = []
    show = _one_line(lambda *a, **k: others.append(a[0]), GraphFallbackWarning)
    show(GraphFallbackWarning("modi train: CUDA graphs ..."), GraphFallbackWarning, "x.py", 1)
    show(UserWarning("else"), UserWarning, "x.py", 1)
    assert capsys.readouterr().err == "modi train: CUDA graphs ...\n" and [str(w) for w in others] == ["else"]


def test_the_device_scripts_comparison_tells_equal_from_not():
    """``benchmarks/gpu_measure.py``'s ``compare_cycles``, the gate of ``AUTO_ENABLES_GRAPHS``: within tolerance is
    equal; a weight off, a loss off, a NaN, a missing step or tensor is not."""
    from benchmarks.gpu_measure import compare_cycles

    def runs(**change):
        losses = [{"d": 1.0, "g": 2.0}, {"d": 1.5, "g": 0.5}]
        state = {"G.w": torch.ones(3), "mean_path_length": torch.tensor(0.25)}
        for k, v in change.items():
            (state if k in state else losses[1])[k] = v
        return {"losses": losses, "state": state}

    ok = compare_cycles(runs(), runs(**{"G.w": torch.ones(3) + 1e-6, "d": 1.5 + 1e-6}))
    assert ok["equal"] and 0 < ok["max_abs_state_diff"] < 1e-5
    assert compare_cycles(runs(), runs(**{"G.w": torch.tensor([1.0, 1.1, 1.0])}))["state_differs"] == ["G.w"]
    assert compare_cycles(runs(), runs(d=1.6))["losses_differ"] == ["step 1 d: 1.5 vs 1.6"]
    assert not compare_cycles(runs(), runs(g=float("nan")))["equal"]
    short = runs()
    short["losses"] = short["losses"][:1]
    assert not compare_cycles(runs(), short)["equal"]
    assert not compare_cycles(runs(), {"losses": runs()["losses"], "state": {"G.w": torch.ones(3)}})["equal"]


# --------------------------------------------------------------------------------------------- on a GPU
@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_real_cuda_graphs_equal_eager_on_the_gpu(proc_data, tmp_path):
    """The real capture (``CudaGraphBackend``): a graphed run of the tiny small-preset config equals an eager one
    within float tolerance (GPU kernels need not be bit-reproducible), every kind captured, no fallback."""
    torch.manual_seed(0)
    a = make_trainer(proc_data, tmp_path / "a", cuda_graphs="off", device="cuda")
    la = run(a, N + 2)
    torch.manual_seed(0)
    b = make_trainer(proc_data, tmp_path / "b", cuda_graphs="on", device="cuda")
    lb = run(b, N + 2)
    rec = b.graphs_record()
    assert rec["backend"] == "cuda" and rec["fallback"] is None and len(rec["captured"]) == 4
    for x, y in zip(la, lb):
        assert x.keys() == y.keys()
        for k in x:
            assert abs(x[k] - y[k]) <= 1e-3 + 1e-3 * abs(x[k]), (k, x[k], y[k])
    sa, sb = full_state(a), full_state(b)
    bad = [k for k in sa if not torch.allclose(sa[k].float(), sb[k].float(), rtol=1e-3, atol=1e-4)]
    assert bad == []
