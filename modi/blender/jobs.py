"""The one background ``modi`` process the add-on runs at a time, and what Blender shows about it.

It also plans the applications (loop, in-between, expand, body-part edit, harmonisation): which actions go to
modi as which BVH and with which flags (:func:`plan`), and the checks that refuse bad input before anything runs.

Blender talks to modi through files only: the command's combined output goes to ``LOG`` (its last line is the
one-line error when it fails), and training rewrites ``RUN/progress.json`` (stage, iteration, ETA). Nothing here
imports bpy, so the logic is the same in the UI, in ``blender -b`` and in tests.
"""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time

SIGTERM_EXIT = 128 + signal.SIGTERM  # what modi exits with after saving on SIGTERM


def last_line(text: str) -> str:
    """The last non-empty line of a log, where progress bars overwrite themselves with carriage returns; a
    ``modi: error:`` line wins over anything printed after it."""
    lines = [seg.strip() for ln in (text or "").splitlines() for seg in ln.split("\r") if seg.strip()]
    errors = [ln for ln in lines if ln.startswith("modi: error:")]
    if errors:
        return errors[-1][len("modi: error:"):].strip()
    return lines[-1] if lines else ""


def _duration(s: float) -> str:
    s = int(round(s))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s" if s >= 60 else f"{s}s"


def progress_text(info: dict) -> str:
    """One status line from ``progress.json``: stage (block of levels), iteration, ETA."""
    lo, hi = info.get("levels", [0, 0])
    text = (f"levels {lo}-{hi} of {info.get('n_levels', '?')} (block {info.get('block')}/{info.get('blocks')}): "
            f"{info.get('iteration')}/{info.get('iterations')}")
    done, total = info.get("done_iterations"), info.get("total_iterations")
    if done is not None and total:
        text += f", {100.0 * done / total:.0f}% of all"
    if info.get("eta_s") is not None:
        text += f", ETA {_duration(info['eta_s'])}"
    return text


class Job:
    """``argv`` running in the background, its output in ``log_path``; ``progress_path`` (optional) is read for
    the status line. ``kind`` is what the panel calls it ("training", "generating", "sampling")."""

    def __init__(self, kind: str, argv: list, log_path: str, progress_path: str | None = None,
                 env: dict | None = None):
        self.kind, self.argv, self.log_path, self.progress_path = kind, list(argv), log_path, progress_path
        self.started = time.time()
        self.returncode = None
        self._log = open(log_path, "w")
        try:
            # its own session: a Ctrl-C in Blender's terminal does not reach it; Cancel sends SIGTERM on purpose
            self.proc = subprocess.Popen(self.argv, stdout=self._log, stderr=subprocess.STDOUT,
                                         stdin=subprocess.DEVNULL, start_new_session=True, env=env)
        except OSError as e:
            self._log.close()
            raise RuntimeError(f"cannot start {self.argv[0]!r}: {e.strerror or e}") from None

    def poll(self):
        """The exit code once finished, else None."""
        if self.returncode is None:
            rc = self.proc.poll()
            if rc is not None:
                self.returncode = rc
                self._log.close()
        return self.returncode

    def wait(self, timeout: float | None = None, tick=None) -> int:
        """Block until done (scripts and ``blender -b``), calling ``tick()`` every 0.2 s."""
        end = None if timeout is None else time.time() + timeout
        while self.poll() is None:
            if end is not None and time.time() > end:
                self.cancel()
                self.proc.wait()
                self.poll()
                break
            if tick is not None:
                tick()
            time.sleep(0.2)
        return self.returncode

    def cancel(self) -> bool:
        """SIGTERM: modi finishes the iteration, saves a resumable checkpoint and exits 143."""
        if self.poll() is not None:
            return False
        self.proc.send_signal(signal.SIGTERM)
        return True

    def output(self) -> str:
        try:
            with open(self.log_path, errors="replace") as fh:
                return fh.read()
        except OSError:
            return ""

    def progress(self) -> dict | None:
        if not self.progress_path:
            return None
        try:
            with open(self.progress_path) as fh:
                return json.load(fh)
        except (OSError, ValueError):
            return None

    def status(self) -> str:
        """The line the panel and the status bar show."""
        rc = self.poll()
        if rc is None:
            info = self.progress()
            if info and info.get("state") == "training":
                return f"{self.kind}: {progress_text(info)}"
            line = last_line(self.output())
            return f"{self.kind} ({_duration(time.time() - self.started)})" + (f": {line}" if line else "")
        return self.outcome()

    def outcome(self) -> str:
        rc = self.returncode
        if rc == 0:
            return f"{self.kind} finished"
        if rc == SIGTERM_EXIT:
            return f"{self.kind} stopped; the run is saved and Resume continues it"
        line = last_line(self.output()) or f"exited with status {rc}"
        return f"modi failed: {line}"


def modi_env() -> dict:
    """The environment for modi without ``PYTHONHOME`` (a Blender build may set it for its bundled Python; the
    user's interpreter must not look there)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONHOME"}
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


# ------------------------------------------------------------------------------------------------- applications
# Loops, in-betweens, expansion, body-part edits and harmonisation: which actions go to modi as which BVH, and the
# ``modi ganimator generate`` flags that use them. Pure logic (no bpy): the operators gather names and frame
# ranges from the scene and pass them here.

APPLICATIONS = ("loop", "inbetween", "expand", "edit", "harmonise")
LABELS = {"loop": "Loop", "inbetween": "In-between", "expand": "Expand", "edit": "Edit Body Part",
          "harmonise": "Harmonise"}


class Refused(Exception):
    """An operator cannot start; the message is its one report line."""


MAX_NAME = 63  # bytes of a Blender ID name (longer names are cut, which would cut the seed and index off)


def action_name(stem: str, seed: int, index: int) -> str:
    """``<stem>.s<seed>.<index>``, the stem shortened (whole UTF-8 characters) so the name fits Blender's 63 bytes
    and keeps its seed and index."""
    suffix = f".s{seed:04d}.{index:03d}"
    room = MAX_NAME - len(suffix.encode())
    raw = stem.encode()
    if len(raw) > room:
        stem = raw[:room].decode(errors="ignore")
    return stem + suffix


def generate_argv(exe: str, run: str, out: str, *, n: int, seed: int, ik: bool = False, extra=()) -> list:
    """``modi ganimator generate RUN --out OUT`` as the add-on runs it: BVH only (no GIF, no viewer page), every
    motion at its own start (no crowd grid), then the application's flags ``extra``."""
    argv = [exe, "ganimator", "generate", run, "--out", out, "--n", str(n), "--seed", str(seed), "--no-gif",
            "--no-view", "--crowd-spacing", "0", *extra]
    if ik:
        argv.append("--ik")
    return argv


_BONE_PATH = re.compile(r'^pose\.bones\["((?:[^"\\]|\\.)*)"\]')


def bones_in_paths(paths) -> list:
    """The bone names an action's F-curve data paths animate (``pose.bones["NAME"].rotation_quaternion``...),
    first seen first."""
    out = []
    for p in paths:
        m = _BONE_PATH.match(p or "")
        if m:
            name = m.group(1).replace('\\"', '"').replace("\\\\", "\\")
            if name not in out:
                out.append(name)
    return out


def check_action_on_rig(action: str, paths, bones, armature: str) -> None:
    """Refuse an action that animates none of ``armature``'s bones (made for another rig, or without keys)."""
    animated = bones_in_paths(paths)
    if not animated:
        raise Refused(f"action {action!r} keys no bones (nothing to send to modi); choose an action of "
                      f"armature {armature!r}")
    bones = set(bones)
    if not any(b in bones for b in animated):
        raise Refused(f"action {action!r} animates another rig (bones {animated[:3]} are not bones of "
                      f"{armature!r}); choose an action of this armature")


def bare_joint(bone: str) -> str:
    """The joint name modi reads for a bone: spaces become '_' and a namespace prefix ('mixamorig:') is dropped."""
    return (re.sub(r"\s+", "_", bone.strip()) or "_").rsplit(":", 1)[-1]


def bvh_joint_names(path: str) -> list | None:
    """The joint names of a BVH's hierarchy (None when it cannot be read)."""
    try:
        with open(path) as fh:
            tok = fh.read().split("MOTION", 1)[0].split()
    except OSError:
        return None
    return [tok[i + 1] for i, t in enumerate(tok[:-1]) if t in ("ROOT", "JOINT")]


def check_run_rig(run_joints, bones, armature: str, run: str) -> None:
    """Refuse an armature that is not the rig the run learned (``run_joints``: its ``source.bvh``'s joints; None:
    unknown, left to modi)."""
    if not run_joints:
        return
    have = {bare_joint(b) for b in bones}
    missing = [j for j in run_joints if bare_joint(j) not in have]
    if missing:
        raise Refused(f"armature {armature!r} is not the rig the run {os.path.basename(os.path.normpath(run))!r} "
                      f"learned: it has no bones {missing[:3]}{' ...' if len(missing) > 3 else ''}")


def keep_arg(keep: str, selected=()) -> str:
    """``--keep``'s value: ``upper`` / ``lower``, or the selected bones (``selected``) as comma-separated joint
    names."""
    if keep in ("upper", "lower"):
        return keep
    names = [bare_joint(b) for b in selected]
    if not names:
        raise Refused("select the bones to keep (Pose Mode), or keep the upper or lower body")
    bad = [n for n in names if "," in n]
    if bad:
        raise Refused(f"bone {bad[0]!r} has a comma in its name; keep upper or lower instead")
    return ",".join(names)


class Plan:
    """What one application sends to modi and how its result comes back.

    ``exports``: ``{file name in the output folder: action name}`` to write as BVH before modi starts; ``args``:
    the flags after :func:`generate_argv`'s (file names relative to the output folder, turned into paths by
    :meth:`argv`); ``stem``: the new actions' name stem; ``frame_start``: the scene frame the result's first frame
    lands on (None: the scene's start); ``cyclic``: the result loops (its actions cycle)."""

    def __init__(self, app, exports, args, stem, frame_start=None, cyclic=False):
        self.app, self.exports, self.args, self.stem = app, dict(exports), list(args), stem
        self.frame_start, self.cyclic = frame_start, cyclic

    def flags(self, out: str) -> list:
        """``args`` with each exported file (and ``FILE@F``) as its path under ``out``."""
        res = []
        for a in self.args:
            head, at, tail = a.partition("@")
            res.append(os.path.join(out, head) + at + tail if head in self.exports else a)
        return res

    def __repr__(self):
        return f"Plan({self.app!r}, exports={self.exports}, args={self.args}, stem={self.stem!r}, " \
               f"frame_start={self.frame_start}, cyclic={self.cyclic})"


def plan(app: str, action: tuple, *, to_action: tuple | None = None, frames: int = 0, span: str = "poses",
         loop_root: str = "travel", at: int = -1, keep: str = "upper", selected=(), level: int = 1) -> Plan:
    """The plan of application ``app`` (:data:`APPLICATIONS`) on ``action`` = ``(name, first frame, last frame)``.

    * ``loop``: ``frames`` frames (0: the run's length) whose last flows into the first; ``loop_root``;
    * ``inbetween``: from ``action`` to ``to_action`` (None or the same: the action back to its own start, to make
      it cycle) with ``frames`` generated frames between. ``span="poses"``: the end pose of one and the start pose
      of the other (``FILE@-1``, ``FILE@0``), the result is the transition with both poses at its ends and starts
      on the action's last frame; ``span="actions"``: the whole actions stay around it (one action: the action,
      then the transition back to its first pose);
    * ``expand``: ``action`` inside a ``frames``-frame motion, from output frame ``at`` (-1: centred);
    * ``edit``: ``action``'s ``keep`` joints (upper, lower, or ``selected`` bones) kept, the rest generated;
    * ``harmonise``: ``action`` injected at pyramid level ``level`` (0: style transfer)."""
    if app not in APPLICATIONS:
        raise Refused(f"unknown application {app!r} (one of {', '.join(APPLICATIONS)})")
    name, lo, hi = action
    n_src = hi - lo + 1
    if app == "loop":
        args = ["--loop", "--loop-root", loop_root] + (["--frames", str(frames)] if frames > 0 else [])
        return Plan(app, {}, args, f"{name}.modi.loop", cyclic=True)
    if app == "inbetween":
        if frames < 1:
            raise Refused("In-between needs at least 1 frame between the two")
        same = to_action is None or to_action[0] == name
        to = action if same else to_action
        if span not in ("poses", "actions"):
            raise Refused(f"unknown span {span!r} (poses or actions)")
        exports = {"from.bvh": name} if same else {"from.bvh": name, "to.bvh": to[0]}
        to_file = "from.bvh" if same else "to.bvh"
        start = "from.bvh@-1" if span == "poses" else "from.bvh"
        end = f"{to_file}@0" if span == "poses" or same else to_file
        stem = f"{name}.modi.cycle" if same else f"{name}.modi.to.{to[0]}"
        return Plan(app, exports, ["--inbetween", start, end, "--frames", str(frames)], stem,
                    frame_start=hi if span == "poses" else lo)
    if app == "expand":
        if at < 0 and frames > n_src:
            at = (frames - n_src) // 2  # centred, as modi centres it: said here so the action lands in place
        args = ["--expand", "clip.bvh", "--frames", str(frames)] + (["--at", str(at)] if at >= 0 else [])
        start = lo - at if at >= 0 else None  # the clip's frames keep their scene frames
        return Plan(app, {"clip.bvh": name}, args, f"{name}.modi.expand", frame_start=start)
    if app == "edit":
        k = keep_arg(keep, selected) if keep == "selected" else keep_arg(keep)
        return Plan(app, {"clip.bvh": name}, ["--edit", "clip.bvh", "--keep", k],
                    f"{name}.modi.{keep if keep != 'selected' else 'kept'}", frame_start=lo)
    return Plan(app, {"clip.bvh": name}, ["--content", "clip.bvh", "--content-level", str(level)],
                f"{name}.modi.{'harmonised' if level else 'styled'}", frame_start=lo)
