"""Step 2's junction rule (mapjoin.association.junction): the link's variance relative to its own map against the
covariance propagated through finite differences of the pose composition, the rows it picks against a loop, and the
pairs it adds on simulated trees against the truth."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin.association import associator, join_associated, local_ids
from mapjoin.association.junction import free_pairs, own_link_variances, undrifted
from mapjoin.se2 import compose
from mapjoin.simulation import simulate


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_own_link_variance_is_the_propagated_covariance(seed):
    """The link (the junction's pose composed with the map's end pose) has covariance J diag(v, v, p, e, e, q) J^T,
    J by central differences of se2.compose: its position's half trace is var_t, its heading's variance p_phi."""
    rng = np.random.default_rng(seed)
    junction = np.array([*rng.normal(size=2) * 20, rng.uniform(-np.pi, np.pi)])
    end = np.array([*rng.normal(size=2) * 10, rng.uniform(-1, 1)])
    v, p, e, q = rng.uniform(1e-4, 1e-1), rng.uniform(1e-6, 1e-2), rng.uniform(1e-4, 1e-1), rng.uniform(1e-6, 1e-2)
    step = 1e-6
    jacobian = np.zeros((3, 6))
    for k in range(6):
        delta = np.zeros(6)
        delta[k] = step
        plus = compose(junction + delta[:3], end + delta[3:])
        minus = compose(junction - delta[:3], end - delta[3:])
        jacobian[:, k] = (plus - minus) / (2 * step)
    covariance = jacobian @ np.diag([v, v, p, e, e, q]) @ jacobian.T
    sums = np.array([[v, p, 0.0, 0.0, 0.0]])  # the terms past v, p are the drift's lever arms: not read here
    found = own_link_variances(np.array([[e, q]]), sums, np.array([complex(end[0], end[1])]))
    assert found[0, 0] == pytest.approx((covariance[0, 0] + covariance[1, 1]) / 2, rel=1e-6)
    assert found[0, 1] == pytest.approx(covariance[2, 2], rel=1e-6)


def test_undrifted_rows_and_free_pairs_against_loops():
    """undrifted: the left rows last seen by their join's link map, the right rows first seen by the next map;
    free_pairs: the pairs neither of whose rows is paired already (each checked row by row)."""
    rng = np.random.default_rng(4)
    left_last, left_link = rng.integers(0, 6, 40), rng.integers(0, 6, 40)
    right_first, right_link = rng.integers(0, 6, 30), rng.integers(0, 6, 30)
    lefts, rights = undrifted(left_last, left_link, right_first, right_link)
    assert lefts.tolist() == [i for i in range(40) if left_last[i] == left_link[i]]
    assert rights.tolist() == [j for j in range(30) if right_first[j] == right_link[j] + 1]
    left, right = rng.choice(40, 10, replace=False), rng.choice(30, 10, replace=False)
    near_left, near_right = rng.integers(0, 40, 25), rng.integers(0, 30, 25)
    expected = [near_left[k] not in left.tolist() and near_right[k] not in right.tolist() for k in range(25)]
    assert free_pairs(left, right, near_left, near_right).tolist() == expected


@pytest.mark.parametrize("count, seed", [(30, 11), (32, 3), (16, 5)])
def test_the_junction_pairs_of_a_simulated_tree_are_true(count, seed, monkeypatch, caplog):
    """Every pair the junction rule adds to a simulated tree join is a true one (its two compact ids' input rows share
    a true id); over these runs it adds some."""
    caplog.set_level(logging.ERROR, logger="mapjoin")
    local, truth = local_ids(simulate(count, seed=seed).maps)
    true_rows = np.concatenate(truth)
    added = []
    original = associator._Associator._junction_pairs

    def checked(self, found, left, left_ids, *rest):
        result = original(self, found, left, left_ids, *rest)
        right_ids = rest[5]
        for i, j in zip(result.left.tolist(), result.right.tolist()):
            if j not in found.right:
                same = np.intersect1d(true_rows[self.row_ids == left_ids[i]], true_rows[self.row_ids == right_ids[j]])
                added.append(len(same) > 0)
        return result

    monkeypatch.setattr(associator._Associator, "_junction_pairs", checked)
    join_associated(local, strategy="tree")
    assert all(added)
    if (count, seed) == (30, 11):
        assert len(added) >= 3
