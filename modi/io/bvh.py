"""BVH reader and writer (numpy; own code).

``load`` accepts any whitespace layout (tabs, spaces, CRLF or CR line ends), any channel subset and
Euler order per joint, joint names with spaces, and any positive frame time. What other tools add is
skipped: a trailing ``#`` comment on a header line, and tokens after ``End Site`` (MoDi's released files
write ``End Site #name: Head``). Every malformation —
missing sections, unbalanced braces, bad OFFSETs, unknown or repeated channels, duplicate joint
names, zero/truncated/extra frames, a wrong value count on a frame line, non-numeric or non-finite
values — raises one :class:`modi.errors.BvhError` carrying the 1-based line number.

The MOTION block dominates the cost, so it is split once per line and converted by numpy in one
call; line-level diagnostics are only computed when that fast path finds a problem.
"""
from __future__ import annotations

import math
import os
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from modi.core.skeleton import Skeleton
from modi.errors import BvhError
from modi.faults import atomic_write

__all__ = ["Bvh", "load", "loads", "save", "dumps", "CHANNEL_NAMES"]

# canonical channel names (matched case-insensitively; the file's spelling is kept)
CHANNEL_NAMES = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")
_CHANNEL_KEY = {c.lower(): c for c in CHANNEL_NAMES}


def _channel_kind(name: str) -> tuple[str, int]:
    """('position'|'rotation', axis 0..2) for a valid channel name."""
    canon = _CHANNEL_KEY[name.lower()]
    return ("position" if canon.endswith("position") else "rotation"), "XYZ".index(canon[0])


@dataclass(eq=False, repr=False)
class Bvh:
    """A parsed BVH file, close to the text: joints in file (topological) order, raw channel values.

    ``offsets[j]`` is the declared OFFSET; joints that have position channels are translated by
    those channels instead (see :meth:`local_translations`). ``motion`` is ``(F, C)`` in file order,
    ``C = sum(len(c) for c in channels)``; rotations are in degrees.
    """

    names: list[str]
    parents: list[int]
    offsets: np.ndarray
    channels: list[list[str]]
    end_sites: dict[int, np.ndarray] = field(default_factory=dict)
    frame_time: float = 1.0 / 30.0
    motion: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    def __post_init__(self) -> None:
        self.offsets = np.asarray(self.offsets, dtype=np.float64).reshape(-1, 3)
        self.motion = np.asarray(self.motion, dtype=np.float64)
        if self.motion.size == 0:
            self.motion = self.motion.reshape(0, self.n_channels)
        self.end_sites = {int(k): np.asarray(v, dtype=np.float64).reshape(3) for k, v in self.end_sites.items()}
        self.channels = [list(c) for c in self.channels]
        self.parents = [int(p) for p in self.parents]
        j = len(self.names)
        if not (len(self.parents) == len(self.channels) == self.offsets.shape[0] == j):
            raise ValueError(
                f"Bvh: names ({j}), parents ({len(self.parents)}), channels ({len(self.channels)}) and "
                f"offsets ({self.offsets.shape[0]}) disagree"
            )
        if self.motion.ndim != 2 or self.motion.shape[1] != self.n_channels:
            raise ValueError(f"Bvh: motion must be (frames, {self.n_channels}), got {self.motion.shape}")
        for jj, chans in enumerate(self.channels):
            for c in chans:
                if c.lower() not in _CHANNEL_KEY:
                    raise ValueError(f"Bvh: joint {self.names[jj]!r} has unknown channel {c!r}")

    def __eq__(self, other: object) -> bool:
        """Exactly the same file content: names, tree, OFFSETs, channels, End Sites, frame time and values."""
        if not isinstance(other, Bvh):
            return NotImplemented
        return (self.names == other.names and self.parents == other.parents and self.channels == other.channels
                and self.frame_time == other.frame_time and np.array_equal(self.offsets, other.offsets)
                and np.array_equal(self.motion, other.motion) and self.end_sites.keys() == other.end_sites.keys()
                and all(np.array_equal(v, other.end_sites[k]) for k, v in self.end_sites.items()))

    __hash__ = None  # type: ignore[assignment]  # mutable, compared by value

    def __repr__(self) -> str:
        return (f"Bvh({self.n_joints} joints (root {self.names[0]!r}), {self.n_channels} channels, "
                f"{self.n_frames} frames, frame time {self.frame_time:g} s)" if self.names else "Bvh(empty)")

    # ------------------------------------------------------------------ basic facts
    @property
    def n_joints(self) -> int:
        return len(self.names)

    @property
    def n_frames(self) -> int:
        return int(self.motion.shape[0])

    @property
    def n_channels(self) -> int:
        return sum(len(c) for c in self.channels)

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    @property
    def channel_starts(self) -> list[int]:
        """Column of each joint's first channel in ``motion``."""
        starts, s = [], 0
        for c in self.channels:
            starts.append(s)
            s += len(c)
        return starts

    @property
    def rotation_orders(self) -> list[str]:
        """Euler order per joint, e.g. ``"ZXY"``, from the order of its rotation channels.

        Axes a joint lacks are appended in XYZ order (their angle is 0); a joint without rotation
        channels gets the file's most common full order, so re-export stays uniform.
        """
        full = [self._rot_axes(j) for j in range(self.n_joints)]
        complete = ["".join("XYZ"[a] for a in ax) for ax in full if len(ax) == 3]
        default = Counter(complete).most_common(1)[0][0] if complete else "ZXY"
        out = []
        for ax in full:
            if not ax:
                out.append(default)
            else:
                out.append("".join("XYZ"[a] for a in ax) + "".join(c for c in "XYZ" if "XYZ".index(c) not in ax))
        return out

    def _rot_axes(self, j: int) -> list[int]:
        return [_channel_kind(c)[1] for c in self.channels[j] if _channel_kind(c)[0] == "rotation"]

    def _index_tables(self) -> tuple[np.ndarray, np.ndarray]:
        """(J,3) motion-column tables for rotations (in each joint's order) and positions (x,y,z); -1 = absent."""
        rot = np.full((self.n_joints, 3), -1, dtype=np.int64)
        pos = np.full((self.n_joints, 3), -1, dtype=np.int64)
        for j, (chans, start) in enumerate(zip(self.channels, self.channel_starts)):
            r = 0
            for k, c in enumerate(chans):
                kind, axis = _channel_kind(c)
                if kind == "rotation":
                    rot[j, r] = start + k
                    r += 1
                else:
                    pos[j, axis] = start + k
        return rot, pos

    def euler_degrees(self) -> np.ndarray:
        """(F, J, 3) Euler angles in degrees, each joint in its own :attr:`rotation_orders` order."""
        rot, _ = self._index_tables()
        padded = np.concatenate([self.motion, np.zeros((self.n_frames, 1))], axis=1)
        return padded[:, np.where(rot < 0, self.n_channels, rot)]

    def local_translations(self) -> np.ndarray:
        """(F, J, 3) translation of each joint in its parent's frame: position channels, else OFFSET."""
        _, pos = self._index_tables()
        padded = np.concatenate([self.motion, np.zeros((self.n_frames, 1))], axis=1)
        vals = padded[:, np.where(pos < 0, self.n_channels, pos)]
        return np.where(pos[None] >= 0, vals, self.offsets[None])

    def skeleton(self) -> Skeleton:
        """The joint tree with the declared OFFSETs and per-joint Euler orders."""
        return Skeleton(
            names=list(self.names),
            parents=list(self.parents),
            offsets=self.offsets.copy(),
            end_sites={k: v.copy() for k, v in self.end_sites.items()},
            rotation_orders=self.rotation_orders,
        )

    def copy(self) -> "Bvh":
        return Bvh(list(self.names), list(self.parents), self.offsets.copy(), [list(c) for c in self.channels],
                   {k: v.copy() for k, v in self.end_sites.items()}, float(self.frame_time), self.motion.copy())


# ====================================================================================== reading


def _strip_comment(tokens: list[str]) -> list[str]:
    """Drop a trailing ``#`` comment: a token that starts with ``#`` and everything after it.

    Exporters annotate hierarchy lines this way (MoDi's released files write ``End Site #name: Head``); a ``#``
    inside a token (a joint named ``Bone#2``) is part of the name.
    """
    for i, tok in enumerate(tokens):
        if tok.startswith("#"):
            return tokens[:i]
    return tokens


class _Tokens:
    """Whitespace tokens of the header (``#`` comments removed) with their 1-based line numbers."""

    def __init__(self, lines: list[str], path: str | None):
        self.lines = lines
        self.path = path
        self.row = 0  # next line to tokenize
        self.buf: list[str] = []
        self.buf_line = 0
        self.pos = 0

    def _fill(self) -> bool:
        while self.pos >= len(self.buf):
            if self.row >= len(self.lines):
                return False
            self.buf = _strip_comment(self.lines[self.row].split())
            self.buf_line = self.row + 1
            self.pos = 0
            self.row += 1
        return True

    def peek(self) -> str | None:
        return self.buf[self.pos] if self._fill() else None

    def line(self) -> int:
        """Line of the next token (or one past the end)."""
        return self.buf_line if self._fill() else len(self.lines) + 1

    def next(self, what: str) -> tuple[str, int]:
        if not self._fill():
            raise self.error(f"unexpected end of file, expected {what}", len(self.lines))
        tok = self.buf[self.pos]
        self.pos += 1
        return tok, self.buf_line

    def next_on_line(self, missing: str, line: int) -> str:
        """Next token, which must be on the same line as the keyword at ``line``; else BvhError(missing)."""
        if self.pos >= len(self.buf) or self.buf_line != line:
            raise self.error(missing, line)
        tok = self.buf[self.pos]
        self.pos += 1
        return tok

    def rest_of_line(self) -> tuple[list[str], int]:
        """Remaining tokens on the current line (used for names that may contain spaces)."""
        toks = self.buf[self.pos:]
        self.pos = len(self.buf)
        return toks, self.buf_line

    def error(self, message: str, line: int | None) -> BvhError:
        return BvhError(message, line=line, path=self.path)


def _number(tokens: _Tokens, what: str, same_line: int | None = None) -> float:
    if same_line is None:
        tok, line = tokens.next(what)
    else:
        tok, line = tokens.next_on_line(f"{what}: missing value", same_line), same_line
    try:
        v = float(tok)
    except ValueError:
        raise tokens.error(f"{what}: expected a number, got {tok!r}", line) from None
    if not math.isfinite(v):
        raise tokens.error(f"{what}: value {tok!r} is not finite", line)
    return v


def _offset(tokens: _Tokens, owner: str, line: int) -> np.ndarray:
    """The three numbers after OFFSET, on the OFFSET's own line."""
    return np.array([_number(tokens, f"OFFSET of {owner} (x y z)", line) for _ in range(3)], dtype=np.float64)


def _parse_hierarchy(tokens: _Tokens):
    tok, line = tokens.next("HIERARCHY")
    if tok.upper() != "HIERARCHY":
        raise tokens.error(f"expected HIERARCHY, got {tok!r}", line)
    tok, line = tokens.next("ROOT")
    if tok.upper() != "ROOT":
        raise tokens.error(f"expected ROOT after HIERARCHY, got {tok!r}", line)

    names: list[str] = []
    parents: list[int] = []
    offsets: list[np.ndarray | None] = []
    channels: list[list[str] | None] = []
    end_sites: dict[int, np.ndarray] = {}
    name_lines: dict[str, int] = {}

    def open_joint(parent: int, keyword: str) -> int:
        toks, nline = tokens.rest_of_line()
        if toks and toks[-1] == "{":
            toks = toks[:-1]
            brace_done = True
        else:
            brace_done = False
        if not toks or any(t in ("{", "}") for t in toks):
            raise tokens.error(f"{keyword} without a name", nline)
        name = " ".join(toks)
        if name in name_lines:
            raise tokens.error(f"duplicate joint name {name!r} (first on line {name_lines[name]})", nline)
        name_lines[name] = nline
        if not brace_done:
            tok, bline = tokens.next("'{'")
            if tok != "{":
                raise tokens.error(f"expected '{{' after {keyword} {name}, got {tok!r}", bline)
        names.append(name)
        parents.append(parent)
        offsets.append(None)
        channels.append(None)
        return len(names) - 1

    stack = [open_joint(-1, "ROOT")]
    while stack:
        j = stack[-1]
        tok, line = tokens.next(f"'}}' closing joint {names[j]!r}")
        key = tok.upper()
        if key == "OFFSET":
            if offsets[j] is not None:
                raise tokens.error(f"second OFFSET in joint {names[j]!r}", line)
            offsets[j] = _offset(tokens, names[j], line)
        elif key == "CHANNELS":
            if channels[j] is not None:
                raise tokens.error(f"second CHANNELS in joint {names[j]!r}", line)
            ntok, nline = tokens.next_on_line("CHANNELS without a count", line), line
            try:
                n = int(ntok)
            except ValueError:
                raise tokens.error(f"CHANNELS count must be an integer, got {ntok!r}", nline) from None
            if not 0 <= n <= 6:
                raise tokens.error(f"CHANNELS count must be 0..6, got {n}", nline)
            chans: list[str] = []
            for k in range(n):
                c, cline = tokens.next_on_line(
                    f"CHANNELS {n} lists only {k} channel names in joint {names[j]!r}", line), line
                if c.lower() not in _CHANNEL_KEY:
                    raise tokens.error(
                        f"unknown channel name {c!r} in joint {names[j]!r} (expected {n} of {', '.join(CHANNEL_NAMES)})",
                        cline,
                    )
                if any(x.lower() == c.lower() for x in chans):
                    raise tokens.error(f"channel {c!r} repeated in joint {names[j]!r}", cline)
                chans.append(c)
            channels[j] = chans
        elif key == "JOINT":
            stack.append(open_joint(j, "JOINT"))
        elif key == "END":
            site, sline = tokens.next("Site")
            if site.upper() != "SITE":
                raise tokens.error(f"expected 'End Site', got 'End {site}'", sline)
            if j in end_sites:
                raise tokens.error(f"second End Site in joint {names[j]!r}", line)
            # some exporters name the end effector on this line (``End Site Head_end``): skip such tokens, up to
            # a brace, so that a missing '{' is still reported below
            rest = tokens.buf if tokens.buf_line == sline else []
            while tokens.pos < len(rest) and rest[tokens.pos] not in ("{", "}"):
                tokens.pos += 1
            b, bline = tokens.next("'{'")
            if b != "{":
                raise tokens.error(f"expected '{{' after End Site, got {b!r}", bline)
            o, oline = tokens.next("OFFSET")
            if o.upper() != "OFFSET":
                raise tokens.error(f"End Site of {names[j]!r} must contain OFFSET, got {o!r}", oline)
            end_sites[j] = _offset(tokens, f"End Site of {names[j]}", oline)
            b, bline = tokens.next("'}'")
            if b != "}":
                raise tokens.error(f"expected '}}' closing End Site of {names[j]!r}, got {b!r}", bline)
        elif tok == "}":
            if offsets[j] is None:
                raise tokens.error(f"joint {names[j]!r} has no OFFSET", name_lines[names[j]])
            if channels[j] is None:
                channels[j] = []  # a joint without CHANNELS is animated by nothing
            stack.pop()
        elif key == "ROOT":
            raise tokens.error("more than one ROOT (only a single skeleton per file is supported)", line)
        elif key == "MOTION":
            raise tokens.error(f"unbalanced braces: MOTION reached while joint {names[j]!r} is still open", line)
        else:
            raise tokens.error(f"unexpected {tok!r} in joint {names[j]!r}", line)
    return names, parents, np.stack(offsets), channels, end_sites


def _parse_motion_header(tokens: _Tokens, check_frame_time: bool = True) -> tuple[int, float, int]:
    tok, line = tokens.next("MOTION")
    if tok.upper() == "ROOT":
        raise tokens.error("more than one ROOT (only a single skeleton per file is supported)", line)
    if tok == "}":
        raise tokens.error("unbalanced braces: '}' after the ROOT was closed", line)
    if tok.upper() != "MOTION":
        raise tokens.error(f"expected MOTION after the hierarchy, got {tok!r}", line)

    def keyword(expected: str) -> None:
        tok, line = tokens.next(f"'{expected}:'")
        if tok.lower() == expected.lower() + ":":
            return
        if tok.lower() == expected.lower():
            colon, cline = tokens.next("':'")
            if colon == ":":
                return
            raise tokens.error(f"expected ':' after {expected}, got {colon!r}", cline)
        raise tokens.error(f"expected '{expected}:', got {tok!r}", line)

    keyword("Frames")
    ftok, fline = tokens.next("frame count")
    try:
        n_frames = int(ftok)
    except ValueError:
        raise tokens.error(f"Frames: expected an integer, got {ftok!r}", fline) from None
    if n_frames <= 0:
        raise tokens.error(f"Frames: {n_frames} (a BVH needs at least one frame)", fline)
    tok, line = tokens.next("'Frame Time:'")
    if tok.lower() != "frame":
        raise tokens.error(f"expected 'Frame Time:', got {tok!r}", line)
    keyword("Time")
    frame_time = _number(tokens, "Frame Time")
    if frame_time <= 0 and check_frame_time:
        raise tokens.error(f"Frame Time must be positive, got {frame_time}", tokens.buf_line)
    if tokens.pos < len(tokens.buf):
        raise tokens.error(f"unexpected {tokens.buf[tokens.pos]!r} after the frame time", tokens.buf_line)
    return n_frames, frame_time, tokens.row  # data starts at this 0-based line index


def _parse_values(lines: list[str], start: int, n_frames: int, n_channels: int, path: str | None) -> np.ndarray:
    rows = [ln.split() for ln in lines[start:]]
    good = [r for r in rows if r]
    if len(good) == n_frames and all(len(r) == n_channels for r in good):
        try:
            data = np.array(good, dtype=np.float64)
        except ValueError:
            data = None
        if data is not None and np.isfinite(data).all():
            return data
    # slow path: find the first offending line (or convert token by token what numpy refused)
    seen = 0
    last = start  # 1-based line of the last frame line seen (or of the header's end)
    values: list[list[float]] = []
    for i, r in enumerate(rows):
        if not r:
            continue
        line = start + i + 1
        if seen == n_frames:
            raise BvhError(f"more frame lines than 'Frames: {n_frames}'", line=line, path=path)
        if len(r) != n_channels:
            raise BvhError(
                f"frame {seen + 1} has {len(r)} values, the hierarchy declares {n_channels} channels",
                line=line, path=path,
            )
        frame = []
        for tok in r:
            try:
                v = float(tok)
            except ValueError:
                raise BvhError(f"non-numeric value {tok!r} in frame {seen + 1}", line=line, path=path) from None
            if not math.isfinite(v):
                raise BvhError(f"non-finite value {tok!r} in frame {seen + 1}", line=line, path=path)
            frame.append(v)
        values.append(frame)
        seen += 1
        last = line
    if seen == n_frames:
        return np.array(values, dtype=np.float64)
    raise BvhError(
        f"truncated MOTION: 'Frames: {n_frames}' but only {seen} frame lines", line=last + 1, path=path
    )


def _read_text(source: str | os.PathLike | bytes) -> tuple[str, str | None]:
    if isinstance(source, bytes):
        raw, path = source, None
    elif isinstance(source, os.PathLike) or (
        isinstance(source, str) and source.strip() and "\n" not in source and "\r" not in source
        and not source.lstrip().upper().startswith("HIERARCHY")
    ):
        path = os.fspath(source)
        with open(path, "rb") as fh:
            raw = fh.read()
    elif isinstance(source, str):
        return source, None
    else:
        raise TypeError(f"bvh.load: expected a path, text or bytes, got {type(source).__name__}")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    return text, path


def load(source: str | os.PathLike | bytes, *, check_frame_time: bool = True) -> Bvh:
    """Read a BVH from a path, from bytes, or from text (a str that contains a line break or starts with HIERARCHY).

    Raises :class:`BvhError` (with ``.line``) for malformed content, ``FileNotFoundError`` for a missing path.
    ``check_frame_time=False`` accepts any finite Frame Time (some tools write 0): for callers that are told the
    true rate and replace ``frame_time`` themselves (``modi eval single --gen-fps``).
    """
    text, path = _read_text(source)
    return _parse(text, path, check_frame_time)


def loads(text: str, *, check_frame_time: bool = True) -> Bvh:
    """Parse BVH text (never interpreted as a path); ``check_frame_time`` as in :func:`load`."""
    if not isinstance(text, str):
        raise TypeError(f"bvh.loads: expected str, got {type(text).__name__}")
    return _parse(text, None, check_frame_time)


def _parse(text: str, path: str | None, check_frame_time: bool = True) -> Bvh:
    if text.startswith("\ufeff"):
        text = text[1:]
    if "\r" in text:
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    lines = text.split("\n")
    if not text.strip():
        raise BvhError("empty file", line=1, path=path)
    tokens = _Tokens(lines, path)
    names, parents, offsets, channels, end_sites = _parse_hierarchy(tokens)
    n_channels = sum(len(c) for c in channels)
    n_frames, frame_time, start = _parse_motion_header(tokens, check_frame_time)
    if n_channels == 0:
        raise BvhError("the hierarchy declares no channels", line=start, path=path)
    motion = _parse_values(lines, start, n_frames, n_channels, path)
    return Bvh(names, parents, offsets, channels, end_sites, frame_time, motion)


# ====================================================================================== writing


def _fmt_vec(v: np.ndarray, precision: int) -> str:
    return " ".join(f"{float(x):.{precision}f}" for x in v)


def _depth_first(parents: list[int]) -> tuple[list[int], dict[int, list[int]]]:
    children: dict[int, list[int]] = {j: [] for j in range(len(parents))}
    for j, p in enumerate(parents):
        if j == 0:
            if p != -1:
                raise ValueError("bvh: joint 0 must be the root (parent -1)")
        elif not 0 <= p < j:
            raise ValueError(f"bvh: joint {j} has parent {p}; parents must precede children")
        else:
            children[p].append(j)
    order: list[int] = []
    stack = [0]
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(reversed(children[j]))
    return order, children


def dumps(bvh: Bvh, precision: int = 6) -> str:
    """BVH text for ``bvh`` (tabs, LF); values with ``precision`` decimals.

    Joints are written depth-first (the only order BVH can express); a ``Bvh`` whose joint order is
    topological but not depth-first is written with its joints — and motion columns — in that order.
    """
    if not isinstance(bvh, Bvh):
        raise TypeError(f"bvh.save: expected a Bvh, got {type(bvh).__name__}")
    motion = np.asarray(bvh.motion, dtype=np.float64)
    if motion.ndim != 2 or motion.shape[1] != bvh.n_channels or motion.shape[0] == 0:
        raise ValueError(f"bvh.save: motion must be (frames >= 1, {bvh.n_channels}), got {motion.shape}")
    if not np.isfinite(motion).all():
        raise ValueError("bvh.save: motion contains NaN or inf")
    if not np.isfinite(bvh.offsets).all():
        raise ValueError("bvh.save: offsets contain NaN or inf")
    if not (math.isfinite(bvh.frame_time) and bvh.frame_time > 0):
        raise ValueError(f"bvh.save: frame_time must be positive, got {bvh.frame_time}")
    order, children = _depth_first(bvh.parents)
    starts = bvh.channel_starts
    columns = [starts[j] + k for j in order for k in range(len(bvh.channels[j]))]
    if columns != list(range(bvh.n_channels)):
        motion = motion[:, columns]

    out: list[str] = ["HIERARCHY"]
    # iterative depth-first walk: ("open", j, depth) / ("close", j, depth) events (no recursion limit)
    stack: list[tuple[str, int, int]] = [("open", 0, 0)]
    while stack:
        event, j, depth = stack.pop()
        ind = "\t" * depth
        if event == "open":
            out.append(f"{ind}{'ROOT' if j == 0 else 'JOINT'} {bvh.names[j]}")
            out.append(f"{ind}{{")
            out.append(f"{ind}\tOFFSET {_fmt_vec(bvh.offsets[j], precision)}")
            out.append(f"{ind}\tCHANNELS {len(bvh.channels[j])}" + "".join(f" {c}" for c in bvh.channels[j]))
            stack.append(("close", j, depth))
            stack.extend(("open", c, depth + 1) for c in reversed(children[j]))
        else:
            if j in bvh.end_sites:
                out.append(f"{ind}\tEnd Site")
                out.append(f"{ind}\t{{")
                out.append(f"{ind}\t\tOFFSET {_fmt_vec(bvh.end_sites[j], precision)}")
                out.append(f"{ind}\t}}")
            out.append(f"{ind}}}")
    out.append("MOTION")
    out.append(f"Frames: {motion.shape[0]}")
    out.append(f"Frame Time: {bvh.frame_time:.8f}")
    row = " ".join([f"%.{precision}f"] * motion.shape[1])
    body = [row % tuple(r) for r in motion.tolist()]
    return "\n".join(out + body) + "\n"


def save(bvh: Bvh, path: str | os.PathLike, precision: int = 6) -> None:
    """Write ``bvh`` to ``path`` (see :func:`dumps`) through :func:`modi.faults.atomic_write`, so a crash or a full
    disk never leaves half a file (a full disk is one ``OutputError`` line)."""
    atomic_write(path, dumps(bvh, precision))
