"""The one background ``modi`` process the add-on runs at a time, and what Blender shows about it.

Blender talks to modi through files only: the command's combined output goes to ``LOG`` (its last line is the
one-line error when it fails), and training rewrites ``RUN/progress.json`` (stage, iteration, ETA). Nothing here
imports bpy, so the logic is the same in the UI, in ``blender -b`` and in tests.
"""
from __future__ import annotations

import json
import os
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
