"""modi.models.optim: what both trainers share about the loop's runtime."""
from __future__ import annotations

import gc

import pytest

from modi.models.optim import frozen_heap


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
