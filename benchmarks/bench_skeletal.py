"""pytest-benchmark suite for the skeletal ops (same cases as compare.py; run ``pytest benchmarks/bench_skeletal.py``).

Benchmarks are not tests: they assert nothing about speed.  ``compare.py`` reports the ref/ext ratios.
"""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from compare import skeletal_cases  # noqa: E402

from modi_ext import HAS_EXT  # noqa: E402

_CASES, _INFO, _SOURCE = skeletal_cases() if HAS_EXT else ({}, {}, "")
SELECTED = [name for name in _CASES if name.split(".")[1] in ("finest", "level1") or name.endswith("coarsest.fwd")]


@pytest.mark.skipif(not HAS_EXT, reason="modi_ext C++ extension not built")
@pytest.mark.parametrize("impl", ["ext", "ref"])
@pytest.mark.parametrize("case", SELECTED or ["none"])
def test_skeletal(benchmark, case, impl):
    ref_fn, ext_fn = _CASES[case]
    fn = ext_fn if impl == "ext" else ref_fn
    benchmark.group = case
    benchmark.extra_info.update(_INFO.get(case, {}))
    benchmark(fn)
