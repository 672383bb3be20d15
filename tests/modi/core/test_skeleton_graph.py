"""Skeleton subsets/feet/height and topology: neighbour lists, entity layout, pooling hierarchies."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from modi.core.skeleton import Skeleton
from modi.core.skeleton_graph import (
    EntityLayout,
    PoolingHierarchy,
    build_hierarchy,
    neighbors,
    neighbors_from_adjacency,
)


def _tree(parents: list[int], names: list[str] | None = None) -> Skeleton:
    n = len(parents)
    rng = np.random.default_rng(n)
    return Skeleton(names or [f"j{i}" for i in range(n)], parents, rng.normal(size=(n, 3)))


def _humanoid20() -> Skeleton:
    """Hips; legs of 4 edges; 3 spine edges; neck + head; arms of 3 edges: the 20-edge layout of MoDi's Table 3."""
    names, parents = ["Hips"], [-1]

    def chain(start_parent: int, labels: list[str]) -> int:
        p = start_parent
        for lab in labels:
            names.append(lab)
            parents.append(p)
            p = len(names) - 1
        return p

    chain(0, ["LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase"])
    chain(0, ["RightUpLeg", "RightLeg", "RightFoot", "RightToeBase"])
    chest = chain(0, ["Spine", "Spine1", "Spine2"])
    chain(chest, ["Neck", "Head"])
    chain(chest, ["LeftArm", "LeftForeArm", "LeftHand"])
    chain(chest, ["RightArm", "RightForeArm", "RightHand"])
    offsets = np.tile([0.0, 0.1, 0.0], (len(names), 1))
    return Skeleton(names, parents, offsets)


# ----------------------------------------------------------------------------------------------------------------
# neighbours and layout on hand-checked trees


def test_neighbors_small_tree_by_hand():
    parents = [-1, 0, 1, 1, 0]  # root edge 0; edge 1 branches into 2, 3; edge 4 is 1's sibling
    assert neighbors(parents, 1) == [[0, 1, 4], [0, 1, 2, 3, 4], [1, 2, 3], [1, 2, 3], [0, 1, 4]]
    assert neighbors(parents, 1, siblings=False) == [[0, 1, 4], [0, 1, 2, 3], [1, 2], [1, 3], [0, 4]]
    assert neighbors(parents, 0) == [[0], [1], [2], [3], [4]]
    assert neighbors(parents, 2, siblings=False)[2] == [0, 1, 2, 3]


def test_neighbors_rejects_bad_input():
    with pytest.raises(ValueError, match="parent"):
        neighbors([-1, 2, 0], 1)
    with pytest.raises(ValueError, match="distance"):
        neighbors([-1, 0], -1)


def test_entity_layout_by_hand():
    lay = EntityLayout([-1, 0, 1, 1, 0], foot_joints=[2, 3])
    assert (lay.n_edges, lay.root_motion, lay.contacts, lay.n_entities) == (5, 5, [6, 7], 8)
    nb = lay.neighbors(1)
    assert nb[5] == [0, 1, 4, 5]  # root motion: root edge and the root edge's neighbours
    assert nb[0] == [0, 1, 4, 5]
    assert nb[1] == [0, 1, 2, 3, 4, 5]
    assert nb[6] == [2, 6] and nb[7] == [3, 7]
    assert nb[2] == [1, 2, 3, 6]
    nb_rm = EntityLayout([-1, 0, 1, 1, 0], [2, 3], contacts_to_root_motion=True).neighbors(1)
    assert nb_rm[6] == [2, 5, 6] and 6 in nb_rm[5] and 7 in nb_rm[5]
    with pytest.raises(ValueError, match="foot joint"):
        EntityLayout([-1, 0], foot_joints=[5])


def test_humanoid20_matches_modi_table3():
    sk = _humanoid20()
    assert sk.n_joints == 20
    h = build_hierarchy(sk, feet=[sk.index("LeftFoot"), sk.index("RightFoot")])
    assert h.edge_counts == [20, 12, 7, 2, 1]
    assert h.entity_counts == [23, 15, 10, 5, 1]
    # level 3 is lower body (hips + legs) and upper body (spine, neck, arms)
    lv3 = h.levels[3]
    lower = {sk.names[e] for e in lv3.groups[0]}
    assert lower == {"Hips", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase",
                     "RightUpLeg", "RightLeg", "RightFoot", "RightToeBase"}
    # odd chains keep their root-side edge alone: Spine alone, Spine1+Spine2 merged
    lv1_sets = [set(g) for g in h.levels[1].groups]
    assert {sk.index("Spine")} in lv1_sets and {sk.index("Spine1"), sk.index("Spine2")} in lv1_sets


# ----------------------------------------------------------------------------------------------------------------
# invariants, on any tree


def _check_hierarchy(h: PoolingHierarchy, n_joints: int, n_feet: int) -> None:
    assert h.levels[-1].n_entities == 1
    assert h.levels[0].n_entities == n_joints + 1 + n_feet
    assert len(h.pooling) == len(h.levels) - 1
    for i, lv in enumerate(h.levels):
        n = lv.n_entities
        assert len(lv.neighbors) == n and len(lv.names) == n and len(lv.parents) == n and len(lv.groups) == n
        for j, nb in enumerate(lv.neighbors):
            assert j in nb and nb == sorted(set(nb)) and all(0 <= k < n for k in nb)
            for k in nb:
                assert j in lv.neighbors[k], f"level {i}: neighbours not symmetric ({j}, {k})"
        # connected
        seen, stack = {0}, [0]
        while stack:
            for k in lv.adjacency[stack.pop()]:
                if k not in seen:
                    seen.add(k)
                    stack.append(k)
        assert len(seen) == n, f"level {i} not connected"
        # parents form a tree ordered parent-first among edge entities
        roots = [j for j, p in enumerate(lv.parents) if p < 0]
        assert roots == [0]
        assert sorted(e for g in lv.groups for e in g) == list(range(h.levels[0].n_entities))
        if i < len(h.levels) - 1:
            assert lv.root_motion == lv.n_edge_entities and len(lv.contacts) == n_feet
    for i, pool in enumerate(h.pooling):
        fine, coarse = h.levels[i], h.levels[i + 1]
        assert len(pool) == coarse.n_entities
        flat = sorted(m for g in pool for m in g)
        assert flat == list(range(fine.n_entities)), f"pooling {i} is not a partition"
        assert len(pool) < fine.n_entities, "each step must merge something"
        for k, members in enumerate(pool):
            assert sorted(coarse.groups[k]) == sorted(e for m in members for e in fine.groups[m])
        if i < len(h.pooling) - 1:  # specials ride along unmerged
            assert pool[coarse.root_motion] == [fine.root_motion]
            assert [pool[c] for c in coarse.contacts] == [[c] for c in fine.contacts]


@st.composite
def trees(draw):
    n = draw(st.integers(2, 60))
    parents = [-1] + [draw(st.integers(0, j - 1)) for j in range(1, n)]
    feet = draw(st.lists(st.integers(0, n - 1), max_size=4, unique=True))
    dist = draw(st.integers(1, 3))
    return parents, feet, dist


@settings(max_examples=150, deadline=None)
@given(trees())
def test_random_trees_pool_to_one(case):
    parents, feet, dist = case
    h = build_hierarchy(_tree(parents), feet=feet, neighbor_distance=dist)
    _check_hierarchy(h, len(parents), len(feet))
    assert h.levels[0].neighbors == neighbors_from_adjacency(h.levels[0].adjacency, dist)
    assert h.neighbors(0, 1) == EntityLayout(parents, feet).neighbors(1)


def test_single_joint_and_chain():
    h = build_hierarchy(_tree([-1]), feet=[])
    assert h.entity_counts == [2, 1]
    h = build_hierarchy(_tree([-1, 0, 1, 2, 3, 4, 5, 6]), feet=[7])
    assert h.edge_counts == [8, 4, 2, 1]  # a chain halves each step


def test_hierarchy_dict_round_trip():
    h = build_hierarchy(_humanoid20(), feet=[3, 7], neighbor_distance=2)
    h2 = PoolingHierarchy.from_dict(h.to_dict())
    assert h2.to_dict() == h.to_dict()


# ----------------------------------------------------------------------------------------------------------------
# Skeleton: subset, reduce, feet, height


def test_subset_reparents_and_sums_offsets():
    sk = Skeleton(["a", "b", "c", "d"], [-1, 0, 1, 2],
                  np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3]], dtype=float))
    sub, kept = sk.subset(["a", "d"])
    assert kept == [0, 3] and sub.parents == [-1, 0]
    np.testing.assert_allclose(sub.offsets[1], [1, 2, 3])
    with pytest.raises(ValueError, match="root"):
        sk.subset([1, 2])
    with pytest.raises(KeyError, match="nope"):
        sk.subset(["a", "nope"])


@settings(max_examples=60, deadline=None)
@given(trees(), st.data())
def test_subset_keeps_rest_positions(case, data):
    parents, _, _ = case
    sk = _tree(parents)
    keep = [0] + data.draw(st.lists(st.integers(1, len(parents) - 1), unique=True)) if len(parents) > 1 else [0]
    sub, kept = sk.subset(keep)
    np.testing.assert_allclose(sub.rest_positions(), sk.rest_positions()[kept], atol=1e-9)
    for j, p in enumerate(sub.parents[1:], start=1):
        assert kept[p] in sk.ancestors(kept[j])


def test_reduce_patterns_and_keep():
    sk = _humanoid20()
    sub, kept = sk.reduce(drop_patterns=["hand$", "toe"], keep=["RightHand"])
    assert "LeftHand" not in sub.names and "RightHand" in sub.names
    assert not any("Toe" in n for n in sub.names)
    assert sub.n_joints == 17
    with pytest.raises(ValueError, match="root"):
        sk.reduce(drop_patterns=["hips"])
    with pytest.raises(ValueError, match="pattern"):
        sk.reduce(drop_patterns=["("])


def test_detect_feet_names_override_and_biped():
    sk = _humanoid20()
    assert [sk.names[j] for j in sk.detect_feet()] == ["LeftToeBase", "RightToeBase"]
    assert [sk.names[j] for j in sk.detect_feet(per_side=2)] == ["LeftFoot", "LeftToeBase", "RightFoot", "RightToeBase"]
    assert sk.detect_feet(names=["Head"]) == [sk.index("Head")]
    with pytest.raises(KeyError):
        sk.detect_feet(names=["Tail"])


def test_skeleton_dict_round_trip():
    sk = _humanoid20()
    assert Skeleton.from_dict(sk.to_dict()).same_as(sk)


# ----------------------------------------------------------------------------------------------------------------
# real skeletons


def _real(shared_data, rel: str) -> Skeleton:
    from modi.io import bvh

    return bvh.load(shared_data / "bvh" / rel).skeleton()


BANDAI = "bandai-namco-1/data/dataset-1_walk_normal_001.bvh"


def test_bandai_hierarchy(shared_data):
    sk = _real(shared_data, BANDAI)
    assert sk.n_joints == 22
    red, kept = sk.reduce()
    assert kept == list(range(22))  # nothing to drop on Bandai's rig
    feet = sk.detect_feet()
    assert [sk.names[f] for f in feet] == ["Toes_L", "Toes_R"]
    h = build_hierarchy(sk, feet)
    _check_hierarchy(h, 22, 2)
    # joint_Root+Hips pair, spine pair, neck pair, 2 pairs per limb -> 11; then 7 -> 2 -> 1
    assert h.edge_counts == [22, 11, 7, 2, 1]
    assert 120 < sk.height() < 200  # a person, in centimetres


def test_mixamo_reduction_matches_ganimator_24(shared_data):
    full = _real(shared_data, "ganimator/Joe/Salsa-Dancing-6.bvh")
    reduced_file = _real(shared_data, "ganimator/Joe/traj-example.bvh")
    assert full.n_joints == 65
    red, kept = full.reduce()
    assert sorted(n.split(":")[-1] for n in red.names) == sorted(reduced_file.names)
    np.testing.assert_allclose(red.rest_positions(), full.rest_positions()[kept], atol=1e-9)
    for sk in (full, red):
        feet = sk.detect_feet()
        assert [sk.names[f].split(":")[-1] for f in feet] == ["LeftToeBase", "RightToeBase"]
        _check_hierarchy(build_hierarchy(sk, feet, neighbor_distance=2), sk.n_joints, 2)
    assert 1.5 < reduced_file.height() < 2.1  # metres


@pytest.mark.parametrize(
    "rel, n_joints, n_feet, foot_word",
    [("ganimator/Crabnew/Crab-dance-long.bvh", 56, 6, "leg"), ("ganimator/Elephant/idle1.bvh", 40, 4, "")],
)
def test_non_humanoids(shared_data, rel, n_joints, n_feet, foot_word):
    sk = _real(shared_data, rel)
    assert sk.n_joints == n_joints
    assert sk.reduce()[0].n_joints == n_joints  # default reduction leaves animals alone
    feet = sk.detect_feet()
    assert len(feet) == n_feet
    assert all(foot_word in sk.names[f].lower() for f in feet)
    assert all(not sk.children(f) for f in feet)
    h = build_hierarchy(sk, feet)
    _check_hierarchy(h, n_joints, n_feet)


# ----------------------------------------------------------------------------------------------------------------
# the released MoDi's topology as options: self + parent + children neighbours, root-preserving pooling
@settings(max_examples=150, deadline=None)
@given(trees())
def test_released_pooling_keeps_root_and_specials_and_stops_at_two_edges(case):
    parents, feet, dist = case
    n = len(parents)
    h = build_hierarchy(_tree(parents), feet=feet, neighbor_distance=dist, pooling="released")
    assert h.edge_counts[-1] <= 2 and (n <= 2 or h.edge_counts[-2] > 2)
    assert all(c > d for c, d in zip(h.edge_counts, h.edge_counts[1:]))  # every step pools something
    for i, lv in enumerate(h.levels):
        assert lv.groups[0] == [0]  # the root edge is never merged with another edge
        assert lv.root_motion == lv.n_edge_entities and len(lv.contacts) == len(feet)  # specials on every level
        assert lv.neighbors == neighbors_from_adjacency(lv.adjacency, dist)
        if i:
            fine = h.levels[i - 1]
            assert sorted(e for g in h.pooling[i - 1] for e in g) == list(range(fine.n_entities))
            assert len(h.pooling[i - 1]) == lv.n_entities
            specials = [[fine.root_motion]] + [[c] for c in fine.contacts]
            assert h.pooling[i - 1][lv.n_edge_entities:] == specials


def test_tree_neighbours_are_self_parent_children():
    parents = [-1, 0, 1, 1, 0]  # 0 -> 1 -> {2, 3}; 0 -> 4
    h = build_hierarchy(_tree(parents), feet=[], siblings=False)
    edges = h.levels[0].neighbors[:5]
    assert edges == [[0, 1, 4, 5], [0, 1, 2, 3, 5], [1, 2], [1, 3], [0, 4, 5]]  # 5 = root motion (root's wiring)
    with_siblings = build_hierarchy(_tree(parents), feet=[]).levels[0].neighbors
    assert with_siblings[2] == [1, 2, 3] and with_siblings[1] == [0, 1, 2, 3, 4, 5]
    with pytest.raises(ValueError, match="pooling"):
        build_hierarchy(_tree(parents), feet=[], pooling="mean")


def test_bandai_released_pooling(shared_data):
    sk = _real(shared_data, BANDAI)
    h = build_hierarchy(sk, sk.detect_feet(), pooling="released")
    assert h.levels[1].names[0] == "joint_Root" and h.edge_counts[-1] <= 2
    assert h.entity_counts[-1] == h.edge_counts[-1] + 3  # root motion and both contacts survive
