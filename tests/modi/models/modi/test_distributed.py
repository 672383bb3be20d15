"""Training across processes and machines (issue 43), as a user on a cluster meets it: real ``torchrun`` jobs of two
CPU processes (gloo, loopback only, tiny model, one thread each) that lose a worker to ``kill -9``, are preempted by
SIGTERM or Ctrl-C, are killed whole during a checkpoint write, hang, meet a second job in their folder, or run as two
nodes with c10d rendezvous; plus the shards of the data, 2 processes x 4 = 1 x 8, the lost-peer line and
``--resume auto`` in one process.

Every job is killed with its workers at the end of its test, whatever happens; every wait has a timeout.
"""
from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from modi.cli import main
from modi.errors import PeerLostError
from modi.models.modi import distributed as mdist
from modi.models.modi.config import MoDiConfig, make_config
from modi.models.modi.distributed import shard_indices
from modi.models.modi.sampling import load_checkpoint, sample_motions
from modi.models.modi.training import Trainer, prepare_data, write_procedural_data

pytestmark = pytest.mark.usefixtures("one_torch_thread")
if not (torch.distributed.is_available() and torch.distributed.is_gloo_available()):
    pytest.skip("this torch build has no torch.distributed with gloo", allow_module_level=True)

REPO = Path(__file__).resolve().parents[4]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1",
       "PYTHONPATH": os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])}
TORCHRUN = [sys.executable, "-m", "torch.distributed.run"]
MODI_TORCHRUN = [sys.executable, "-m", "modi", "torchrun"]
SMALL = ["--preset", "small", "--frames", "16", "--batch", "2", "--no-tensorboard", "--sample-every", "0",
         "--no-cache", "--threads", "1", "--log-every", "1"]


# --------------------------------------------------------------------------------------------- helpers
@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return write_procedural_data(tmp_path_factory.mktemp("dist") / "data", n_clips=6, frames=40, seed=1)


@pytest.fixture
def jobs():
    """Start jobs; at the end kill each one's processes by their ids: the agent, and its workers (torchrun starts
    each in a session of its own, so they outlive the agent's)."""
    started: list[subprocess.Popen] = []

    def start(argv: list[str], log: Path) -> subprocess.Popen:
        proc = subprocess.Popen(argv, stdout=open(log, "ab"), stderr=subprocess.STDOUT, env=ENV,
                                start_new_session=True)
        started.append(proc)
        return proc

    yield start
    for proc in started:
        _kill(proc)


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (Linux /proc)."""
    out = []
    for name in os.listdir("/proc"):
        try:
            if name.isdigit() and int(Path(f"/proc/{name}/stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(name))
        except (OSError, IndexError, ValueError):
            continue
    return out


def _kill(proc: subprocess.Popen) -> list[int]:
    """SIGKILL the job ``proc`` (agent and workers, by their ids, as when its machine is lost) and wait for its
    workers to go; returns their pids."""
    workers = _children(proc.pid)
    for pid in (proc.pid, *workers):
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    proc.wait(timeout=30)
    t = time.time()
    while any(_running(pid) for pid in workers):  # orphans now: whoever reaps them may be slow
        assert time.time() - t < 30, f"killed workers {workers} still run"
        time.sleep(0.02)
    return workers


def _running(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except (OSError, IndexError):
        return False


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _one_node(nproc: int = 2, restarts: int = 0) -> list[str]:
    return ["--nproc-per-node", str(nproc), "--max-restarts", str(restarts), "--master-addr", "127.0.0.1",
            "--master-port", str(_port())]


def _train(data: Path, run: Path, *extra: str) -> list[str]:
    return ["-m", "modi", "train", str(data), "--out", str(run), *SMALL, *extra]


def _steps(run: Path) -> list[int]:
    try:
        return [json.loads(line)["step"] for line in (run / "log.jsonl").read_text().splitlines() if line.strip()]
    except FileNotFoundError:
        return []


def _text(log: Path) -> str:
    return log.read_text(errors="replace").replace("\r", "\n")


def _wait_for(cond, proc: subprocess.Popen, log: Path, what: str, timeout: float = 120.0) -> None:
    t = time.time()
    while not cond():
        if proc.poll() is not None:
            pytest.fail(f"job ended (rc {proc.returncode}) before {what}:\n{_text(log)[-3000:]}")
        if time.time() - t > timeout:
            pytest.fail(f"timed out waiting for {what}:\n{_text(log)[-3000:]}")
        time.sleep(0.02)


def _end(proc: subprocess.Popen, log: Path, timeout: float = 180.0) -> int:
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        pytest.fail(f"job did not end within {timeout} s:\n{_text(log)[-3000:]}")


def _workers(agent: int) -> dict[int, int]:
    """{rank: pid} of the agent's worker processes (Linux /proc)."""
    out = {}
    for pid in _children(agent):
        try:
            env = dict(kv.split("=", 1) for kv in Path(f"/proc/{pid}/environ").read_text().split("\0") if "=" in kv)
        except OSError:
            continue
        if "RANK" in env:
            out[int(env["RANK"])] = pid
    return out


def _find(pattern: str, text: str) -> str:
    """The first group of ``pattern``'s first match in ``text`` (the test fails showing the text when none)."""
    m = re.search(pattern, text)
    assert m, f"no {pattern!r} in:\n{text[-3000:]}"
    return m.group(1)


def _line(words: str, text: str) -> str:
    """The first line of ``text`` holding ``words``, from there on (the test fails showing the text when none)."""
    line = next((ln for ln in text.splitlines() if words in ln), None)
    assert line is not None, f"no line with {words!r} in:\n{text[-3000:]}"
    return line[line.index(words):]


def _no_bug(text: str) -> None:
    assert "internal error" not in text and "Traceback" not in text, text[-3000:]


def _finished(run: Path, iters: int) -> dict:
    """The run reached ``iters``: its log reads as one run (every step once, increasing) and its checkpoint loads
    and samples."""
    assert _steps(run) == list(range(1, iters + 1)), _steps(run)
    ckpt = load_checkpoint(run / "checkpoint.pt")
    assert ckpt["step"] == iters and ckpt["world_size"] == 2
    motions = sample_motions(run / "checkpoint.pt", 2, seed=0)
    assert len(motions) == 2 and motions[0].n_frames == 16
    assert not list(run.glob(".checkpoint.pt.*.tmp"))
    return ckpt


# --------------------------------------------------------------------------------------------- a lost worker
def test_kill_9_of_a_worker_restarts_from_the_newest_checkpoint_and_completes(data, tmp_path, jobs):
    """The issue's scenario: ``kill -9`` of rank 1 mid-run under ``--max-restarts 2``. Rank 0 says so in one line
    (not "internal error"), torchrun restarts both, they continue from the newest checkpoint (before issue 43 they
    refused: "checkpoint.pt exists") and the run reaches its last step, retraining at most --ckpt-every steps."""
    run, log, iters, every = tmp_path / "run", tmp_path / "job.log", 30, 10
    job = jobs([*TORCHRUN, *_one_node(restarts=2), *_train(data, run, "--iters", str(iters), "--ckpt-every",
                                                           str(every))], log)
    _wait_for(lambda: len(_steps(run)) >= 15, job, log, "step 15")
    at = _steps(run)[-1]
    os.kill(_workers(job.pid)[1], signal.SIGKILL)
    assert _end(job, log) == 0, _text(log)[-3000:]
    text = _text(log)
    _no_bug(text)
    line = _line("modi: error:", text)
    lost = int(_find(r"rank 1 \(pid \d+ on .+\) has ended at step (\d+) \(", line))
    saved = int(_find(r"the newest checkpoint, step (\d+) in \S+checkpoint.pt, is intact", line))
    assert "torchrun restarts the job from it (restart 1 of 2)" in line and "--resume auto" in line, line
    resumed = int(_find(r"continuing \S+checkpoint.pt from step (\d+)", text))
    # rank 0 had finished step `lost` when rank 1 went away: those past the checkpoint are trained again
    assert resumed == saved and at <= lost and 0 <= lost - resumed <= every, (at, lost, resumed)
    assert len(re.findall(r"continuing \S+checkpoint.pt from step", text)) == 1  # one restart was enough
    print(f"\nkill -9 of rank 1 after step {lost}: restarted from step {resumed}, {lost - resumed} step(s) "
          f"trained again, finished at step {iters}")
    _finished(run, iters)


# --------------------------------------------------------------------------------------------- preemption
@pytest.mark.parametrize("target,sig", [("agent", signal.SIGTERM), ("rank 1", signal.SIGINT)],
                         ids=["SIGTERM to the agent", "SIGINT to rank 1"])
def test_a_signal_saves_once_exits_143_or_130_then_resume_finishes(data, tmp_path, jobs, target, sig):
    """SIGTERM to the torchrun agent (how a scheduler preempts a job), or Ctrl-C's SIGINT to one rank: every rank
    finishes the same step, one checkpoint is written (no periodic ones here: --ckpt-every 0), ``modi torchrun``
    exits 143 / 130 (plain torchrun: a traceback and 1); then ``--resume auto`` trains to the end (once: the same
    for both)."""
    run, log, iters = tmp_path / "run", tmp_path / "job.log", 20
    argv = [*MODI_TORCHRUN, *_one_node(restarts=0), *_train(data, run, "--iters", str(iters), "--ckpt-every", "0")]
    job = jobs(argv, log)
    _wait_for(lambda: len(_steps(run)) >= 4, job, log, "step 4")
    os.kill(job.pid if target == "agent" else _workers(job.pid)[1], sig)
    assert _end(job, log) == 128 + sig, _text(log)[-3000:]
    text = _text(log)
    _no_bug(text)
    stops = re.findall(r"interrupted at step (\d+): checkpoint saved", text)
    assert len(stops) == 1, text[-3000:]
    step = int(stops[0])
    assert load_checkpoint(run / "checkpoint.pt")["step"] == step and _steps(run)[-1] == step
    if target != "agent":
        return
    job = jobs([*argv, "--resume", "auto"], log)
    assert _end(job, log) == 0, _text(log)[-3000:]
    assert f"continuing {run / 'checkpoint.pt'} from step {step}" in _text(log)
    _finished(run, iters)


# --------------------------------------------------------------------------------------------- a killed save
SLOW_SAVE = """# modi, whose rank 0 stops halfway through writing the checkpoint of step STEP (half its bytes in the temp
# file) and touches MARKER: the test's moment to kill the job. Usage: slow_save.py STEP MARKER ARGS...
import io
import os
import sys
import time
from pathlib import Path

import torch

from modi.cli import main

STEP, MARKER = int(sys.argv[1]), Path(sys.argv[2])
_save = torch.save


def save(obj, f, *args, **kwargs):
    if os.environ.get("RANK") == "0" and isinstance(obj, dict) and obj.get("step") == STEP:
        buf = io.BytesIO()
        _save(obj, buf, *args, **kwargs)
        f.write(buf.getvalue()[: len(buf.getvalue()) // 2])
        f.flush()
        MARKER.touch()
        time.sleep(300)  # killed long before
    return _save(obj, f, *args, **kwargs)


torch.save = save
sys.exit(main(sys.argv[3:]))
"""


def test_a_job_killed_during_a_checkpoint_write_resumes_from_the_previous_one(data, tmp_path, jobs):
    """SIGKILL to the whole job (agent and workers, as when a node is lost) while rank 0 is halfway through writing
    the checkpoint of step 4 (a wrapper of ``modi`` stops it there): the half-written copy is only a temp file and
    the lock is left behind; ``--resume auto`` takes the folder, loads step 3, clears the temp file and trains to
    the end."""
    run, log, iters, marker = tmp_path / "run", tmp_path / "job.log", 8, tmp_path / "saving"
    script = tmp_path / "slow_save.py"
    script.write_text(SLOW_SAVE)
    train = ["train", str(data), "--out", str(run), *SMALL, "--iters", str(iters), "--ckpt-every", "1"]
    job = jobs([*TORCHRUN, *_one_node(), str(script), "4", str(marker), *train], log)
    _wait_for(marker.exists, job, log, "rank 0 halfway through the checkpoint of step 4")
    assert len(_kill(job)) == 2
    temps = list(run.glob(".checkpoint.pt.*.tmp"))
    assert len(temps) == 1 and temps[0].stat().st_size > 0 and (run / ".lock").exists()  # what the kill left
    assert load_checkpoint(run / "checkpoint.pt")["step"] == 3  # whole: the rename never happened
    job = jobs([*TORCHRUN, *_one_node(), *_train(data, run, "--iters", str(iters), "--ckpt-every", "1",
                                                 "--resume", "auto")], log)
    assert _end(job, log) == 0, _text(log)[-3000:]
    assert f"continuing {run / 'checkpoint.pt'} from step 3" in _text(log)
    _no_bug(_text(log))
    _finished(run, iters)


# --------------------------------------------------------------------------------------------- a hung peer
def test_a_hung_worker_is_one_line_and_exit_75_within_the_timeout(data, tmp_path, jobs):
    """A worker that stops answering (SIGSTOP) while the other waits in a collective: past ``--dist-timeout`` the
    waiting rank gives up with the lost-peer line and exit 75 (torch's gloo default would wait 30 minutes)."""
    run, log, timeout = tmp_path / "run", tmp_path / "job.log", 6
    job = jobs([*MODI_TORCHRUN, *_one_node(), *_train(data, run, "--iters", "5000", "--ckpt-every", "2",
                                                      "--dist-timeout", str(timeout))], log)
    _wait_for(lambda: len(_steps(run)) >= 3, job, log, "step 3")
    # meanwhile a second job of two ranks into the same folder is refused on every rank, in one line, exit 2
    other_log = tmp_path / "other.log"
    other = jobs([*MODI_TORCHRUN, *_one_node(), *_train(data, run, "--iters", "5000", "--resume", "auto")], other_log)
    assert _end(other, other_log) == 2, _text(other_log)[-3000:]
    other_text = _text(other_log)
    _no_bug(other_text)
    assert re.search(rf"modi: error: {re.escape(str(run))} is in use by another run \(pid {_workers(job.pid)[0]}",
                     other_text), other_text[-3000:]
    assert "rank 0 could not take the run folder" in other_text  # rank 1's line
    assert job.poll() is None and _steps(run)[-1] >= 3
    hung = _workers(job.pid)[1]
    os.kill(hung, signal.SIGSTOP)
    t = time.time()
    try:
        _wait_for(lambda: "did not answer" in _text(log), job, log, "the lost-peer line", timeout=timeout + 60)
    finally:
        os.kill(hung, signal.SIGCONT)  # let it take torchrun's SIGTERM
    waited = time.time() - t
    assert waited <= timeout + 30, waited
    assert _end(job, log) == PeerLostError.exit_code == 75, _text(log)[-3000:]
    text = _text(log)
    _no_bug(text)
    line = _line("modi: error:", text)
    assert re.search(rf"rank 1 \(pid {hung} on .+\) did not answer within {timeout} s", line), line
    assert re.search(r"the newest checkpoint, step \d+ in \S+, is intact; to continue: .*--resume auto", line), line


# --------------------------------------------------------------------------------------------- two nodes
def test_two_nodes_by_c10d_rendezvous_train_one_run(tmp_path, jobs):
    """Two torchrun agents of one process each, joined by c10d rendezvous on the loopback, as two machines would be
    (the data is the word 'procedural': both write it into the run folder at once, and must read the same)."""
    run, iters, port = tmp_path / "run", 10, _port()
    nodes = []
    for node in (0, 1):
        argv = [*MODI_TORCHRUN, "--nnodes", "2", "--nproc-per-node", "1", "--rdzv-backend", "c10d",
                "--rdzv-endpoint", f"127.0.0.1:{port}", "--rdzv-id", "issue43", "--max-restarts", "0",
                *_train(Path("procedural"), run, "--iters", str(iters), "--ckpt-every", "5")]
        nodes.append((jobs(argv, tmp_path / f"node{node}.log"), tmp_path / f"node{node}.log"))
    for job, log in nodes:
        assert _end(job, log) == 0, _text(log)[-3000:]
        _no_bug(_text(log))
    texts = [_text(log) for _, log in nodes]
    assert sum(len(re.findall(r"modi train: step 10 in", t)) for t in texts) == 1  # rank 0 alone reports
    assert "2 process(es)" in "".join(texts)
    _finished(run, iters)


# --------------------------------------------------------------------------------------------- the shards
@pytest.mark.parametrize("n,batch,world", [(20, 4, 2), (23, 8, 2), (7, 16, 4), (50, 6, 3), (5, 2, 1)])
def test_every_window_once_per_epoch_across_the_ranks(n, batch, world):
    """The stream of global batches, each cut into the ranks' shards, holds every window exactly once per epoch
    (a batch may straddle two epochs); the shards of one step never overlap."""
    steps = (3 * n) // batch + 2
    stream = []
    for step in range(steps):
        shards = [shard_indices(n, batch, world, r, seed=5, step=step) for r in range(world)]
        assert all(len(s) == batch // world for s in shards)
        stream += torch.cat(shards).tolist()
    for epoch in range(len(stream) // n):
        assert sorted(stream[epoch * n:(epoch + 1) * n]) == list(range(n)), epoch
    assert stream[:n] != stream[n:2 * n]  # a new order every epoch
    # the data of a step depends on the step only: 2 ranks x 8 see the windows 1 rank x 16 sees
    for step in range(4):
        two = torch.cat([shard_indices(n, 16, 2, r, seed=5, step=step) for r in range(2)])
        assert torch.equal(two, shard_indices(n, 16, 1, 0, seed=5, step=step))


def test_the_trainer_trains_each_rank_on_its_own_shard(data, tmp_path):
    """Rank r of w takes the r-th slice of the step's global batch (before issue 43 every rank drew windows at
    random, with repeats within a step and across the ranks)."""
    cfg = make_config("small", [], **{"model.channels": (8, 8, 8, 6, 6), "model.latent_dim": 16, "model.n_mlp": 2,
                                      "data.n_frames": 16, "train.batch": 4, "train.sample_every": 0})
    tr = Trainer(cfg, prepare_data(data, cfg, cache=False), tmp_path, progress=False, tensorboard=False,
                 write_samples=False)
    n = tr.windows.shape[0]
    assert n >= 8
    seen = []
    for step in range(n // 4):
        shards = []
        for rank in (0, 1):
            tr.rank, tr.world = rank, 2  # what a process group of two would give
            shards.append(tr._batch_indices(step))
        assert len(shards[0]) == 2 and not set(shards[0].tolist()) & set(shards[1].tolist())
        seen += torch.cat(shards).tolist()
    assert len(set(seen)) == len(seen) == n // 4 * 4  # none twice within the epoch


# --------------------------------------------------------------------------------------------- 2 x b = 1 x 2b
EQUAL = {"model.channels": (8, 8, 8, 6, 6), "model.latent_dim": 16, "model.n_mlp": 2, "data.n_frames": 16,
         "train.batch": 8, "train.sample_every": 0, "train.ckpt_every": 0, "train.d_reg_every": 2,
         "train.snapshot_every": 0,
         # what couples the samples of a process (see docs/distributed.md), off for an exact comparison
         "model.mbstd_group": 1, "train.path_weight": 0.0, "train.mixing": 0.0}
EQUAL_STEPS = 4


def _shared_latents(tr: Trainer) -> None:
    """The latents of the global batch from one generator per draw, each rank taking its slice: the world size
    then changes nothing the ranks draw (by default each rank draws its own)."""
    dim, draws = tr.cfg.model.latent_dim, [0]

    def z(n: int) -> tuple[list[torch.Tensor], None]:
        draws[0] += 1
        every = torch.randn(n * tr.world, dim, generator=torch.Generator().manual_seed(draws[0]))
        return [every[tr.rank * n:(tr.rank + 1) * n]], None  # (latents, inject index: no mixing)

    tr._z = z


def _equal_run(tr: Trainer) -> tuple[list[dict[str, float]], dict[str, torch.Tensor]]:
    """``EQUAL_STEPS`` steps: each step's losses (means over the ranks = over the global batch) and G_ema."""
    _shared_latents(tr)
    losses = []
    for _ in range(EQUAL_STEPS):
        out = tr.train_step()
        keys = sorted(out)
        t = torch.tensor([out[k] for k in keys], dtype=torch.float64)
        losses.append(dict(zip(keys, tr._all_mean(t).tolist())))
    return losses, {k: v.detach().clone() for k, v in tr.G_ema.state_dict().items()}


def _equal_worker(rank: int, init_file: str, data, cfg: dict, out: str) -> None:
    torch.set_num_threads(1)
    torch.distributed.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=2)
    tr = Trainer(MoDiConfig.from_dict(cfg), data, out, progress=False, tensorboard=False, write_samples=False)
    assert tr.distributed and tr.local_batch == 4
    losses, g_ema = _equal_run(tr)
    if rank == 0:
        torch.save({"losses": losses, "G_ema": g_ema}, Path(out) / "two.pt")
    torch.distributed.barrier()
    os._exit(0)  # the process group is not torn down: see modi.cli.leave_without_teardown


def test_two_processes_of_batch_4_train_as_one_of_batch_8(data, tmp_path):
    """DDP averages the ranks' gradients and the ranks take the shards of one global batch, so 2 processes x 4
    windows train as 1 x 8 -- to float rounding, once the latents are the same draws (by default every rank draws
    its own: the spread between runs of different seeds) and what couples the samples of one process is off
    (minibatch stddev groups, the path-length mean; as in StyleGAN2, each process has its own)."""
    cfg = make_config("small", [], **EQUAL)
    windows = prepare_data(data, cfg, cache=False)
    torch.multiprocessing.spawn(_equal_worker, args=(str(tmp_path / "init"), windows, cfg.to_dict(), str(tmp_path)),
                                nprocs=2, join=True)
    two = torch.load(tmp_path / "two.pt", weights_only=True)
    one_losses, one_g = _equal_run(Trainer(cfg, windows, tmp_path / "one", progress=False, tensorboard=False,
                                           write_samples=False))
    assert "r1" in one_losses[0] and "contact" in one_losses[0]
    for step, (a, b) in enumerate(zip(one_losses, two["losses"])):
        assert a.keys() == b.keys()
        for k in a:
            assert abs(a[k] - b[k]) <= 1e-4 * max(1.0, abs(a[k])), (step, k, a[k], b[k])
    for k, v in one_g.items():
        torch.testing.assert_close(two["G_ema"][k], v, rtol=1e-4, atol=1e-5, msg=k)
    assert abs(one_losses[-1]["d"] - one_losses[0]["d"]) > 1e-6  # it trained


# --------------------------------------------------------------------------------------------- the line, resume auto
def test_lost_peer_errors_are_told_from_bugs_and_make_one_line(monkeypatch):
    gloo_reset = RuntimeError("[/pytorch/third_party/gloo/gloo/transport/tcp/pair.cc:537] Read error "
                              "[127.0.0.1]:27025: Connection reset by peer. This is typically caused by a remote "
                              "worker hanging or bugs in the application. GLHF!")
    gloo_timeout = RuntimeError("[/pytorch/third_party/gloo/gloo/transport/tcp/unbound_buffer.cc:78] Timed out "
                                "waiting 4000ms for recv operation to complete")
    mesh = RuntimeError("[../third_party/gloo/gloo/transport/tcp/pair.cc:...] connectFullMesh failed")
    for exc in (gloo_reset, gloo_timeout, mesh, torch.distributed.DistNetworkError("store lost")):
        assert mdist.is_peer_failure(exc), exc
    for exc in (RuntimeError("mat1 and mat2 shapes cannot be multiplied"), ValueError("Connection reset by peer")):
        assert not mdist.is_peer_failure(exc), exc
    monkeypatch.setitem(mdist._state, "peers", [("here", 1), ("elsewhere", 2)])
    monkeypatch.setitem(mdist._state, "rank", 0)
    monkeypatch.setitem(mdist._state, "timeout_s", 4.0)
    monkeypatch.setenv("TORCHELASTIC_RESTART_COUNT", "2")
    monkeypatch.setenv("TORCHELASTIC_MAX_RESTARTS", "2")
    err = mdist.peer_lost_error(gloo_timeout, step=61, checkpoint=Path("RUN/checkpoint.pt"), checkpoint_step=50)
    text = str(err)
    assert isinstance(err, PeerLostError) and err.exit_code == 75 and "\n" not in text
    assert text.startswith("rank 1 (pid 2 on elsewhere) did not answer within 4 s"), text
    assert "at step 61 (Timed out waiting 4000ms for recv operation to complete)" in text
    assert "the newest checkpoint, step 50 in RUN/checkpoint.pt, is intact; to continue: " in text
    assert text.endswith("--resume auto"), text
    assert mdist.without_resume(["train", "d", "--resume", "--iters", "5", "--resume=x", "--resume", "c.pt"]) == \
        ["train", "d", "--iters", "5"]


def test_a_sigterm_after_a_peer_died_is_told_as_the_lost_peer(monkeypatch):
    """torchrun SIGTERMs the survivors once a worker died; when that signal reaches rank 0 before its own collective
    fails, rank 0 reports the lost peer (exit 75), not "terminated". A job stopped as a whole (its peers alive when
    the signal arrives) stays a plain SIGTERM."""
    host = socket.gethostname()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()  # ended and reaped
    monkeypatch.setitem(mdist._state, "rank", 0)
    monkeypatch.setitem(mdist._state, "timeout_s", 4.0)
    monkeypatch.setenv("TORCHELASTIC_RESTART_COUNT", "0")
    monkeypatch.setenv("TORCHELASTIC_MAX_RESTARTS", "2")
    monkeypatch.setitem(mdist._state, "peers", [(host, os.getpid()), (host, os.getppid())])
    assert mdist.stopped_for_a_lost_peer() is None  # the peer is alive: the whole job was stopped
    monkeypatch.setitem(mdist._state, "peers", [(host, os.getpid()), (host, dead.pid)])
    lost = mdist.stopped_for_a_lost_peer()
    assert lost is not None
    text = str(mdist.peer_lost_error(lost, step=16, checkpoint=Path("RUN/checkpoint.pt"), checkpoint_step=10))
    assert text.startswith(f"rank 1 (pid {dead.pid} on {host}) has ended at step 16 (torchrun stopped this "
                           "worker (SIGTERM) after the loss); the newest checkpoint, step 10 in RUN/checkpoint.pt, "
                           "is intact; torchrun restarts the job from it (restart 1 of 2)"), text


def test_resume_auto_starts_continues_and_refuses_another_config(data, tmp_path, capsys, monkeypatch):
    run = tmp_path / "run"
    tiny = ["train", str(data), "--out", str(run), *SMALL]
    assert main([*tiny, "--iters", "1", "--resume", "auto"]) == 0  # nothing to continue: a new run
    assert main([*tiny, "--iters", "2"]) == 2 and "--resume" in capsys.readouterr().err
    capsys.readouterr()
    assert main([*tiny, "--iters", "2", "--resume", "auto"]) == 0
    assert "continuing" in capsys.readouterr().out and load_checkpoint(run / "checkpoint.pt")["step"] == 2
    assert main([*tiny, "--iters", "3", "--resume", "auto", "--lr", "0.001", "--seed", "4"]) == 2
    err = capsys.readouterr().err
    assert "was trained with another config: --lr 0.001 (train.lr is 0.002 in the checkpoint); --seed 4 " \
           "(train.seed is 0 in the checkpoint)" in err, err
    monkeypatch.setenv("TORCHELASTIC_RESTART_COUNT", "1")  # a torchrun restart is --resume auto unasked
    assert main([*tiny, "--iters", "3"]) == 0
    assert load_checkpoint(run / "checkpoint.pt")["step"] == 3 and _steps(run) == [1, 2, 3]
