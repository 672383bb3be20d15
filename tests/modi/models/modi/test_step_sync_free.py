"""Issue 51, item 2: a MoDi training step with no host syncs and the same ops every time (CPU, tiny models).

* A ``TorchDispatchMode`` counter (``benchmarks/step_ops.py``) runs steps of each kind (plain, path length, R1,
  R1 + path length) through the training loop: no ``aten::_local_scalar_dense`` and no tensor made from host data
  outside log steps, the same (op, shapes) sequence from step to step of a kind, and an op budget per kind.
* Reading the losses only at log steps gives the losses of reading them every step.
* A checkpoint written before the change resumes as it did (``data/training_before_issue51.json``: the code of
  commit d34b2ee, mixing 0 -- with mixing > 0 every step now draws its latents, index and choice whether it mixes or
  not, so the stream differs from the first step that does not mix); a saved ``capturable`` flag is replaced.
* A non-finite loss skips its step on the device, is reported at the next log step, and ``NONFINITE_STEPS`` in a
  row stop the run without a checkpoint.
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from test_modi_training import full_state  # every weight and optimiser state of a trainer

from benchmarks.step_ops import OpCounter, count_loop, step_kind
from modi.data.normalization import Normalizer
from modi.models.modi import training
from modi.models.modi.config import make_config
from modi.models.modi.distributed import shard_indices
from modi.models.modi.sampling import load_checkpoint
from modi.models.modi.training import NONFINITE_STEPS, NonFiniteLossError, Trainer, prepare_data, \
    write_procedural_data

TINY = {"model.channels": (8, 8, 8, 6, 6), "model.latent_dim": 16, "model.n_mlp": 2, "data.n_frames": 16,
        "data.stride": 8, "train.batch": 4, "train.sample_every": 0, "train.ckpt_every": 0, "train.log_every": 1,
        "train.d_reg_every": 2, "train.g_reg_every": 2, "train.snapshot_every": 0}
FIXTURE = Path(__file__).parent / "data" / "training_before_issue51.json"
# ATen ops that do work (not views) per step of the TINY model, counted with a dispatch mode (so through the
# registered ops, the eager shortcut off): 1,074-1,076 / 2,693-2,704 / 1,479-1,490 / 3,098 (log steps read a few
# more), with ~3% room; the history of these counts is on the results page (docs/results.md, host syncs and ops)
BUDGET = {"plain": 1110, "path": 2790, "r1": 1540, "r1+path": 3200}

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def tiny_cfg(**kw):
    return make_config("small", [], **{**TINY, **kw})


@pytest.fixture(scope="module")
def proc_data(tmp_path_factory):
    folder = write_procedural_data(tmp_path_factory.mktemp("proc") / "data", n_clips=6, frames=40, seed=1)
    return prepare_data(folder, tiny_cfg(), cache=False)


def make_trainer(data, run_dir, cfg=None, **kw) -> Trainer:
    kw = {"progress": False, "tensorboard": False, "write_samples": False, "log": lambda m: None, **kw}
    return Trainer(cfg or tiny_cfg(), data, run_dir, **kw)



# --------------------------------------------------------------------------------------------- the counter
def test_steps_read_nothing_from_the_host_and_repeat_their_ops(proc_data, tmp_path):
    # d_reg_every 3, g_reg_every 2: steps 0 r1+path, 1 plain, 2 path, 3 r1, 4 path, 5 plain, 6 r1+path, 7 plain,
    # 8 path, 9 r1; log steps after steps 4 and 9 (log_every 5)
    cfg = tiny_cfg(**{"train.d_reg_every": 3, "train.g_reg_every": 2, "train.log_every": 5})
    tr = make_trainer(proc_data, tmp_path, cfg=cfg)
    counter = OpCounter()
    with counter:
        count_loop(tr, 10, lambda s: counter.mark(step=s, kind=step_kind(s, cfg.train)))
    steps = counter.steps[:10]
    assert [s["step"] for s in steps] == list(range(10))
    # step 0 is the first use of every layer: modi_ext checks the layers' index maps and runs its self-check once
    for s in steps[1:]:
        log_step = (s["step"] + 1) % 5 == 0
        if not log_step:
            assert s["syncs"] == 0, (s["step"], s["kind"], [op for op, _ in s["seq"] if "scalar_dense" in op])
        assert s["h2d"] == 0, (s["step"], [op for op, _ in s["seq"] if "lift_fresh" in op])
        assert s["work"] <= BUDGET[s["kind"]], (s["step"], s["kind"], s["work"])
    # the same ops at the same shapes in every step of a kind (step 0 also builds what the first step builds; a
    # step whose windows open an epoch also sends that epoch's order to the device)
    n, batch = tr.windows.shape[0], cfg.train.batch
    by_kind: dict[str, list] = {}
    for s in steps[1:]:
        if (s["step"] * batch) // n != ((s["step"] - 1) * batch) // n:
            continue
        seq = s["seq"]
        if (s["step"] + 1) % 5 == 0:  # a log step: its reads come after the step's own ops
            assert s["kind"] in by_kind
            seq = seq[:len(by_kind[s["kind"]])]
        if s["kind"] in by_kind:
            assert seq == by_kind[s["kind"]], f"step {s['step']} ({s['kind']}) runs other ops than the first"
        else:
            by_kind[s["kind"]] = seq
    assert set(by_kind) == {"plain", "path", "r1", "r1+path"}


def test_losses_read_at_log_steps_equal_losses_read_every_step(proc_data, tmp_path):
    n = 5
    every = make_trainer(proc_data, tmp_path / "a")  # log_every 1: read after every step
    seen: list[dict[str, float]] = []
    every._after_step = lambda losses: seen.append(losses)
    every.train(n)
    lazy = make_trainer(proc_data, tmp_path / "b", cfg=tiny_cfg(**{"train.log_every": 1000}))
    kept: list[dict[str, torch.Tensor]] = []
    step = lazy.run_step

    def keep():
        out = step()
        kept.append({k: v.clone() for k, v in out.items()})
        return out

    lazy.run_step = keep
    lazy.train(n)
    read = [training.read_losses(k) for k in kept]
    assert len(seen) == n and all(s is not None for s in seen)
    for i, (a, b) in enumerate(zip(seen, read)):
        assert {k: a[k] for k in b} == b, i
    assert lazy.last_losses == every.last_losses
    sa, sb = full_state(every), full_state(lazy)
    assert [k for k in sa if not torch.equal(sa[k], sb[k])] == []


# --------------------------------------------------------------------------------------------- old checkpoints
def _check_digest(tr: Trainer, want: dict, what: str) -> None:
    import hashlib

    assert tr.step == want["step"]
    assert hashlib.sha256(torch.get_rng_state().numpy().tobytes()).hexdigest() == want["rng_sha256"], what
    state = full_state(tr)
    assert sorted(state) == sorted(want["tensors"]), what
    for k, v in state.items():
        d = v.detach().double().flatten()
        got = torch.tensor([float(d.sum()), float(d.abs().sum()), *[float(x) for x in d[:3]]], dtype=torch.float64)
        torch.testing.assert_close(got, torch.tensor(want["tensors"][k], dtype=torch.float64), rtol=1e-4,
                                   atol=1e-5, msg=f"{what}: {k}")


def test_a_checkpoint_from_before_resumes_as_it_did(proc_data, tmp_path):
    before = json.loads(FIXTURE.read_text())
    cfg = tiny_cfg(**{"train.mixing": 0.0})
    tr = make_trainer(proc_data, tmp_path, cfg=cfg)
    tr.train(2)
    _check_digest(tr, before["at_2"], "the state at step 2 (the checkpoint the old code wrote)")
    ckpt = load_checkpoint(tmp_path / "checkpoint.pt")
    assert all(g["capturable"] is False for g in ckpt["g_optim"]["param_groups"])
    for opt in ("g_optim", "d_optim"):  # as a CUDA run would have saved it: the flag must not come back
        for g in ckpt[opt]["param_groups"]:
            g["capturable"] = True
    resumed = make_trainer(proc_data, tmp_path / "b", cfg=cfg, resume=ckpt)
    assert all(not g["capturable"] for opt in (resumed.g_optim, resumed.d_optim) for g in opt.param_groups)
    resumed.train(4)
    _check_digest(resumed, before["at_4"], "the state after resuming to step 4")
    got = {k: v for k, v in resumed.last_losses.items() if k != "sec_per_iter"}
    assert got.keys() == before["losses_4"].keys()
    for k, v in before["losses_4"].items():
        assert got[k] == pytest.approx(v, rel=1e-4, abs=1e-6), k
    # with mixing (the default) the same checkpoint resumes too
    mixed = make_trainer(proc_data, tmp_path / "c", resume=tmp_path / "checkpoint.pt")
    mixed.train(4)
    assert mixed.step == 4 and all(torch.isfinite(v).all() for v in full_state(mixed).values())


def test_mixing_by_index_tensor_equals_the_listed_form(proc_data, tmp_path):
    tr = make_trainer(proc_data, tmp_path)
    G = tr.G
    w1, w2 = torch.randn(3, 16), torch.randn(3, 16)
    for i in range(1, G.n_latent):
        assert torch.equal(G.make_wplus([w1, w2], torch.tensor(i)), G.make_wplus([w1, w2], i))
    assert torch.equal(G.make_wplus([w1, w2], torch.tensor(G.n_latent)), G.make_wplus(w1))


def test_device_indices_follow_the_step_stream(proc_data, tmp_path):
    tr = make_trainer(proc_data, tmp_path)
    n = tr.windows.shape[0]
    for step in range(0, 3 * n):
        want = shard_indices(n, tr.cfg.train.batch, 1, 0, tr.cfg.train.seed, step)
        assert torch.equal(tr._device_indices(step), want), step
    uploads = []
    orig = training._epoch_order
    try:
        training._epoch_order = lambda *a: (uploads.append(a), orig(*a))[1]
        tr._orders.clear()
        tr._stream = None
        for step in range(0, 40 * n // tr.cfg.train.batch):
            tr._device_indices(step)
    finally:
        training._epoch_order = orig
    assert len(uploads) <= 41  # one new epoch order per epoch (and the one after the first)


def test_normaliser_statistics_are_made_once_per_device():
    norm = Normalizer(torch.zeros(2, 3), torch.ones(2, 3))
    x = torch.randn(4, 2, 3, 5, dtype=torch.float64)
    a, b = norm._stats(x), norm._stats(x)
    assert a[0] is b[0] and a[1] is b[1] and a[0].dtype == torch.float64
    norm.mean.add_(1.0)  # changed in place: made again
    assert torch.equal(norm.denormalize(torch.zeros_like(x)), torch.ones_like(x))


# --------------------------------------------------------------------------------------------- non-finite losses
def _nan_at(steps: set[int], tr: Trainer, monkeypatch) -> None:
    real = training.d_logistic_loss

    def loss(real_pred, fake_pred):
        out = real(real_pred, fake_pred)
        return out * float("nan") if tr.step in steps else out

    monkeypatch.setattr(training, "d_logistic_loss", loss)


def test_a_non_finite_step_is_skipped_and_reported(proc_data, tmp_path, monkeypatch):
    lines: list[str] = []
    tr = make_trainer(proc_data, tmp_path, cfg=tiny_cfg(**{"train.log_every": 2}), log=lines.append)
    tr.train(1)
    _nan_at({1}, tr, monkeypatch)
    d_before = {k: v.clone() for k, v in tr.D.state_dict().items()}
    steps_before = [tr.d_optim.state[p]["step"].clone() for p in tr.D.parameters()]
    tr.run_step()  # step 1: D's update skipped
    assert all(torch.equal(v, tr.D.state_dict()[k]) for k, v in d_before.items())
    assert all(torch.equal(a, tr.d_optim.state[p]["step"]) for a, p in zip(steps_before, tr.D.parameters()))
    res = tr.train(4)
    assert res.step == 4 and all(torch.isfinite(v).all() for v in full_state(tr).values())
    assert any("skipped 1 step(s) with a non-finite loss" in line for line in lines), lines
    logged = [json.loads(x) for x in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [(r["step"], r.get("skipped")) for r in logged] == [(1, None), (4, 1.0)], logged


def test_non_finite_steps_in_a_row_stop_without_a_checkpoint(proc_data, tmp_path, monkeypatch):
    tr = make_trainer(proc_data, tmp_path, cfg=tiny_cfg(**{"train.ckpt_every": 1}))
    tr.train(1)
    _nan_at(set(range(2, 100)), tr, monkeypatch)
    with pytest.raises(NonFiniteLossError, match=r"non-finite loss \(d\) at step 2: training stopped without "
                                                 r"writing a checkpoint; the last good checkpoint is"):
        tr.train(50)
    assert tr.step == 2 + NONFINITE_STEPS
    # none written at the stop; those of the skipped steps hold the finite weights of step 2 (nothing was applied)
    ckpt = load_checkpoint(tmp_path / "checkpoint.pt")
    assert ckpt["step"] == 1 + NONFINITE_STEPS
    assert all(torch.isfinite(v).all() for k in ("G", "D", "G_ema") for v in ckpt[k].values() if v.is_floating_point())
