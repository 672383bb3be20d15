"""`python -m modi_ext.validate --out DIR` (issue 51, item 1): the measurements of one device call, proven on the CPU.

The dry run runs every stage of ``benchmarks/gpu_measure.py`` on the CPU at tiny sizes and each writes its JSON with
the precision settings; on the GPU path a stage killed or crashed still leaves a JSON saying so (its partial figures
kept), the order and the TF32-off pass are as documented, and without a GPU the command says so in one line.
"""
from __future__ import annotations

import json
import types

import pytest
import torch

from modi_ext import validate

PRECISION_KEYS = {"matmul_allow_tf32", "cudnn_allow_tf32", "cudnn_benchmark"}


def _read(path):
    return json.loads(path.read_text(encoding="utf-8"))


def test_dry_run_writes_every_stage_json_with_the_precision_settings(tmp_path):
    """Every stage's plumbing on the CPU (tiny sizes, one process): each writes ``<stage>.json`` with the precision
    settings before and after its work; a stage that needs CUDA (or data not here) says why."""
    assert validate.measure(tmp_path, budget=240, dry_run=True) == 0
    summary = _read(tmp_path / "summary.json")
    assert set(summary["stages"]) == set(validate.MEASURE_STAGES) and summary["verdict"] == "ok"
    assert PRECISION_KEYS <= set(summary["precision_defaults"])
    for stage in validate.MEASURE_STAGES:
        rec = _read(tmp_path / f"{stage}.json")
        assert rec["stage"] == stage and rec["device"] == "cpu" and rec["tf32"] == "default"
        assert PRECISION_KEYS <= set(rec["precision"]), stage
        assert rec["status"] in ("pass", "skipped"), (stage, rec.get("error"), rec.get("traceback"))
        if rec["status"] == "skipped":
            assert rec["reason"], stage
        else:
            assert PRECISION_KEYS <= set(rec["precision_after"]), stage
    for stage in ("build", "cuda_tests"):  # the command a GPU would run is in the reason
        rec = _read(tmp_path / f"{stage}.json")
        assert rec["status"] == "skipped" and "no CUDA" in rec["reason"]
    assert "build_ext --inplace" in _read(tmp_path / "build.json")["reason"]
    assert "-m cuda" in _read(tmp_path / "cuda_tests.json")["reason"]
    step = _read(tmp_path / "modi_step.json")
    if step["status"] == "pass":  # the Bandai data is here
        assert step["eager"]["2"]["cycle_mean_s"] > 0
        assert step["graphed"]["status"] in ("not available", "skipped")
        assert _read(tmp_path / "sampling.json")["motions_per_s"] > 0
        prof = _read(tmp_path / "profile.json")["kinds"]
        assert prof and all(k["aten_events"] > 0 and "gpu_busy_fraction" in k for k in prof.values())
    kern = _read(tmp_path / "kernels.json")  # issue 52's GPU rows; on the CPU the tensor-core switch changes nothing
    assert kern["status"] == "pass" and len(kern["cases"]) == 4, kern
    for case in kern["cases"].values():
        assert set(case["ms"]) == {"ext", "ext_mma", "dense", "ref"} and case["mma_vs_ext_max_rel_diff"] == 0.0
        assert case["ext_vs_ref_max_rel_diff"] < (0.05 if case["dtype"] == "bf16" else 1e-4), case
    peer = _read(tmp_path / "peer_modi_step.json")
    if peer["status"] == "pass":  # the authors' code ran on the CPU, with the stand-in ops
        assert peer["evidence"]["op_module"] == "modi stand-in"
        assert peer["eager"]["2"]["their_g_ema_device"] == "cpu"


def test_measure_plan_runs_defaults_first_then_tf32_off():
    both = validate.measure_plan("both")
    assert [s for s, m, _ in both if m == "default"] == list(validate.MEASURE_STAGES)
    assert [s for s, m, _ in both if m == "off"] == list(validate.MEASURE_TIMED)
    assert [m for _, m, _ in both] == ["default"] * len(validate.MEASURE_STAGES) + ["off"] * len(validate.MEASURE_TIMED)
    assert {m for _, m, _ in validate.measure_plan("off")} == {"off"}
    assert {m for _, m, _ in validate.measure_plan("default")} == {"default"}
    assert validate.measure_file(validate.ROOT, "modi_step", "off").name == "modi_step_tf32off.json"


def test_a_killed_or_crashed_stage_still_leaves_its_json(tmp_path, monkeypatch):
    """The GPU path with the stages faked: one killed at its limit after writing partial figures, one that dies
    without writing, one that writes its own result; each JSON has the precision settings of its pass."""
    seen = []

    def fake_group(cmd, timeout_s, env=None, cwd=None):
        stage, mode = cmd[2], cmd[cmd.index("--tf32") + 1]
        seen.append((stage, mode, timeout_s))
        path = validate.measure_file(tmp_path, stage, mode)
        if stage == "modi_step":
            path.write_text(json.dumps({"stage": stage, "status": "running", "precision": {"x": 1},
                                        "eager": {"16": {"cycle_mean_s": 0.1}}}))
            return None, "killed", True
        if stage == "sampling":
            path.write_text(json.dumps({"stage": stage, "status": "pass", "precision": {"y": 2}}))
            return 0, "", False
        return 1, "Traceback: boom", False

    monkeypatch.setattr(validate, "run_group", fake_group)
    monkeypatch.setattr(validate, "no_gpu_message", lambda: None)
    monkeypatch.setattr(torch.cuda, "get_device_properties",
                        lambda i: types.SimpleNamespace(name="Fake GPU", multi_processor_count=132))
    assert validate.measure(tmp_path, budget=1000, tf32="both") == 1
    assert [(s, m) for s, m, _ in seen] == [(s, m) for s, m, _ in validate.measure_plan("both")]
    killed = _read(tmp_path / "modi_step.json")
    assert killed["status"] == "timeout" and killed["partial"]["eager"]["16"]["cycle_mean_s"] == 0.1
    assert killed["precision"] == {"x": 1}  # the stage's own record of what it ran under
    assert _read(tmp_path / "sampling.json")["status"] == "pass"
    died = _read(tmp_path / "build.json")
    assert died["status"] == "fail" and "boom" in died["tail"] and PRECISION_KEYS <= set(died["precision"])
    off = _read(tmp_path / "ganimator_tf32off.json")
    assert off["tf32"] == "off" and off["precision"]["matmul_allow_tf32"] is False
    assert off["precision"]["cudnn_allow_tf32"] is False
    summary = _read(tmp_path / "summary.json")
    assert summary["gpu"] == "Fake GPU" and summary["verdict"] == "fail"
    assert summary["stages"]["modi_step"]["status"] == "timeout" and "ganimator_tf32off" in summary["stages"]


def test_a_spent_budget_skips_the_rest_with_a_json_each(tmp_path, monkeypatch):
    clock = iter(range(0, 10_000, 100))  # every stage "takes" 100 s of a 250 s budget
    monkeypatch.setattr(validate.time, "perf_counter", lambda: float(next(clock)))
    monkeypatch.setattr(validate, "run_group", lambda cmd, t, env=None, cwd=None: (1, "", False))
    monkeypatch.setattr(validate, "no_gpu_message", lambda: None)
    monkeypatch.setattr(torch.cuda, "get_device_properties",
                        lambda i: types.SimpleNamespace(name="Fake GPU", multi_processor_count=132))
    validate.measure(tmp_path, budget=250, tf32="default")
    last = _read(tmp_path / "profile.json")
    assert last["status"] == "skipped" and last["reason"] == "time budget spent"
    assert PRECISION_KEYS <= set(last["precision"])


def test_out_without_a_gpu_says_so_in_one_line(tmp_path, capsys):
    if torch.cuda.is_available():
        pytest.skip("a GPU is visible here")
    assert validate.main(["--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("validate: ") and "--dry-run" in err
    assert "no GPU" in _read(tmp_path / "summary.json")["error"]
