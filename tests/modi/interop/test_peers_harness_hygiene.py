"""The released-code harness leaves the process as it found it: other tests (and sklearn) share the interpreter."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.peers import released_modi as R  # noqa: E402

STAND_INS = ("pandas", "cv2", "numpy.core.umath_tests")


def test_no_stand_in_module_is_left_behind():
    """Stand-ins for modules the released code imports but never calls are gone after the block: sklearn
    (`modi latent cluster`) takes any `pandas` in `sys.modules` for the real one and failed on the stand-in."""
    try:
        R.require_peer()
    except Exception as exc:  # noqa: BLE001 - the peer sources are optional
        pytest.skip(f"the released MoDi cannot run here: {exc}")
    assert not R._ACTIVE, "an outer peer_runtime block is open: this test would see nothing"
    before = {n: sys.modules.get(n) for n in STAND_INS}
    with R.peer_runtime():
        assert all(n in sys.modules for n in ("pandas", "cv2")), "the released imports need these names"
    assert {n: sys.modules.get(n) for n in STAND_INS} == before
