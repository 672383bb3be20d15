"""Random skeletal-op cases shared by the op families' tests (``skeletal/``, ``demod/``, ``runtime/``): random trees
and poolings built here (independent of ``modi.core.skeleton_graph``), one op call's inputs, and a uniform call of the
public op or the reference.  Importable by name from any test folder: ``tests/modi_ext/conftest.py`` puts this folder
on ``sys.path``."""
from __future__ import annotations

import random

import torch

from modi_ext.csr import csr_from_lists
from modi_ext.skeletal import ops
from modi_ext.skeletal import reference as R

KINDS = ("conv", "down", "up")


# ----------------------------------------------------------------------------------------------- topology helpers
def random_parents(n: int, rng: random.Random) -> list[int]:
    return [-1] + [rng.randrange(j) for j in range(1, n)]


def tree_neighbors(parents: list[int], distance: int) -> list[list[int]]:
    """Entities within `distance` tree hops (self included), sorted: built here, independent of modi.core.skeleton_graph."""
    adj = [set() for _ in parents]
    for j, p in enumerate(parents):
        if p >= 0:
            adj[j].add(p)
            adj[p].add(j)
    out = []
    for j in range(len(parents)):
        seen, front = {j}, {j}
        for _ in range(distance):
            front = {m for f in front for m in adj[f]} - seen
            seen |= front
        out.append(sorted(seen))
    return out


def random_pooling(n_fine: int, rng: random.Random) -> list[list[int]]:
    """Random partition of the fine entities into coarse groups of 1-3 (order shuffled)."""
    fine = list(range(n_fine))
    rng.shuffle(fine)
    groups, i = [], 0
    while i < n_fine:
        k = rng.randint(1, 3)
        groups.append(sorted(fine[i:i + k]))
        i += k
    return groups


def make_case(kind: str, rng: random.Random, dtype=torch.float64, n_joints=None, distance=None, U=None,
              B=2, cin=3, cout=4, T=None, style=None, demod=None, padding=None, bias=True):
    """Random inputs for one op call: returns (args, kwargs) of the public ops function (positional order)."""
    n = n_joints or rng.randint(2, 40)
    d = distance or rng.randint(1, 2)
    U = U or rng.choice([1, 3, 5])
    T = T or rng.randint(4, 12)
    style = rng.random() < 0.5 if style is None else style
    demod = rng.random() < 0.5 if demod is None else demod
    padding = padding or rng.choice(["zeros", "reflect"])
    g = torch.Generator().manual_seed(rng.randrange(2**31))
    if kind == "conv":
        topo = csr_from_lists(tree_neighbors(random_parents(n, rng), d))
        x = torch.randn(B, cin, n, T, dtype=dtype, generator=g)
        w = torch.randn(cout, topo.nnz, cin, U, dtype=dtype, generator=g)
        extra = ()
    else:
        topo = csr_from_lists(random_pooling(n, rng), require_cover=True)
        if kind == "down":
            x = torch.randn(B, cin, n, T, dtype=dtype, generator=g)
            w = torch.randn(cout, topo.nnz, cin, U, dtype=dtype, generator=g)
            extra = ()
        else:
            x = torch.randn(B, cin, topo.n_out, T, dtype=dtype, generator=g)
            w = torch.randn(cin, topo.nnz, cout, U, dtype=dtype, generator=g)
            extra = (n,)
    b = torch.randn(cout, dtype=dtype, generator=g) if bias else None
    s = torch.randn(B, cin, dtype=dtype, generator=g) if style else None
    args = (x, w, b, topo.index, topo.offsets) + extra
    return args, dict(style=s, demodulate=demod, padding_mode=padding)


def call(kind: str, fn_mod, args, kw):
    """Call ops.* or reference.* (which takes style/demod/padding positionally) uniformly."""
    if fn_mod is ops:
        return getattr(ops, f"skeletal_{kind}")(*args, **kw)
    return getattr(R, f"skeletal_{kind}")(*args, kw["style"], kw["demodulate"], kw["padding_mode"])
