"""Training in bf16 (docs/precision.md): ``--precision`` / ``precision=``, its record in the checkpoint and in
``modi info``, resume (keep or switch), one error for a bad value, the non-finite guard, fp32 weights after a bf16
step, and the first step's losses in bf16 against fp32's (tiny models on the procedural clips)."""
from __future__ import annotations

import json
import math

import pytest
import torch

from modi.api import training as api
from modi.api.info import inspect
from modi.cli import main
from modi.errors import UserError
from modi.models.ganimator.config import preset as ganimator_preset
from modi.models.ganimator.data import load_sequences
from modi.models.ganimator.training import Trainer as GanimatorTrainer
from modi.models.ganimator.training import read_checkpoint
from modi.models.modi.checkpoint import load_checkpoint
from modi.models.modi.config import MoDiConfig, make_config
from modi.models.modi.training import NonFiniteLossError, Trainer, prepare_data, write_procedural_data

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TINY = {"model.channels": (8, 8, 8, 6, 6), "model.latent_dim": 16, "model.n_mlp": 2, "data.n_frames": 16,
        "data.stride": 8, "train.batch": 4, "train.sample_every": 0, "train.ckpt_every": 0, "train.log_every": 1,
        "train.d_reg_every": 2, "train.g_reg_every": 2, "train.snapshot_every": 0}
U = 2.0 ** -8  # bf16's unit roundoff: 8 significand bits, round to nearest
GAN_TINY = {"iterations": 2, "d_steps": 1, "max_levels": 4, "fake_pool": 4, "seed": 0, "checkpoint_every": 1e9}


def tiny_cfg(**kw) -> MoDiConfig:
    return make_config("small", **{**TINY, **kw})


@pytest.fixture(scope="module")
def proc_dir(tmp_path_factory):
    return write_procedural_data(tmp_path_factory.mktemp("proc") / "data", n_clips=6, frames=40, seed=1)


@pytest.fixture(scope="module")
def proc_data(proc_dir):
    return prepare_data(proc_dir, tiny_cfg(), cache=False)


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """One procedural BVH clip for GANimator."""
    folder = write_procedural_data(tmp_path_factory.mktemp("clip") / "data", n_clips=1, frames=120, seed=1)
    return sorted(folder.glob("*.bvh"))[0]


def make_trainer(data, run_dir, cfg=None, **kw) -> Trainer:
    kw = {"progress": False, "tensorboard": False, "write_samples": False, **kw}
    return Trainer(cfg or tiny_cfg(), data, run_dir, **kw)


def full_state(tr: Trainer) -> dict[str, torch.Tensor]:
    out = {}
    for name, module in (("G", tr.G), ("D", tr.D), ("G_ema", tr.G_ema)):
        out.update({f"{name}.{k}": v.detach().clone() for k, v in module.state_dict().items()})
    for name, opt in (("g_opt", tr.g_optim), ("d_opt", tr.d_optim)):
        for pid, st in opt.state_dict()["state"].items():
            out.update({f"{name}.{pid}.{k}": torch.as_tensor(v).clone() for k, v in st.items()})
    out["mean_path_length"] = tr.mean_path_length.clone()
    return out


def float_tensors(obj) -> list[torch.Tensor]:
    """Every floating tensor inside a checkpoint's nested containers."""
    if isinstance(obj, torch.Tensor):
        return [obj] if obj.is_floating_point() else []
    if isinstance(obj, dict):
        return [t for v in obj.values() for t in float_tensors(v)]
    if isinstance(obj, (list, tuple)):
        return [t for v in obj for t in float_tensors(v)]
    return []


def _without_precision(src, dst) -> None:
    """A copy of a checkpoint written by today's code without the precision record: what an older modi wrote."""
    st = torch.load(src, weights_only=True)
    del st["precision"]
    torch.save(st, dst)


# --------------------------------------------------------------------------------------------- the option
def test_cli_passes_precision_to_the_api(monkeypatch, tmp_path, clip):
    got = {}

    class Result:
        exit_code = 0

    def fake_modi(*args, **kw):
        got["modi"] = kw.get("precision")
        return Result()

    def fake_ganimator(*args, **kw):
        got["ganimator"] = kw.get("precision")

    monkeypatch.setattr(api, "run_modi_training", fake_modi)
    monkeypatch.setattr(api, "train_ganimator", fake_ganimator)
    assert main(["train", "procedural", "--out", str(tmp_path / "m"), "--precision", "bf16"]) == 0
    assert got["modi"] == "bf16"
    assert main(["train", "procedural", "--out", str(tmp_path / "m2")]) == 0
    assert got["modi"] is None  # unset: a resume keeps its checkpoint's, a new run is fp32
    assert main(["ganimator", "train", str(clip), "--out", str(tmp_path / "g"), "--precision", "bf16", "--quiet"]) == 0
    assert got["ganimator"] == "bf16"


@pytest.mark.parametrize("argv", [["train", "procedural", "--out", "{out}", "--precision", "fp16"],
                                  ["ganimator", "train", "{clip}", "--out", "{out}", "--precision", "half"]])
def test_bad_precision_is_one_line_exit_2(argv, tmp_path, clip, capsys):
    out = tmp_path / "out"
    rc = main([a.format(out=out, clip=clip) for a in argv])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert rc == 2 and len(err) == 1, err
    assert "argument --precision: invalid choice" in err[0] and "fp32" in err[0] and "bf16" in err[0]
    assert not out.exists()


def test_bad_precision_in_python_is_one_user_error_before_any_work(tmp_path, clip):
    with pytest.raises(UserError, match=r"precision 'fp16': choose one of fp32, bf16"):
        api.train_modi("procedural", tmp_path / "m", precision="fp16")
    with pytest.raises(UserError, match=r"precision 'half': choose one of fp32, bf16"):
        api.train_ganimator(clip, tmp_path / "g", preset="tiny", precision="half")
    assert not (tmp_path / "m").exists() and not (tmp_path / "g").exists()


# --------------------------------------------------------------------------------------------- MoDi
def test_precision_is_stored_shown_and_kept_or_switched_on_resume(proc_dir, tmp_path, capsys):
    run = tmp_path / "run"
    lines: list[str] = []
    api.train_modi(proc_dir, run, config={**TINY, "train.iters": 2}, precision="bf16", log=lines.append)
    assert load_checkpoint(run / "checkpoint.pt")["precision"] == "bf16"
    assert any("precision bf16" in line for line in lines)
    info = inspect(run)
    assert info.precision == "bf16" and "precision:   trained in bf16" in str(info)
    assert main(["info", str(run), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["precision"] == "bf16"

    lines.clear()  # no precision given: the checkpoint's is kept, and nothing is said about a switch
    api.train_modi(proc_dir, run, config={"train.iters": 3}, resume=True, log=lines.append)
    assert load_checkpoint(run / "checkpoint.pt")["precision"] == "bf16"
    assert not any("continuing in" in line for line in lines) and any("precision bf16" in line for line in lines)

    lines.clear()  # given: the run switches to it and says so
    api.train_modi(proc_dir, run, config={"train.iters": 4}, resume=True, precision="fp32", log=lines.append)
    st = load_checkpoint(run / "checkpoint.pt")
    assert st["precision"] == "fp32" and st["step"] == 4
    assert any("trained in bf16; continuing in fp32 as asked" in line for line in lines), lines


def test_checkpoint_without_the_field_reads_as_fp32_and_resumes_exactly_as_before(proc_data, tmp_path):
    straight = make_trainer(proc_data, tmp_path / "a")
    straight.train(4)
    expect = full_state(straight)

    first = make_trainer(proc_data, tmp_path / "b")
    first.train(2)
    old = tmp_path / "old.pt"
    _without_precision(tmp_path / "b" / "checkpoint.pt", old)
    info = inspect(old)
    assert info.precision == "fp32" and "trained in fp32" in str(info)
    del first
    resumed = make_trainer(proc_data, tmp_path / "b", resume=old)
    assert resumed.precision == "fp32" and resumed.step == 2
    resumed.train(4)
    got = full_state(resumed)
    bad = [k for k in expect if not torch.equal(expect[k], got[k])]
    assert not bad, f"differs after resume: {bad[:5]}"
    assert load_checkpoint(tmp_path / "b" / "checkpoint.pt")["precision"] == "fp32"


def test_bf16_resume_equals_an_uninterrupted_bf16_run(proc_data, tmp_path):
    straight = make_trainer(proc_data, tmp_path / "a", precision="bf16")
    straight.train(4)
    first = make_trainer(proc_data, tmp_path / "b", precision="bf16")
    first.train(2)
    del first
    resumed = make_trainer(proc_data, tmp_path / "b", resume=tmp_path / "b" / "checkpoint.pt")
    assert resumed.precision == "bf16"
    resumed.train(4)
    expect, got = full_state(straight), full_state(resumed)
    bad = [k for k in expect if not torch.equal(expect[k], got[k])]
    assert not bad, f"differs after resume: {bad[:5]}"


def test_bf16_steps_leave_finite_fp32_weights_and_checkpoint(proc_data, tmp_path):
    fp32 = make_trainer(proc_data, tmp_path / "a")
    bf16 = make_trainer(proc_data, tmp_path / "b", precision="bf16")
    fp32.train(2)  # step 0 runs R1 and path length (d_reg_every = g_reg_every = 2), step 1 neither
    bf16.train(2)
    for name, t in full_state(bf16).items():
        if t.is_floating_point():
            assert t.dtype == torch.float32 and bool(torch.isfinite(t).all()), name
    st = load_checkpoint(tmp_path / "b" / "checkpoint.pt")
    assert st["precision"] == "bf16"
    assert {t.dtype for k in ("G", "G_ema", "D", "g_optim", "d_optim") for t in float_tensors(st[k])} == \
        {torch.float32}
    # bf16 did run: the same seeds and data give other weights than fp32's
    assert not torch.equal(fp32.G.mapping.net[1].weight, bf16.G.mapping.net[1].weight)


def _weighted_layer_calls(net: torch.nn.Module, run) -> int:
    """How many calls of a layer holding a weight matrix (a convolution or linear: what autocast rounds to bf16)
    ``run()`` makes in ``net``: an upper bound on the weighted layers any output passes through."""
    calls = [0]

    def count(*_):
        calls[0] += 1

    hooks = [m.register_forward_hook(count) for m in net.modules()
             if any(p.ndim >= 2 for p in m.parameters(recurse=False))]
    try:
        with torch.no_grad():
            run()
    finally:
        for h in hooks:
            h.remove()
    return calls[0]


def test_first_step_losses_agree_with_fp32_within_bf16_rounding(proc_data, tmp_path):
    """One step from the same weights, seeds and data (learning rate 0, so every loss of the step sees the initial
    weights) in fp32 and bf16. First-order rounding model: a weighted layer under autocast rounds its two operands
    to bf16, each within U relative, so an output that passed n such layers is within 2nU of fp32's, and so are the
    adversarial and touch losses (means of Lipschitz-1 functions of it); R1, the squared norm of a gradient that runs
    D forward and back, within 2 * 2 * 2nU. n is counted, not chosen. The path-length term runs in fp32 in both
    (docs/precision.md): equal. The contact term, a difference of nearby foot positions, has no bound from rounding
    alone (its condition number is position over displacement): checked finite."""
    cfg = tiny_cfg(**{"train.lr": 0.0})
    a = make_trainer(proc_data, tmp_path / "a", cfg=cfg).train_step()
    tr = make_trainer(proc_data, tmp_path / "b", cfg=cfg, precision="bf16")
    b = tr.train_step()
    zs = [torch.randn(cfg.train.batch, cfg.model.latent_dim)]
    n_g = _weighted_layer_calls(tr.G, lambda: tr.G(zs))
    n_d = _weighted_layer_calls(tr.D, lambda: tr.D(tr.G(zs)))
    bound = {"d": 2 * (n_g + n_d) * U, "g": 2 * (n_g + n_d) * U, "touch": 2 * n_g * U, "r1": 8 * n_d * U}
    assert set(bound) | {"path", "path_length", "contact"} <= set(a)
    for name, tol in bound.items():
        assert math.isfinite(b[name]) and abs(b[name] - a[name]) <= tol * abs(a[name]), (name, a[name], b[name], tol)
    assert b["path"] == a["path"] and b["path_length"] == a["path_length"]
    assert math.isfinite(b["contact"])
    assert b["real_score"] != a["real_score"]  # bf16 did run


def test_nonfinite_guard_stops_a_bf16_run_without_a_poisoned_checkpoint(proc_data, tmp_path):
    tr = make_trainer(proc_data, tmp_path, cfg=tiny_cfg(**{"train.ckpt_every": 1}), precision="bf16")
    tr.train(1)
    assert load_checkpoint(tmp_path / "checkpoint.pt")["step"] == 1
    with torch.no_grad():
        tr.D.final_linear[1].bias.fill_(float("nan"))
    with pytest.raises(NonFiniteLossError, match="at step 1"):
        tr.train(3)
    st = load_checkpoint(tmp_path / "checkpoint.pt")
    assert st["step"] == 1 and torch.isfinite(st["D"]["final_linear.1.bias"]).all()


# --------------------------------------------------------------------------------------------- GANimator
def test_ganimator_precision_is_stored_shown_kept_and_switched(clip, tmp_path):
    run = tmp_path / "run"
    lines: list[str] = []
    # two blocks of two levels; max_minutes ~0 pauses (checkpointed) after the first iteration
    api.train_ganimator(clip, run, preset="tiny", precision="bf16", max_minutes=1e-9, log=lines.append, **GAN_TINY)
    ck = read_checkpoint(run)
    assert ck["precision"] == "bf16" and ck["state"]["iteration"] == 1
    assert {t.dtype for t in float_tensors([ck["model"]["gens"], ck["discs"], ck["opt_g"], ck["opt_d"],
                                            ck["pools"]])} == {torch.float32}
    assert any(ck["pools"]) and all(bool(torch.isfinite(t).all()) for t in float_tensors(ck["model"]["gens"]))
    assert inspect(run).precision == "bf16" and "trained in bf16" in str(inspect(run))

    lines.clear()  # kept
    api.train_ganimator(clip, run, preset="tiny", resume=True, max_minutes=1e-9, log=lines.append, **GAN_TINY)
    assert read_checkpoint(run)["precision"] == "bf16"
    assert any("in bf16" in line for line in lines) and not any("as asked" in line for line in lines)

    lines.clear()  # switched, and said
    api.train_ganimator(clip, run, preset="tiny", resume=True, precision="fp32", log=lines.append, **GAN_TINY)
    assert read_checkpoint(run)["precision"] == "fp32"
    assert any("was trained in bf16; continuing in fp32 as asked" in line for line in lines), lines

    old = tmp_path / "old.ckpt"
    _without_precision(run / "ganimator.ckpt", old)
    assert inspect(old).precision == "fp32"


def test_ganimator_nonfinite_guard_under_bf16(clip, tmp_path):
    cfg = ganimator_preset("tiny", **GAN_TINY)
    tr = GanimatorTrainer(load_sequences([clip], cfg), cfg, tmp_path, precision="bf16")
    with torch.no_grad():
        next(tr.model.discs[0].parameters()).fill_(float("nan"))
    with pytest.raises(NonFiniteLossError, match="non-finite loss"):
        tr.run(progress=False, log=None)
    assert not (tmp_path / "ganimator.ckpt").exists()
