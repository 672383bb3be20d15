"""CUDA graphs of the MoDi training step (``modi train --cuda-graphs auto|on|off``).

A step on a GPU is host-bound: thousands of small launches, each paying Python and dispatch. A CUDA graph records
one step's launches once and replays them with one call. The step already asks nothing of the host and runs the same
ops at the same shapes every time for a given kind (``Trainer`` in ``training.py``), so one graph per kind -- plain,
path length, R1, R1 + path length -- replays every later step of that kind:

* what changes from step to step reaches the graph through static device buffers filled before the replay: the
  batch's window indices (copied from the epoch's order on the device) and the EMA weight; random draws (latents,
  style mixing) come from the CUDA generator, whose offset a replay advances as the eager step would;
* each kind is first run eagerly ``warmup`` times on a side stream (lazy initialisation, the kernels' first-use
  checks, ``MODI_EXT_IMPL=auto``'s timing and the optimiser's state all happen there, outside any capture), then
  captured once and replayed; the step in which a kind is captured is executed by replaying its new graph (a capture
  records, it does not run);
* the graphs share one memory pool (they never run at the same time); their loss outputs are copied out after each
  replay (one launch) so that the values a caller keeps are never overwritten by a later replay;
* a capture that fails (a host read or an op CUDA cannot capture) is one warning line, and the run continues eagerly
  from that very step: the failed capture changed nothing on the device, so no step is lost or taken twice.

The capture mechanism is a :class:`CaptureBackend`. :class:`CudaGraphBackend` is the real one; :class:`OpTape` is its
stand-in on any device: it records the step's ATen ops and replays them against the same tensors with every
non-tensor argument frozen at capture, as a graph freezes them, so that tests without a GPU prove the step is
graph-shaped (what is read from the host, which buffers are static) and that graphed training equals eager.
"""
from __future__ import annotations

import warnings
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from typing import Any, Callable, ContextManager, Iterator

import torch
from torch import Tensor
from torch.utils._python_dispatch import TorchDispatchMode

from modi.errors import UserError

__all__ = ["GRAPH_MODES", "GRAPH_WARMUP", "AUTO_ENABLES_GRAPHS", "auto_enables_graphs", "check_graph_mode",
           "GraphCaptureError", "GraphFallbackWarning", "Captured", "CaptureBackend", "CudaGraphBackend", "OpTape",
           "StepGraphs"]

GRAPH_MODES = ("auto", "on", "off")
GRAPH_WARMUP = 3  # eager steps of a kind, on a side stream, before that kind is captured

# Whether ``auto`` turns graphs on for a CUDA device. False until a GPU has shown a graphed lazy-regularisation cycle
# equal to an eager one: ``benchmarks/gpu_measure.py``'s ``modi_step`` stage (``python -m modi_ext.validate``) runs
# one cycle of every step kind eagerly and one graphed from the same seed, and records ``graphed_equals_eager``
# (every step's losses and every weight and optimiser state after the cycle, allclose within float tolerance). Flip
# this when that JSON, from the paper preset at batch 16 and 64, says ``"equal": true``; keep the JSON beside it in
# ``benchmarks/results/``.
AUTO_ENABLES_GRAPHS = False


def auto_enables_graphs(device: torch.device | str) -> bool:
    """Whether ``cuda_graphs="auto"`` graphs a run on ``device``: only on CUDA, and only once
    :data:`AUTO_ENABLES_GRAPHS` records the GPU proof (see there)."""
    return torch.device(device).type == "cuda" and AUTO_ENABLES_GRAPHS


def check_graph_mode(mode: Any) -> str:
    """``mode`` if it is one of :data:`GRAPH_MODES`, else one ``UserError`` naming them."""
    if mode not in GRAPH_MODES:
        raise UserError(f"cuda_graphs {mode!r}: choose one of {', '.join(GRAPH_MODES)}")
    return mode


class GraphCaptureError(RuntimeError):
    """The step did something a graph cannot hold (e.g. a read of a device value on the host)."""


class GraphFallbackWarning(UserWarning):
    """A step kind could not be captured: the run continues eagerly (same results, no speed-up)."""


@dataclass
class Captured:
    """One captured step: ``replay()`` runs it again and rewrites ``outputs`` (the tensors its body returned)."""

    replay: Callable[[], None]
    outputs: Any


class CaptureBackend:
    """How a step is captured and where its warm-up runs; :class:`StepGraphs` asks nothing else of it."""

    name = "none"

    def side_stream(self) -> ContextManager:
        """The context of the eager warm-up steps."""
        return nullcontext()

    def capture(self, body: Callable[[], Any]) -> Captured:
        """Record ``body`` (without applying its effects) and return its replay; raise if it cannot be captured."""
        raise NotImplementedError


class CudaGraphBackend(CaptureBackend):
    """``torch.cuda.CUDAGraph`` captures on one side stream, every graph in one shared memory pool."""

    name = "cuda"

    def __init__(self, device: torch.device | str):
        self.device = torch.device(device)
        self.stream = torch.cuda.Stream(device=self.device)
        self.pool = torch.cuda.graph_pool_handle()

    @contextmanager
    def side_stream(self) -> Iterator[None]:
        # the side stream waits for the work already queued, and the default stream for the warm-up's; so a block
        # freed on one stream is never reused on the other while the first still reads it
        current = torch.cuda.current_stream(self.device)
        self.stream.wait_stream(current)
        try:
            with torch.cuda.stream(self.stream):
                yield
        finally:
            current.wait_stream(self.stream)

    def capture(self, body: Callable[[], Any]) -> Captured:
        graph = torch.cuda.CUDAGraph()
        current = torch.cuda.current_stream(self.device)
        self.stream.wait_stream(current)
        with torch.cuda.graph(graph, pool=self.pool, stream=self.stream):
            outputs = body()
        current.wait_stream(self.stream)
        return Captured(graph.replay, outputs)


# ---------------------------------------------------------------------------------------------- the stand-in
_HOST_READS = {torch.ops.aten._local_scalar_dense.default, torch.ops.aten.equal.default,
               torch.ops.aten.is_nonzero.default}


def _leaves(x: Any) -> list[Tensor]:
    """The tensors in an op's argument or result (a tensor, or lists/tuples of them); pytree's general walk costs
    more than the ops of a tiny model."""
    if isinstance(x, Tensor):
        return [x]
    if isinstance(x, (list, tuple)):
        return [t for v in x for t in _leaves(v)]
    return []


def _swap(x: Any, env: dict[int, Tensor]) -> Any:
    """``x`` with each tensor made during the capture replaced by the replay's (the others are the live ones)."""
    if isinstance(x, Tensor):
        return env.get(id(x), x)
    if isinstance(x, (list, tuple)):
        return type(x)(_swap(v, env) for v in x)
    return x


_WRITES: dict[Any, tuple[tuple[int, str], ...]] = {}


def _written(func, args: tuple, kwargs: dict) -> list[Tensor]:
    """The tensors ``func`` writes in place (by its schema)."""
    where = _WRITES.get(func)
    if where is None:
        where = _WRITES[func] = tuple((i, a.name) for i, a in enumerate(func._schema.arguments)
                                      if a.alias_info is not None and a.alias_info.is_write)
    out: list[Tensor] = []
    for i, name in where:
        out += _leaves(args[i] if i < len(args) else kwargs.get(name))
    return out


class _Tape(TorchDispatchMode):
    """Records every ATen op of a capture; keeps what each in-place op overwrote outside the capture's own tensors,
    so that the capture can be undone (a graph capture records without running)."""

    def __init__(self):
        super().__init__()
        self.ops: list[tuple[Any, tuple, dict, Any]] = []
        self.fresh: set[int] = set()  # storages the capture allocated
        self.saved: list[tuple[Tensor, Tensor]] = []  # (tensor from outside, its value before the first write)
        self._saved_ids: set[int] = set()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in _HOST_READS:
            raise GraphCaptureError(f"{func} reads a device value on the host inside the captured step")
        for t in _written(func, args, kwargs):
            if t.untyped_storage().data_ptr() not in self.fresh and id(t) not in self._saved_ids:
                self._saved_ids.add(id(t))
                self.saved.append((t, t.detach().clone()))
        out = func(*args, **kwargs)
        self.ops.append((func, args, kwargs, out))  # holds every tensor: no id is reused while the tape lives
        for ret, value in zip(func._schema.returns, out if isinstance(out, (tuple, list)) else (out,)):
            if ret.alias_info is None:
                self.fresh.update(t.untyped_storage().data_ptr() for t in _leaves(value))
        return out

    def undo(self) -> None:
        with torch.no_grad():
            for t, before in reversed(self.saved):
                t.copy_(before)
        self.saved = []


class OpTape(CaptureBackend):
    """A graph's stand-in on any device: ``capture`` runs the body under a dispatch mode that records its ATen ops,
    then undoes what the body wrote to tensors from outside it and rewinds the CPU generator (a capture does not
    run); ``replay`` runs the recorded ops again, each tensor argument the live tensor (from outside) or the replay's
    own (made inside), every other argument as captured, and copies the results into the captured outputs.

    It raises :class:`GraphCaptureError` for a host read, as a CUDA capture fails on one. Slower than eager (Python
    per op): for tests."""

    name = "optape"

    def capture(self, body: Callable[[], Any]) -> Captured:
        rng = torch.get_rng_state()
        cuda_rng = torch.cuda.get_rng_state_all() if torch.cuda.is_initialized() else None
        tape = _Tape()
        try:
            with tape:
                outputs = body()
        finally:
            tape.undo()
            torch.set_rng_state(rng)
            if cuda_rng is not None:
                torch.cuda.set_rng_state_all(cuda_rng)
        ops = [(func, args, kwargs, _leaves(out)) for func, args, kwargs, out in tape.ops]
        kept = _leaves(list(outputs.values()) if isinstance(outputs, dict) else outputs)

        def replay() -> None:
            env: dict[int, Tensor] = {}
            with torch.no_grad():
                for func, args, kwargs, made in ops:
                    res = func(*_swap(args, env), **{k: _swap(v, env) for k, v in kwargs.items()})
                    for o, r in zip(made, _leaves(res)):
                        env[id(o)] = r
                for t in kept:
                    if id(t) in env and env[id(t)] is not t:
                        t.copy_(env[id(t)])

        return Captured(replay, outputs)


# ---------------------------------------------------------------------------------------------- the schedule
class StepGraphs:
    """One graph per step kind: ``warmup`` eager steps of a kind on the side stream, then its capture, then
    replays. ``run(kind, body)`` runs one step and returns its losses (fresh tensors, never a graph's buffers).

    After a failed capture every later step runs eagerly (``fallback`` says why; one :class:`GraphFallbackWarning`).
    ``reset()`` drops the graphs and the warm-up counts: after a checkpoint load the optimiser's state tensors are
    new, and a graph holds the addresses it captured. A graph also keeps every host value it captured (learning
    rates, loss weights, the config): change one mid-run and ``reset()``, or the replays go on with the old one."""

    def __init__(self, backend: CaptureBackend, warmup: int = GRAPH_WARMUP,
                 on_fail: Callable[[], None] | None = None):
        self.backend = backend
        self.warmup = int(warmup)
        self.on_fail = on_fail or (lambda: None)  # tidies the caller's host-side state after a failed capture
        self.graphs: dict[str, Captured] = {}
        self.warm: dict[str, int] = {}
        self.replays: dict[str, int] = {}
        self.fallback: str | None = None

    @property
    def active(self) -> bool:
        return self.fallback is None

    def reset(self) -> None:
        self.graphs.clear()
        self.warm.clear()

    def run(self, kind: str, body: Callable[[], dict[str, Tensor]]) -> dict[str, Tensor]:
        if self.fallback is not None:
            return body()
        if self.warm.get(kind, 0) < self.warmup:
            with self.backend.side_stream():
                out = body()
            self.warm[kind] = self.warm.get(kind, 0) + 1
            return out
        graph = self.graphs.get(kind)
        if graph is None:
            try:
                graph = self.backend.capture(body)
            except Exception as exc:  # noqa: BLE001 - any capture failure: eager from here, same results
                self.fallback = f"{kind} step: {type(exc).__name__}: {' '.join(str(exc).split())[:300]}"
                self.graphs.clear()
                self.on_fail()
                warnings.warn(f"modi train: CUDA graph capture failed ({self.fallback}); training continues "
                              f"eagerly", GraphFallbackWarning, stacklevel=4)
                return body()
            self.graphs[kind] = graph
        graph.replay()
        self.replays[kind] = self.replays.get(kind, 0) + 1
        keys = list(graph.outputs)
        # one multi-tensor launch; x * 1 is an exact copy (NaN stays NaN, -0 stays -0)
        return dict(zip(keys, torch._foreach_mul([graph.outputs[k] for k in keys], 1.0)))

    def report(self) -> dict[str, Any]:
        return {"backend": self.backend.name, "warmup": self.warmup, "captured": sorted(self.graphs),
                "replays": dict(self.replays), "fallback": self.fallback}
