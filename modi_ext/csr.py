"""Topology as data: neighbor lists / pooling maps (lists of lists) -> CSR index tensors.

Every skeletal op takes a CSR map from each *output* entity ``j`` to the input entities it reads:
``index[offsets[j]:offsets[j+1]]`` (int64).  Entry ``p`` of ``index`` is a "pair" ``(j, index[p])``; the
compact weights store one ``(Cout, Cin, U)`` block per pair, so only connections that exist cost memory
and multiply-adds.  Validation happens here, once, with messages that name the offending list entry.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch


@dataclass(frozen=True)
class SparseTopology:
    """CSR form of ``lists`` (output entity -> input entities); ``pair_entity[p]`` is the output entity of pair p."""

    index: torch.Tensor
    offsets: torch.Tensor
    pair_entity: torch.Tensor
    n_out: int
    n_in: int

    @property
    def nnz(self) -> int:
        return int(self.index.numel())

    def fan_in_counts(self) -> torch.Tensor:
        """Number of input entities each output entity reads (|N(j)|), int64 (n_out,)."""
        return self.offsets[1:] - self.offsets[:-1]

    def in_degree(self) -> torch.Tensor:
        """How many output entities read each input entity, int64 (n_in,)."""
        return torch.bincount(self.index, minlength=self.n_in)


def csr_from_lists(lists: Sequence[Sequence[int]], n_in: int | None = None, *,
                   name: str = "neighbors", require_cover: bool = False) -> SparseTopology:
    """Validate ``lists`` and build its CSR tensors.

    ``n_in`` is the number of input entities (default: largest index + 1).  Each row must be non-empty, hold
    distinct integers in ``[0, n_in)``; rows keep their given order.  ``require_cover`` demands that every input
    entity appears in some row (a pooling map must cover every fine entity, or the upsampler leaves it empty).
    """
    if isinstance(lists, torch.Tensor) or not isinstance(lists, Sequence) or isinstance(lists, (str, bytes)):
        raise TypeError(f"{name} must be a list of lists of ints, got {type(lists).__name__}")
    if len(lists) == 0:
        raise ValueError(f"{name} is empty: need at least one output entity")
    flat: list[int] = []
    offsets = [0]
    for j, row in enumerate(lists):
        if isinstance(row, (str, bytes)) or not isinstance(row, Sequence):
            raise TypeError(f"{name}[{j}] must be a list of ints, got {type(row).__name__}")
        if len(row) == 0:
            raise ValueError(f"{name}[{j}] is empty: entity {j} has no neighbors")
        seen = set()
        for n in row:
            if isinstance(n, bool) or not isinstance(n, int):
                try:
                    import numpy as np  # lazy: numpy is an optional dependency; ints from numpy arrays are fine
                    if isinstance(n, np.integer):
                        n = int(n)
                    else:
                        raise TypeError
                except (ImportError, TypeError):
                    raise TypeError(f"{name}[{j}] holds {n!r}, not an int") from None
            if n < 0:
                raise ValueError(f"{name}[{j}] holds negative index {n}")
            if n in seen:
                raise ValueError(f"{name}[{j}] lists entity {n} twice")
            seen.add(n)
            flat.append(int(n))
        offsets.append(len(flat))
    top = max(flat) + 1
    if n_in is None:
        n_in = top
    elif top > n_in:
        bad = next(j for j, row in enumerate(lists) if max(int(v) for v in row) >= n_in)
        raise ValueError(f"{name}[{bad}] holds index {max(int(v) for v in lists[bad])} out of range "
                         f"for {n_in} input entities")
    if require_cover:
        missing = sorted(set(range(n_in)) - set(flat))
        if missing:
            raise ValueError(f"{name} does not cover input entities {missing[:10]}: each fine entity must belong "
                             f"to some coarse entity")
    index = torch.tensor(flat, dtype=torch.int64)
    off = torch.tensor(offsets, dtype=torch.int64)
    return SparseTopology(index=index, offsets=off, pair_entity=pair_entity(off, len(flat)), n_out=len(lists),
                          n_in=int(n_in))


def pair_entity(offsets: torch.Tensor, nnz: int) -> torch.Tensor:
    """Output entity of each pair, from CSR offsets (compile-friendly: the output size is given)."""
    # repeat_interleave(counts) is [0] * counts[0] + [1] * counts[1] + ...: the entity of each pair, in one op
    return torch.repeat_interleave(offsets.diff(), output_size=nnz)
