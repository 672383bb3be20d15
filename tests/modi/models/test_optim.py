"""modi.models.optim: what both trainers share about the loop's runtime."""
from __future__ import annotations

import ctypes
import ctypes.util
import gc
import subprocess
import sys
from pathlib import Path

import pytest

from modi.models.optim import frozen_heap

REPO = Path(__file__).resolve().parents[3]


@pytest.fixture(autouse=True)
def _no_freeze_left():
    gc.unfreeze()
    yield
    gc.unfreeze()


def test_frozen_heap_freezes_the_objects_of_the_time_and_gives_them_back():
    old = [[1], [2]]
    with frozen_heap():
        assert gc.get_freeze_count() > 0
        tracked = {id(o) for o in gc.get_objects()}  # the collector's generations, not the frozen ones
        assert id(old) not in tracked
        young = [[3]]  # made inside: still the collector's
        assert id(young) in {id(o) for o in gc.get_objects()}
    assert gc.get_freeze_count() == 0
    assert id(old) in {id(o) for o in gc.get_objects()}


def test_frozen_heap_unfreezes_on_an_exception():
    with pytest.raises(RuntimeError):
        with frozen_heap():
            raise RuntimeError("a failed step")
    assert gc.get_freeze_count() == 0


def test_frozen_heap_leaves_a_callers_freeze_in_place():
    gc.freeze()
    held = gc.get_freeze_count()
    with frozen_heap():
        pass
    assert gc.get_freeze_count() == held > 0


def test_garbage_cycles_made_inside_are_still_collected():
    class Node:
        pass

    with frozen_heap():
        a, b = Node(), Node()
        a.other, b.other = b, a
        ids = {id(a), id(b)}
        del a, b
        gc.collect()
        assert not any(id(o) in ids for o in gc.get_objects() if type(o).__name__ == "Node")


_HEAP_PROBE = r"""
import ctypes, ctypes.util, sys
from modi.models.optim import retain_freed_memory
applied = retain_freed_memory() if sys.argv[1] == "retain" else None
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
class Mallinfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks",
                 "keepcost")]
libc.mallinfo2.restype = Mallinfo2
mapped_before = libc.mallinfo2().hblks
p = libc.malloc(4 << 20)  # 4 MB: mapped on its own by default, from the heap once retained
mapped = libc.mallinfo2().hblks > mapped_before
ctypes.memset(p, 1, 4 << 20)
libc.free(p)
print(applied, mapped, libc.mallinfo2().keepcost >= 4 << 20)  # keepcost: free memory kept at the heap's top
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc (Linux) only")
def test_retain_freed_memory_keeps_large_blocks_in_the_heap():
    """In a fresh process each: by default glibc maps a 4 MB block on its own (given back on free); once retained,
    the block comes from the heap and, freed, stays there for the next allocation."""
    def probe(mode: str) -> str:
        out = subprocess.run([sys.executable, "-c", _HEAP_PROBE, mode], capture_output=True, text=True, check=True,
                             cwd=REPO)
        return out.stdout.split()

    try:
        ctypes.CDLL(ctypes.util.find_library("c")).mallinfo2
    except AttributeError:
        pytest.skip("this libc has no mallinfo2 (glibc >= 2.33)")
    assert probe("default") == ["None", "True", "False"]
    assert probe("retain") == ["True", "False", "True"]
