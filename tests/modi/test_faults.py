"""Faults a long training run meets (issue 22), for ``modi train``, ``modi ganimator train`` and ``modi encoder train``:
SIGTERM at a random moment (exit 143, a checkpoint, and resuming gives the same parameters as an uninterrupted
run), a full disk and a read-only folder (exit 2, one line, the old checkpoint loads), a second run into a held
folder (exit 2 naming the holder), a stale lock of a killed process, SIGKILL during a save, DDP ranks stopping
together. Tiny models, one thread; the signalled runs are real ``python -m modi`` processes.

The SIGTERM moment is random: set MODI_FAULTS_SEED to replay one (failures print it).
"""
from __future__ import annotations

import errno
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import pytest
import torch

from modi import faults
from modi.cli import main

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SEED = int(os.environ.get("MODI_FAULTS_SEED", time.time_ns() % 100_000))
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
MODI = [sys.executable, "-m", "modi"]
SMALL = ["--preset", "small", "--frames", "16", "--batch", "2", "--no-tensorboard", "--sample-every", "0",
         "--no-cache", "--threads", "1"]
GAN = ["--preset", "tiny", "--iterations", "30", "--base-channels", "16", "--d-steps", "1", "--threads", "1",
       "--quiet"]
ENC = ["--batch", "4", "--eval-every", "0", "--ckpt-every", "0", "--quiet", "--threads", "1", "--no-cache"]


# --------------------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def mdata(tmp_path_factory) -> Path:
    from modi.models.modi.training import write_procedural_data

    return write_procedural_data(tmp_path_factory.mktemp("faults") / "mdata", n_clips=6, frames=40, seed=1)


@pytest.fixture(scope="module")
def gbvh(tmp_path_factory) -> Path:
    from modi.models.modi.training import write_procedural_data

    return next(write_procedural_data(tmp_path_factory.mktemp("faults") / "g", n_clips=1, frames=60).glob("*.bvh"))


@pytest.fixture(scope="module")
def gen_ckpt(mdata, tmp_path_factory) -> Path:
    """A one-step MoDi generator checkpoint for the encoder to invert."""
    run = tmp_path_factory.mktemp("faults") / "gen"
    assert main(["train", str(mdata), "--out", str(run), "--iters", "1", *SMALL]) == 0
    return run / "checkpoint.pt"


def _train_argv(kind: str, out: Path, mdata: Path, gbvh: Path, gen_ckpt: Path | None, *extra: str) -> list[str]:
    if kind == "modi":
        return ["train", str(mdata), "--out", str(out), *SMALL, *extra]
    if kind == "ganimator":
        return ["ganimator", "train", str(gbvh), "--out", str(out), *GAN, *extra]
    return ["encoder", "train", str(gen_ckpt), str(mdata), "--out", str(out), *ENC, *extra]


# --------------------------------------------------------------------------------------------- helpers
def _lines(path: Path) -> int:
    try:
        return path.read_bytes().count(b"\n")
    except FileNotFoundError:
        return 0


def _start(argv: list[str], tmp_path: Path, name: str) -> tuple[subprocess.Popen, Path]:
    err = tmp_path / f"{name}.stderr"
    proc = subprocess.Popen(MODI + argv, stdout=subprocess.DEVNULL, stderr=open(err, "wb"), env=ENV)
    return proc, err


def _wait_for(cond, proc: subprocess.Popen, err: Path, what: str, timeout: float = 90.0) -> None:
    t = time.time()
    while not cond():
        if proc.poll() is not None:
            pytest.fail(f"process ended (rc {proc.returncode}) before {what}: {err.read_text()[-2000:]}")
        if time.time() - t > timeout:
            proc.kill()
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.01)


def _sigterm_while_stepping(proc: subprocess.Popen, err: Path, log: Path, rng: random.Random, max_lines: int) -> str:
    """SIGTERM after the run has written 1..max_lines log lines (it is stepping) plus a random fraction of a step."""
    n = rng.randint(1, max_lines)
    _wait_for(lambda: _lines(log) >= n, proc, err, f"{n} log lines in {log.name}")
    delay = rng.uniform(0.0, 0.2)
    time.sleep(delay)
    proc.send_signal(signal.SIGTERM)
    rc = proc.wait(timeout=120)
    text = err.read_text(errors="replace")
    assert rc == 143, f"seed {SEED}: rc {rc} after SIGTERM at line {n} + {delay:.3f} s: {text[-2000:]}"
    assert "SIGTERM: stopping after this" in text and "Traceback" not in text and "internal error" not in text, text
    return text


def _differences(a, b, path: str = "") -> list[str]:
    """Paths where two checkpoint trees differ (tensors bit for bit; wall-clock entries skipped)."""
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return [f"{path}: keys {sorted(set(a) ^ set(b))}"]
        return [d for k in a if k not in ("block_seconds", "sec_per_iter", "seconds")
                for d in _differences(a[k], b[k], f"{path}.{k}")]
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            return [f"{path}: length {len(a)} vs {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _differences(x, y, f"{path}[{i}]")]
    if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
        return [] if a.shape == b.shape and a.dtype == b.dtype and torch.equal(a, b) else [path]
    return [] if a == b else [f"{path}: {a!r} vs {b!r}"]


def _load(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)


def _one_error_line(err: str) -> str:
    """The stderr of a failed command, progress bars aside, must be exactly one ``modi: error:`` line."""
    assert "Traceback" not in err and "internal error" not in err, err
    lines = [ln for ln in err.replace("\r", "\n").splitlines() if ln.startswith("modi: error:")]
    assert len(lines) == 1, err
    return lines[0]


@contextmanager
def _tmpfs(path: Path, size: str):
    """A tmpfs of ``size`` at ``path`` (root only); yields False where it cannot be mounted."""
    path.mkdir(parents=True, exist_ok=True)
    ok = os.geteuid() == 0 and shutil.which("mount") is not None and subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True).returncode == 0
    try:
        yield ok
    finally:
        if ok:
            subprocess.run(["umount", "-l", str(path)], capture_output=True)


def _hold_in_other_process(folder: Path, lock_name: str = faults.LOCK_NAME) -> subprocess.Popen:
    code = ("import sys, time\nfrom modi.faults import hold_run_folder\n"
            "with hold_run_folder(sys.argv[1], sys.argv[2]):\n    print('held', flush=True)\n    time.sleep(120)\n")
    p = subprocess.Popen([sys.executable, "-c", code, str(folder), lock_name], stdout=subprocess.PIPE, env=ENV)
    assert p.stdout.readline().strip() == b"held"
    return p


# --------------------------------------------------------------------------------------------- SIGTERM + resume
def test_modi_sigterm_saves_and_resume_equals_uninterrupted(mdata, tmp_path, capsys):
    rng = random.Random(SEED)
    iters = ["--iters", "24", "--log-every", "1", "--ckpt-every", "5"]  # the signal may land in a save
    assert main(_train_argv("modi", tmp_path / "a", mdata, None, None, *iters)) == 0
    proc, err = _start(_train_argv("modi", tmp_path / "b", mdata, None, None, *iters), tmp_path, "b")
    _sigterm_while_stepping(proc, err, tmp_path / "b" / "log.jsonl", rng, 6)
    step = _load(tmp_path / "b" / "checkpoint.pt")["step"]
    assert 1 <= step < 24, f"seed {SEED}: stopped at step {step}"
    assert not (tmp_path / "b" / ".lock").exists()
    assert main(["train", str(mdata), "--out", str(tmp_path / "b"), "--resume", "--no-cache", "--threads", "1"]) == 0
    a, b = _load(tmp_path / "a" / "checkpoint.pt"), _load(tmp_path / "b" / "checkpoint.pt")
    assert b["step"] == 24
    diff = _differences({k: a[k] for k in ("G", "D", "G_ema", "g_optim", "d_optim", "rng", "mean_path_length")},
                        {k: b[k] for k in ("G", "D", "G_ema", "g_optim", "d_optim", "rng", "mean_path_length")})
    assert not diff, f"seed {SEED}: SIGTERM at step {step}, resumed run differs: {diff[:5]}"


def test_ganimator_sigterm_saves_and_rerun_equals_uninterrupted(gbvh, tmp_path):
    rng = random.Random(SEED + 1)
    assert main(_train_argv("ganimator", tmp_path / "a", None, gbvh, None)) == 0
    proc, err = _start(_train_argv("ganimator", tmp_path / "b", None, gbvh, None), tmp_path, "b")
    text = _sigterm_while_stepping(proc, err, tmp_path / "b" / "log.jsonl", rng, 8)
    assert "checkpoint saved to" in text
    st = _load(tmp_path / "b" / "ganimator.ckpt")["state"]
    assert (st["block"], st["iteration"]) != (4, 0), f"seed {SEED}: ran to the end before the signal"
    assert main(_train_argv("ganimator", tmp_path / "b", None, gbvh, None)) == 0  # the same command resumes
    a, b = _load(tmp_path / "a" / "ganimator.ckpt"), _load(tmp_path / "b" / "ganimator.ckpt")
    diff = _differences(a, b)
    assert not diff, f"seed {SEED}: SIGTERM at block {st['block']} iteration {st['iteration']}: {diff[:5]}"


def test_ganimator_sigterm_in_a_blocks_last_iteration_closes_the_block_first(gbvh, tmp_path):
    """The edge of the random test above, made certain: stopped in the last iteration of block 0, the run saves the
    block closed (history and all), and the rerun equals an uninterrupted run."""
    from modi.models.ganimator.config import preset
    from modi.models.ganimator.data import load_sequences
    from modi.models.ganimator.training import Trainer, TrainingInterrupted

    cfg = preset("tiny", iterations=4, base_channels=8, d_steps=1, max_levels=4, checkpoint_every=1e9)
    clips = load_sequences([str(gbvh)], cfg)
    Trainer(clips, cfg, tmp_path / "a").run(progress=False, log=None)
    tr = Trainer(clips, cfg, tmp_path / "b")
    step = tr._iteration

    def last_iteration_signalled(*a):
        if tr.state["block"] == 0 and tr.state["iteration"] == 3:
            os.kill(os.getpid(), signal.SIGTERM)
        return step(*a)

    tr._iteration = last_iteration_signalled
    with pytest.raises(TrainingInterrupted) as exc:
        tr.run(progress=False, log=None)
    assert exc.value.exit_code == 143
    st = _load(tmp_path / "b" / "ganimator.ckpt")["state"]
    assert (st["block"], st["iteration"], len(st["history"])) == (1, 0, 1)
    Trainer(clips, cfg, tmp_path / "b").run(progress=False, log=None)
    diff = _differences(_load(tmp_path / "a" / "ganimator.ckpt"), _load(tmp_path / "b" / "ganimator.ckpt"))
    assert not diff, diff[:5]


def test_encoder_sigterm_saves_and_resume_equals_uninterrupted(mdata, gen_ckpt, tmp_path):
    rng = random.Random(SEED + 2)
    assert main(_train_argv("encoder", tmp_path / "a.pt", mdata, None, gen_ckpt, "--iters", "50")) == 0
    proc, err = _start(_train_argv("encoder", tmp_path / "b.pt", mdata, None, gen_ckpt, "--iters", "50"),
                       tmp_path, "b")
    _sigterm_while_stepping(proc, err, tmp_path / "b.pt.log.jsonl", rng, 2)
    step = _load(tmp_path / "b.pt")["step"]
    assert 20 <= step < 50, f"seed {SEED}: stopped at step {step}"
    assert main(_train_argv("encoder", tmp_path / "b.pt", mdata, None, gen_ckpt, "--iters", "50", "--resume")) == 0
    a, b = _load(tmp_path / "a.pt"), _load(tmp_path / "b.pt")
    assert b["step"] == 50
    diff = _differences({k: a[k] for k in ("encoder", "optim", "rng", "metrics")},
                        {k: b[k] for k in ("encoder", "optim", "rng", "metrics")})
    assert not diff, f"seed {SEED}: SIGTERM at step {step}, resumed encoder differs: {diff[:5]}"


def test_sigterm_before_the_first_step_unwinds_cleanly(tmp_path):
    """SIGTERM while the run is still preparing its data (or just starting to step): exit 143, no traceback, the
    lock released and removed, no temp file anywhere."""
    run = tmp_path / "run"
    # a budget it cannot finish before the signal lands (5 iterations could end first on a quick machine)
    proc, err = _start(["train", "procedural", "--out", str(run), *SMALL, "--iters", "100000"], tmp_path, "a")
    try:
        _wait_for(lambda: (run / faults.LOCK_NAME).exists(), proc, err, "the run folder's lock")
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 143
    finally:  # a failed wait must not leave a 100000-step run behind on the CI machine
        if proc.poll() is None:
            proc.kill()
    text = err.read_text()
    assert "Traceback" not in text and ("modi: terminated (SIGTERM)" in text or "SIGTERM: stopping" in text), text
    assert not (run / faults.LOCK_NAME).exists() and not list(tmp_path.rglob(".*.tmp"))


@contextmanager
def _sigint_handler(handler):
    """SIGINT handled as given for the block, then whatever the process had put back: a background job (``nohup
    ... &``, a batch queue) starts with SIGINT ignored, an interactive one with Python's ``default_int_handler``."""
    before = signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)


@pytest.mark.parametrize("sig, exc", [(signal.SIGTERM, faults.Terminated), (signal.SIGINT, KeyboardInterrupt)])
def test_a_signal_while_the_lock_is_being_taken_still_removes_it(tmp_path, monkeypatch, sig, exc):
    """The race the test above hit now and then: a signal landing after the lock file is created but before the
    block that removes it. Sent from inside that window (while the holder's name is written), it waits, unwinds
    the block before its body runs, and the file is gone. (SIGINT as an interactive process handles it, however
    this test process was started.)"""
    run = tmp_path / "run"
    real = faults._command_line

    def signalled() -> str:
        assert (run / faults.LOCK_NAME).exists()  # the file exists: this is the window
        os.kill(os.getpid(), sig)
        return real()

    monkeypatch.setattr(faults, "_command_line", signalled)
    monkeypatch.setattr(faults, "_sigterm_seen", False)  # the handler sets it for the process: put it back after
    with _sigint_handler(signal.default_int_handler):
        before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
        with pytest.raises(exc):
            with faults.terminate_on_sigterm(), faults.hold_run_folder(run):
                pytest.fail("the block ran although a signal was waiting")
        assert not (run / faults.LOCK_NAME).exists()
        assert {s: signal.getsignal(s) for s in before} == before  # the handlers are put back


def test_an_ignored_sigint_while_the_lock_is_being_taken_stays_ignored(tmp_path, monkeypatch):
    """In a background job SIGINT is ignored: one arriving in the same window is dropped (the block runs), the
    lock file is still removed after it, and the handler is SIG_IGN again, not Python's default."""
    run = tmp_path / "run"
    real = faults._command_line

    def signalled() -> str:
        os.kill(os.getpid(), signal.SIGINT)
        return real()

    monkeypatch.setattr(faults, "_command_line", signalled)
    ran = []
    with _sigint_handler(signal.SIG_IGN):
        with faults.terminate_on_sigterm(), faults.hold_run_folder(run):
            ran.append(True)
        assert ran and not (run / faults.LOCK_NAME).exists()
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN


def test_a_sigterm_while_the_temp_file_is_being_made_still_removes_it(tmp_path, monkeypatch):
    """The same window in atomic_output: a SIGTERM right after the temp file is created waits for the try that
    removes it; the target keeps its previous content."""
    target = tmp_path / "out.txt"
    target.write_text("before")
    real = faults.tempfile.mkstemp

    def signalled(*args, **kwargs):
        made = real(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGTERM)
        return made

    monkeypatch.setattr(faults.tempfile, "mkstemp", signalled)
    monkeypatch.setattr(faults, "_sigterm_seen", False)
    calls = []
    with faults.terminate_on_sigterm():
        handler = signal.getsignal(signal.SIGTERM)
        signal.signal(signal.SIGTERM, lambda signum, frame: (calls.append(signum), handler(signum, frame)))
        with pytest.raises(faults.Terminated):
            faults.atomic_write(target, "after")
    assert calls == [signal.SIGTERM]  # delivered once, not again by the cleanup
    assert target.read_text() == "before" and sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_ddp_ranks_stop_together_on_one_ranks_sigterm_or_rank0s_full_disk(mdata, tmp_path):
    import torch.multiprocessing as mp

    from modi.models.modi.config import make_config
    from modi.models.modi.training import prepare_data

    cfg = make_config("small", [], **{"model.channels": (8, 8, 8, 6, 6), "model.latent_dim": 16, "model.n_mlp": 2,
                                      "data.n_frames": 16, "train.batch": 4, "train.sample_every": 0,
                                      "train.ckpt_every": 0, "train.snapshot_every": 0, "train.log_every": 1})
    data = prepare_data(mdata, cfg, cache=False)
    mp.spawn(_ddp_worker, args=(str(tmp_path / "init"), data, cfg.to_dict(), str(tmp_path)), nprocs=2, join=True)
    r0, r1 = (torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in (0, 1))
    assert r0["sigterm"] == r1["sigterm"] == {"step": 3, "interrupted": True, "exit_code": 143}, (r0, r1)
    assert _load(tmp_path / "checkpoint.pt")["step"] == 3
    # rank 0's log write fails at step 5: both ranks leave at step 6's start, rank 0 with the disk's words
    assert r0["full"] == ["OutputError", "no space left on the device writing log.jsonl", 5], r0
    assert r1["full"][0] == "UserError" and "rank 0's message" in r1["full"][1] and r1["full"][2] == 5, r1


def _ddp_worker(rank: int, init_file: str, data, cfg_dict: dict, out_dir: str) -> None:
    import torch.distributed as dist

    from modi.models.modi.config import MoDiConfig
    from modi.models.modi.training import Trainer

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=2)
    try:
        tr = Trainer(MoDiConfig.from_dict(cfg_dict), data, out_dir, progress=False, tensorboard=False,
                     write_samples=False)
        step = tr.run_step

        def step_then_signal():
            out = step()
            if rank == 1 and tr.step == 3:  # only rank 1 is told to stop, in the middle of its loop
                os.kill(os.getpid(), signal.SIGTERM)
            return out

        tr.run_step = step_then_signal
        res = tr.train(50)
        out = {"sigterm": {"step": res.step, "interrupted": res.interrupted, "exit_code": res.exit_code}}
        log = tr._log_scalars

        def log_on_a_full_disk(losses):
            if tr.step == 5:
                raise faults.OutputError("no space left on the device writing log.jsonl", errno.ENOSPC)
            log(losses)

        tr._log_scalars = log_on_a_full_disk
        try:
            tr.train(50)
            out["full"] = ["no error", "", tr.step]
        except Exception as exc:  # noqa: BLE001 - what each rank saw
            out["full"] = [type(exc).__name__, str(exc), tr.step]
        torch.save(out, Path(out_dir) / f"rank{rank}.pt")
    finally:
        dist.destroy_process_group()
    # Leave without interpreter finalisation: gloo's worker threads can still be torn down there and abort the
    # process ("terminate called without an active exception", SIGABRT; seen once in CI, pytorch/pytorch#179291
    # describes the teardown). The ranks' results are saved and closed above.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


# --------------------------------------------------------------------------------------------- full disk
def _fail_saves_after_the_first(monkeypatch) -> None:
    """Every checkpoint write after the first fails with ENOSPC, as a disk with room for one copy would."""
    made, real_init, real_write = [], faults._Recorder.__init__, faults._Recorder.write

    def init(self, f):
        real_init(self, f)
        made.append(self)

    def write(self, b):
        if self is not made[0]:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(self, b)

    monkeypatch.setattr(faults._Recorder, "__init__", init)
    monkeypatch.setattr(faults._Recorder, "write", write)


def test_full_disk_is_one_line_exit_2_and_the_previous_checkpoint_loads(mdata, tmp_path, capsys, monkeypatch):
    """A 60 MB tmpfs holds one 44 MB checkpoint but not a second copy (root); elsewhere the writer is made to fail
    with ENOSPC on the second save."""
    with _tmpfs(tmp_path / "disk", "60m") as mounted:
        if not mounted:  # every torch save after the first fails as a full disk would
            _fail_saves_after_the_first(monkeypatch)
        run = tmp_path / "disk" / "run"
        capsys.readouterr()
        rc = main(["train", str(mdata), "--out", str(run), "--iters", "4", "--ckpt-every", "2", *SMALL])
        line = _one_error_line(capsys.readouterr().err)
        assert rc == 2, line
        assert line.startswith(f"modi: error: no space left on the device writing {run / 'checkpoint.pt'}: "), line
        size = (run / "checkpoint.pt").stat().st_size
        m = re.search(r"the checkpoint needs [\d.]+ MB \((\d+) bytes\) free beside the previous one .*, "
                      r"([\d.]+) (bytes|kB|MB|GB|TB) free; ", line)
        assert m and abs(int(m[1]) - size) < 4096, (line, size)  # the new one is the old one's size, give or take
        if mounted:
            assert float(m[2]) * {"bytes": 1, "kB": 1e3, "MB": 1e6, "GB": 1e9, "TB": 1e12}[m[3]] < size, line
        assert line.endswith("the previous checkpoint (step 2) is intact"), line
        assert _load(run / "checkpoint.pt")["step"] == 2
        assert not list(run.glob(".checkpoint.pt.*")) and not (run / ".lock").exists()
        # resuming on the still-full disk says the same, and the checkpoint still loads
        rc = main(["train", str(mdata), "--out", str(run), "--resume", "--iters", "6", "--no-cache", "--threads", "1"])
        line = _one_error_line(capsys.readouterr().err)
        assert rc == 2 and "no space left on the device" in line and "(step 2) is intact" in line, line
        assert _load(run / "checkpoint.pt")["step"] == 2


@pytest.mark.parametrize("kind", ["ganimator", "encoder"])
def test_full_disk_names_the_intact_checkpoint_of_ganimator_and_encoder(kind, mdata, gbvh, gen_ckpt, tmp_path, capsys,
                                                                        monkeypatch):
    """ENOSPC injected into the second checkpoint write (the writer's own failure path: a tmpfs per trainer would
    only repeat the MoDi test): one line naming the intact checkpoint's position, exit 2, and it loads."""
    _fail_saves_after_the_first(monkeypatch)
    out = tmp_path / ("enc.pt" if kind == "encoder" else "run")
    extra = ["--iters", "3", "--ckpt-every", "1"] if kind == "encoder" else ["--block-iters", "2"]
    capsys.readouterr()
    assert main(_train_argv(kind, out, mdata, gbvh, gen_ckpt, *extra)) == 2
    line = _one_error_line(capsys.readouterr().err)
    ckpt = out if kind == "encoder" else out / "ganimator.ckpt"
    assert line.startswith(f"modi: error: no space left on the device writing {ckpt}: the checkpoint needs "), line
    where = "step 1" if kind == "encoder" else "block 2/4, iteration 0"
    assert line.endswith(f"the previous checkpoint ({where}) is intact"), line
    st = _load(ckpt)
    assert (st["step"] if kind == "encoder" else (st["state"]["block"], st["state"]["iteration"])) == \
        (1 if kind == "encoder" else (1, 0))
    assert not list(ckpt.parent.glob(f".{ckpt.name}.*"))


def test_writers_on_a_full_disk_leave_the_previous_file_whole(tmp_path, capsys):
    from torch.utils.tensorboard import SummaryWriter

    with _tmpfs(tmp_path / "disk", "256k") as mounted:
        if not mounted:
            pytest.skip("needs root and mount(8) (util-linux) for a tiny tmpfs")
        d = tmp_path / "disk"
        writer = SummaryWriter(str(d / "tb"))
        faults.atomic_write(d / "out.json", '{"old": 1}\n')
        faults.append_line(d / "log.jsonl", '{"step": 1}')
        fd = os.open(d / "filler", os.O_WRONLY | os.O_CREAT)
        try:  # fill the device to the last block
            while os.write(fd, b"\0" * 4096):
                pass
        except OSError as exc:
            assert exc.errno == errno.ENOSPC
        finally:
            os.close(fd)
        with pytest.raises(faults.OutputError, match=r"^no space left on the device writing .*out\.json$"):
            faults.atomic_write(d / "out.json", "x" * 200_000)
        assert (d / "out.json").read_text() == '{"old": 1}\n'
        with pytest.raises(faults.OutputError, match="no space left on the device writing .*log.jsonl"):
            faults.append_line(d / "log.jsonl", "y" * 100_000)
        assert (d / "log.jsonl").read_text() == '{"step": 1}\n'  # no half record appended
        with pytest.raises(faults.OutputError) as exc:
            faults.atomic_torch_save({"w": torch.zeros(100_000)}, d / "ck.pt", previous_step=7)
        assert "bytes) free beside the previous one" in str(exc.value) and "nothing was written" in str(exc.value)
        assert sorted(p.name for p in d.iterdir()) == ["filler", "log.jsonl", "out.json", "tb"]
        # TensorBoard appends from its own thread: the error comes back at add_scalar/flush as one OutputError
        with pytest.raises(faults.OutputError, match="no space left on the device writing .*tb$"):
            with faults.output_errors(d / "tb"):
                for i in range(5000):
                    writer.add_scalar("loss/d", float(i), i)
                writer.flush()
        with pytest.raises(faults.OutputError):
            with faults.output_errors(d / "tb"):
                writer.close()
        assert "Traceback" not in capsys.readouterr().err


def test_read_only_run_folder_is_one_line_exit_2(mdata, tmp_path, capsys):
    with _tmpfs(tmp_path / "ro", "100m") as mounted:
        run = tmp_path / "ro" / "run"
        assert main(["train", str(mdata), "--out", str(run), "--iters", "1", *SMALL]) == 0
        if mounted:
            assert subprocess.run(["mount", "-o", "remount,ro", str(tmp_path / "ro")]).returncode == 0
        elif os.geteuid() != 0:
            run.chmod(0o555)
        else:
            pytest.skip("root ignores folder permissions and mount(8) is unavailable")
        capsys.readouterr()
        rc = main(["train", str(mdata), "--out", str(run), "--resume", "--iters", "2", "--no-cache"])
        line = _one_error_line(capsys.readouterr().err)
        assert rc == 2 and line.startswith(f"modi: error: cannot write {run}"), line
        assert "read-only file system" in line or "permission denied" in line, line
        assert _load(run / "checkpoint.pt")["step"] == 1


# --------------------------------------------------------------------------------------------- run-folder lock
def test_second_modi_run_into_a_running_folder_is_refused_naming_the_holder(mdata, tmp_path, capsys):
    run = tmp_path / "run"
    proc, err = _start(_train_argv("modi", run, mdata, None, None, "--iters", "400", "--log-every", "1"),
                       tmp_path, "a")
    _wait_for(lambda: _lines(run / "log.jsonl") >= 1, proc, err, "the first run to step")
    config = (run / "config.json").read_bytes()
    t = time.time()
    rc = main(_train_argv("modi", run, mdata, None, None, "--iters", "2"))
    line = _one_error_line(capsys.readouterr().err)
    assert rc == 2 and time.time() - t < 5, line
    assert line.startswith(f"modi: error: {run} is in use by another run (pid {proc.pid} on "), line
    assert (run / "config.json").read_bytes() == config
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=60) == 143


@pytest.mark.parametrize("kind", ["modi", "ganimator", "encoder"])
def test_held_folder_refused_then_a_killed_holders_lock_is_no_obstacle(kind, mdata, gbvh, gen_ckpt, tmp_path,
                                                                       capsys):
    out = tmp_path / ("enc.pt" if kind == "encoder" else "run")
    folder, name = (tmp_path, ".enc.pt.lock") if kind == "encoder" else (out, faults.LOCK_NAME)
    holder = _hold_in_other_process(folder, name)
    small = {"modi": ["--iters", "1"], "ganimator": ["--block-iters", "2"], "encoder": ["--iters", "2"]}[kind]
    try:
        assert main(_train_argv(kind, out, mdata, gbvh, gen_ckpt, *small)) == 2
        line = _one_error_line(capsys.readouterr().err)
        assert f"modi: error: {out} is in use by another run (pid {holder.pid} on " in line, line
    finally:
        holder.kill()  # SIGKILL: no clean-up, the lock file stays with the dead holder's pid
        holder.wait()
    assert f"pid={holder.pid}" in (folder / name).read_text()
    assert main(_train_argv(kind, out, mdata, gbvh, gen_ckpt, *small)) == 0, capsys.readouterr().err
    assert not (folder / name).exists()  # a clean exit removes the lock file


def test_lock_is_reentrant_in_one_process_and_removed_on_exit(tmp_path):
    with faults.hold_run_folder(tmp_path / "r") as lock:
        assert f"pid={os.getpid()}" in lock.read_text()
        with faults.hold_run_folder(tmp_path / "r"):
            pass
        assert lock.exists()  # the inner exit does not release the outer hold
    assert not lock.exists()


def test_sigkill_during_a_save_leaves_the_last_checkpoint_loadable(mdata, tmp_path):
    run = tmp_path / "run"
    proc, err = _start(_train_argv("modi", run, mdata, None, None, "--iters", "400", "--ckpt-every", "1"),
                       tmp_path, "a")
    _wait_for(lambda: (run / "checkpoint.pt").is_file(), proc, err, "the first checkpoint")
    _wait_for(lambda: any(run.glob(".checkpoint.pt.*.tmp")), proc, err, "a save in progress")
    proc.kill()
    proc.wait()
    step = _load(run / "checkpoint.pt")["step"]
    assert step >= 1
    assert main(["train", str(mdata), "--out", str(run), "--resume", "--iters", str(step + 1), "--no-cache",
                 "--threads", "1"]) == 0
    assert _load(run / "checkpoint.pt")["step"] == step + 1
    assert not list(run.glob(".checkpoint.pt.*.tmp"))  # the killed save's temp file was cleared


# --------------------------------------------------------------------------------------------- the signal flag
def test_sigterm_sets_the_flag_a_second_is_ignored_and_handlers_come_back(capsys):
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    with faults.stop_on_signals("step") as stop:
        signal.raise_signal(signal.SIGTERM)
        assert stop and stop.signum == signal.SIGTERM and stop.exit_code == 143
        signal.raise_signal(signal.SIGTERM)  # a scheduler repeating itself: the save goes on
        assert stop.agreed() and stop.exit_code == 143
        with pytest.raises(KeyboardInterrupt):  # a Ctrl-C on top of it: the user insists
            signal.raise_signal(signal.SIGINT)
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
    err = capsys.readouterr().err
    assert err.count("SIGTERM: stopping after this step and saving a checkpoint") == 1, err
    with faults.stop_on_signals("step") as stop:
        signal.raise_signal(signal.SIGINT)
        assert stop.exit_code == 130


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the swallowed Terminated, on purpose
def test_a_sigterm_swallowed_by_a_finaliser_still_stops_the_run(monkeypatch):
    """Python drops an exception raised in ``__del__`` ("Exception ignored in ..."): a SIGTERM whose handler runs
    there must still stop the next training loop at its first step (before this, such a run went on to the end)."""
    monkeypatch.setattr(faults, "_sigterm_seen", False)

    class SignalsInFinaliser:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(100_000):  # the handler runs between these bytecodes, inside __del__
                pass

    with faults.terminate_on_sigterm():
        obj = SignalsInFinaliser()
        del obj  # the Terminated raised inside __del__ is printed and swallowed
        assert faults.sigterm_pending()
        with faults.stop_on_signals("step", notice=False) as stop:
            assert stop and stop.exit_code == 143
