"""argparse ``type=`` callables and output-path checks shared by every ``modi`` command.

Bad numbers, devices and output paths are refused while the command line is parsed, so the error names the
option (argparse prints ``modi CMD: error: argument --lr: must be a finite number > 0, got nan``) and nothing has
been loaded, trained or written yet. Each factory returns a plain function whose ``__name__`` reads well in
argparse's messages; the bounds on sizes (``--batch``, ``--n``, ``--frames``, ``--fps``) are there so a typo such
as ``--n 100000000`` fails at once instead of running for minutes or being killed for memory.

This module imports only the standard library at import time (torch is imported lazily for device names), so
building the parser stays cheap.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path
from typing import Callable, Iterable

from modi.errors import UserError
from modi.faults import existing_file as input_file  # one check of input files (API and CLI)
from modi.faults import refuse_overwrite, unique_names  # noqa: F401  (the same checks for the API and the CLI)

# Upper bounds of the sizes a user can ask for. They are far above anything the models are used with and far below
# what would exhaust memory or run for hours by mistake.
MAX_FPS = 1000.0          # mocap is captured at <= 480 fps; resampling up to 1e6 fps allocates gigabytes per clip
MAX_BATCH = 1024          # --batch when training (MoDi's paper batch is 16): activations and gradients of each
MAX_SAMPLE_BATCH = 4096   # --batch when only sampling (no gradients): motions per forward pass
MAX_SAMPLES = 20_000      # motions generated / sampled in one command (~0.5 GB of MoDi output at 64 frames)
MAX_FRAMES = 100_000      # ~55 minutes at 30 fps
MAX_THREADS = 1024
MAX_ITERS = 100_000_000
MAX_SEED = 2**32 - 1      # numpy's seed range


def _int(text: str) -> int:
    try:
        return int(text, 10)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None


def _float(text: str) -> float:
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def _named(fn: Callable, name: str) -> Callable:
    fn.__name__ = name
    return fn


# ------------------------------------------------------------------------------------------------ integers
def int_range(lo: int | None = None, hi: int | None = None, what: str = "") -> Callable[[str], int]:
    """An integer in ``[lo, hi]`` (either bound may be None). ``what`` is appended to the message (a reason)."""
    def parse(text: str) -> int:
        v = _int(text)
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            if lo is not None and hi is not None:
                rng = f"between {lo} and {hi}"
            elif lo is not None:
                rng = f">= {lo}"
            else:
                rng = f"<= {hi}"
            raise argparse.ArgumentTypeError(f"must be an integer {rng}{what}, got {text}")
        return v
    return _named(parse, "int")


positive_int = int_range(1)
nonneg_int = int_range(0)
seed_int = int_range(0, MAX_SEED)
threads_int = int_range(1, MAX_THREADS)
iters_int = int_range(0, MAX_ITERS)
batch_int = int_range(1, MAX_BATCH, " (a larger batch does not fit in memory)")
sample_batch_int = int_range(1, MAX_SAMPLE_BATCH, " (motions per forward pass)")
samples_int = int_range(1, MAX_SAMPLES)
frames_int = int_range(2, MAX_FRAMES)


def multiple_of(m: int, lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """A positive integer multiple of ``m`` (e.g. MoDi's window length, halved at every level of the hierarchy)."""
    base = int_range(lo if lo is not None else m, hi)

    def parse(text: str) -> int:
        v = base(text)
        if v % m:
            raise argparse.ArgumentTypeError(f"must be a multiple of {m}, got {v} (e.g. {max(m, v // m * m)})")
        return v
    return _named(parse, "int")


# ------------------------------------------------------------------------------------------------ old spellings
class _Renamed(argparse.Action):
    """An old option spelling: still works, hidden from ``--help``, and says once what replaced it."""

    def __init__(self, option_strings, dest, new: str = "", flag: bool = False, **kw) -> None:
        self.new, self.flag = new, flag
        super().__init__(option_strings, dest, nargs=0 if flag else None, **kw)

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        print(f"modi: note: {option_string} is now {self.new}", file=sys.stderr)
        setattr(namespace, self.dest, True if self.flag else values)


def renamed_option(parser: argparse.ArgumentParser, old: str, new: str, dest: str, type: Callable | None = None,
                   flag: bool = False) -> None:
    """Keep ``old`` working as a hidden alias of ``new`` (same ``dest`` and checks; ``flag``: an on/off switch), so
    no user's script breaks."""
    kw = {} if flag else {"type": type}
    parser.add_argument(old, dest=dest, action=_Renamed, new=new, flag=flag, help=argparse.SUPPRESS,
                        default=argparse.SUPPRESS, **kw)


def renamed_command(sub, old: str, new: str, build: Callable[[argparse.ArgumentParser], None], **kw
                    ) -> argparse.ArgumentParser:
    """Keep subcommand ``old`` working as a hidden alias of ``new``: the same options (``build`` adds them to a
    parser), left out of the listing (no ``help=``), and a note naming the new spelling when it runs."""
    p = sub.add_parser(old, **kw)
    build(p)
    run = p.get_default("func")

    def func(args):
        print(f"modi: note: '{old}' is now '{new}'", file=sys.stderr)
        return run(args)
    p.set_defaults(func=func)
    return p


# ------------------------------------------------------------------------------------------------ floats
def float_range(lo: float | None = None, hi: float | None = None, lo_inclusive: bool = True,
                hi_inclusive: bool = True) -> Callable[[str], float]:
    """A finite float in the interval given by ``lo``/``hi`` (None = unbounded) and the inclusive flags."""
    def parse(text: str) -> float:
        v = _float(text)
        bad_lo = lo is not None and (v < lo if lo_inclusive else v <= lo)
        bad_hi = hi is not None and (v > hi if hi_inclusive else v >= hi)
        if bad_lo or bad_hi:
            if lo is not None and hi is not None:
                rng = f"in {'[' if lo_inclusive else '('}{lo:g}, {hi:g}{']' if hi_inclusive else ')'}"
            elif lo is not None:
                rng = f"{'>=' if lo_inclusive else '>'} {lo:g}"
            else:
                rng = f"{'<=' if hi_inclusive else '<'} {hi:g}"
            raise argparse.ArgumentTypeError(f"must be a finite number {rng}, got {text}")
        return v
    return _named(parse, "float")


finite_float = _named(lambda text: _float(text), "float")
positive_finite_float = float_range(0.0, None, lo_inclusive=False)
nonneg_finite_float = float_range(0.0, None)
fps_float = float_range(0.0, MAX_FPS, lo_inclusive=False)
lr_float = float_range(0.0, 10.0, lo_inclusive=False)
probability = float_range(0.0, 1.0)
minutes_float = float_range(0.0, None, lo_inclusive=False)
angle_float = float_range(-36000.0, 36000.0)


# ------------------------------------------------------------------------------------------------ devices
def available_devices() -> list[str]:
    """The torch device names that exist here: ``cpu`` and ``cuda:N`` for every visible GPU."""
    import torch

    devs = ["cpu"]
    if torch.cuda.is_available():
        n = torch.cuda.device_count()
        devs += ["cuda"] + [f"cuda:{i}" for i in range(n)]
    mps = getattr(torch.backends, "mps", None)
    if mps is not None and mps.is_available():
        devs.append("mps")
    return devs


def device_type(allow_auto: bool = False) -> Callable[[str], str]:
    """A device name checked against what exists (``auto`` too when ``allow_auto``); returns the name."""
    def parse(text: str) -> str:
        name = text.strip().lower()
        if allow_auto and name == "auto":
            return name
        devs = available_devices()
        if name in devs:
            return name
        exist = ", ".join(devs) + (", auto" if allow_auto else "")
        if name.startswith("cuda") and "cuda" not in devs:
            raise argparse.ArgumentTypeError(f"{text!r}: this torch has no CUDA device; devices here: {exist}")
        raise argparse.ArgumentTypeError(f"unknown device {text!r}; devices here: {exist}")
    return _named(parse, "device")


device = device_type()
device_or_auto = device_type(allow_auto=True)


# ------------------------------------------------------------------------------------------------ paths
def _file_above(path: Path) -> Path | None:
    """The first existing ancestor of ``path`` that is not a folder (a file in the way), if any."""
    for parent in path.absolute().parents:
        if parent.exists():
            return None if parent.is_dir() else parent
    return None


def output_dir(text: str) -> str:
    """An output folder: may exist as a folder or not at all; not a file, nor under a file."""
    p = Path(text)
    if p.exists() and not p.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a file, expected a folder (choose another name)")
    blocker = _file_above(p)
    if blocker is not None:
        raise argparse.ArgumentTypeError(f"{text} lies under {blocker}, which is a file, not a folder")
    return text


def output_file(text: str) -> str:
    """An output file: not an existing folder, not under a file (an existing file is replaced)."""
    p = Path(text)
    if p.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder, expected a file name")
    blocker = _file_above(p)
    if blocker is not None:
        raise argparse.ArgumentTypeError(f"{text} lies under {blocker}, which is a file, not a folder")
    return text


_named(output_dir, "folder")
_named(output_file, "file")


__all__ = ["int_range", "positive_int", "nonneg_int", "seed_int", "threads_int", "iters_int", "batch_int",
           "sample_batch_int", "renamed_option", "renamed_command", "samples_int", "frames_int", "multiple_of", "float_range", "finite_float", "positive_finite_float",
           "nonneg_finite_float", "fps_float", "lr_float", "probability", "minutes_float", "angle_float",
           "available_devices", "device_type", "device", "device_or_auto", "output_dir", "output_file",
           "input_file", "refuse_overwrite", "unique_names", "MAX_FPS", "MAX_BATCH", "MAX_SAMPLE_BATCH", "MAX_SAMPLES",
           "MAX_FRAMES"]


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """``(default: X)`` after an option's help, except where it says nothing: no default (None, False for a flag)
    or a help text that already states its default in words."""

    def _get_help_string(self, action):
        text = action.help or ""
        if action.default in (None, False, argparse.SUPPRESS) or "default" in text.lower() or "%(default)" in text:
            return text
        return super()._get_help_string(action)


def use_help_formatter(parser: argparse.ArgumentParser) -> None:
    """Give ``parser`` and every sub-command parser under it :class:`HelpFormatter` (in place of argparse's
    ``ArgumentDefaultsHelpFormatter``, which prints "(default: None)")."""
    stack, seen = [parser], set()
    while stack:
        p = stack.pop()
        if id(p) in seen:
            continue
        seen.add(id(p))
        if p.formatter_class is argparse.ArgumentDefaultsHelpFormatter:
            p.formatter_class = HelpFormatter
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                stack.extend(action.choices.values())
