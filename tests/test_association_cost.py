"""The association's shortcuts (mapjoin.association's rooms): each one leaves the association as it was. Step 6's exit when no
pair can vote against the pairs that vote, counted by brute force; the rounds' candidate search against every pair
within the radius; the median against numpy's; the rounds' reuse of a repeated joint test and of the last search, and
step 6's exit and the pairs' drift asked once per pair, against the association with each shortcut disabled, on
simulated runs and on real maps."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin import io as mapio
from mapjoin.association import associator, drifted, gate, join_associated, local_ids, rounds
from mapjoin.simulation import simulate

values = st.lists(st.sampled_from([0.0, 1e-3, 0.01, 0.1, 0.5, 1.0, 2.0, 10.0]), min_size=1, max_size=6)


def votes_by_brute_force(left_noise, left_drift, right_noise, right_drift, reach, moved: bool) -> bool:
    """Whether any (left, right) pair votes in step 6, pair by pair: its spread (the two drifts; ``moved``: the right
    feature's ``reach`` when the drifts are below the noise, else 0) at least its noise."""
    for ln, ld in zip(left_noise, left_drift):
        for rn, rd, move in zip(right_noise, right_drift, reach):
            noise, spread = ln + rn, ld + rd
            if moved:
                spread = move if spread < noise else 0.0
            if spread >= noise:
                return True
    return False


@settings(max_examples=300, deadline=None)
@given(st.data(), values, values, st.booleans())
def test_no_vote_is_said_only_where_no_pair_votes(data, left_noise, right_noise, moved):
    lefts, rights = len(left_noise), len(right_noise)
    left_drift = data.draw(st.lists(st.sampled_from([0.0, 0.01, 0.3, 1.0, 5.0]), min_size=lefts, max_size=lefts))
    right_drift = data.draw(st.lists(st.sampled_from([0.0, 0.01, 0.3, 1.0, 5.0]), min_size=rights, max_size=rights))
    reach = data.draw(st.lists(st.sampled_from([0.0, 0.02, 0.4, 3.0]), min_size=rights, max_size=rights))
    arrays = [np.array(a) for a in (left_noise, left_drift, right_noise, right_drift, reach)]
    may = drifted._may_vote(arrays[0], arrays[1], arrays[2], arrays[4] if moved else arrays[3], moved)
    if votes_by_brute_force(left_noise, left_drift, right_noise, right_drift, reach, moved):
        assert may


def test_no_vote_where_every_drift_and_move_is_below_the_noise():
    """The exit is taken: features without drift (or a move of their prediction) below their noise vote nowhere."""
    noise = np.array([0.1, 0.2, 0.3])
    assert not drifted._may_vote(noise, np.zeros(3), noise, np.zeros(3), False)
    assert not drifted._may_vote(noise, np.zeros(3), noise, np.full(3, 0.1), True)
    assert drifted._may_vote(noise, np.array([0.0, 0.0, 0.5]), noise, np.zeros(3), False)
    assert drifted._may_vote(noise, np.zeros(3), noise, np.array([0.0, 0.0, 0.5]), True)


points = st.lists(st.tuples(st.floats(-20, 20), st.floats(-20, 20)), min_size=1, max_size=30)


@settings(max_examples=200, deadline=None)
@given(points, points, st.floats(0.1, 8.0), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0))
def test_a_later_search_finds_every_pair_within_its_radius(left, right, radius, shrink, dx, dy):
    """A first search, then a second around moved predictions with other radii (inside the first's reach or not): the
    pairs the second gives include every (left, right) pair within the second radius, by brute force (the reused
    pairs or a fresh search)."""
    left = np.array([complex(*p) for p in left])
    predicted = np.array([complex(*p) for p in right])
    first_radius = np.full(len(predicted), radius)
    search = gate._Searched()
    search(left, np.zeros(len(left), np.intp), predicted, np.zeros(len(predicted), np.intp), first_radius, 1)
    moved = predicted + complex(dx, dy) * radius * abs(shrink)
    second_radius = first_radius * (1 - shrink / 2)
    i, j = search(left, np.zeros(len(left), np.intp), moved, np.zeros(len(moved), np.intp), second_radius, 1)
    found = set(zip(i.tolist(), j.tolist()))
    within = {(a, b) for a in range(len(left)) for b in range(len(moved))
              if abs(left[a] - moved[b]) <= second_radius[b]}
    assert within <= found
    order = list(zip(i.tolist(), j.tolist()))
    assert order == sorted(order)  # by left row, then right row, as a fresh search gives them


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1e6, 1e6), min_size=1, max_size=40) | st.lists(st.integers(0, 500), min_size=1, max_size=9))
def test_median_is_numpys(values):
    assert rounds._median(np.array(values)) == float(np.median(np.array(values)))


def associated(maps, strategy: str, monkeypatch, **disabled):
    """The global ids and per-join counts of ``join_associated``, with the shortcuts named in ``disabled`` replaced
    by functions that never take them (in the room that calls them, :data:`CALLER`)."""
    with monkeypatch.context() as patch:
        for name, replacement in disabled.items():
            patch.setattr(CALLER[name], name, replacement)
        found = join_associated(maps, strategy=strategy)
    return np.concatenate(found.global_ids), [(r.ambiguous, r.rejected) for r in found.report]


def never_repeated(*_):
    return False


def always_may_vote(*_):
    return True


def always_search():
    return gate._candidates


def always_asked(pair_drift):
    return pair_drift


#: where each shortcut is looked up when the association takes it
CALLER = {"_repeated": rounds, "_may_vote": drifted, "_Searched": rounds, "_asked_once": associator}
DISABLED = {"_repeated": never_repeated, "_may_vote": always_may_vote, "_Searched": always_search,
            "_asked_once": always_asked}


@settings(max_examples=6, deadline=None)
@given(st.integers(1, 10_000), st.sampled_from(["sequential", "tree"]), st.booleans())
def test_shortcuts_change_no_association_of_simulated_runs(seed, strategy, covariances):
    local, _ = local_ids(simulate(16, seed=seed).maps)
    if not covariances:
        local = tuple(dataclasses.replace(m, covariance=None) for m in local)
    with pytest.MonkeyPatch.context() as patch:
        fast = associated(local, strategy, patch)
        slow = associated(local, strategy, patch, **DISABLED)
    assert np.array_equal(fast[0], slow[0]) and fast[1] == slow[1]


@pytest.mark.parametrize("strategy", ["sequential", "tree"])
def test_shortcuts_change_no_association_of_a_loop_closing_dataset(data_dir, strategy, monkeypatch):
    """DLR's first 80 maps (loop closures, joint tests that fail): the shortcuts are taken and change nothing."""
    local, _ = local_ids(mapio.read_maps(str(data_dir / "DLR_200_local_maps"))[:80])
    taken = {"_repeated": 0, "_may_vote": 0}

    def counted(name):
        original = getattr(CALLER[name], name)

        def call(*arguments):
            answer = original(*arguments)
            taken[name] += answer if name == "_repeated" else not answer
            return answer
        return call

    fast = associated(local, strategy, monkeypatch, _repeated=counted("_repeated"), _may_vote=counted("_may_vote"))
    slow = associated(local, strategy, monkeypatch, **DISABLED)
    assert np.array_equal(fast[0], slow[0]) and fast[1] == slow[1]
    assert taken["_repeated"] > 0


@settings(max_examples=100, deadline=None)
@given(st.lists(st.lists(st.tuples(st.integers(0, 6), st.integers(0, 6), st.sampled_from([0.5, 1.0])), max_size=12),
                min_size=1, max_size=5))
def test_pair_drift_is_asked_once_per_pair_and_answered_as_asked_directly(asks):
    """associator._asked_once over a sequence of pair sets (each right row once, as a join's pairs are): every
    answer is the function's own for that pair, and of each set only the pairs not in the set before it (same left
    row, right row and noise) are asked."""
    asked = []

    def pair_drift(i, j, noise):  # elementwise, as the associator's are
        asked.append(set(zip(i.tolist(), j.tolist(), noise.tolist())))
        return i * 100.0 + j + noise / 8

    remembered = associator._asked_once(pair_drift)
    before: set = set()
    for pairs in asks:
        pairs = list({j: (i, j, n) for i, j, n in pairs}.values())  # one pair per right row
        i, j, noise = (np.array(column, dtype=dtype) for column, dtype in
                       zip(zip(*pairs) if pairs else ([], [], []), (np.intp, np.intp, float)))
        calls = len(asked)
        answer = remembered(i, j, noise)
        assert answer.tolist() == (i * 100.0 + j + noise / 8).tolist()
        new = set(zip(i.tolist(), j.tolist(), noise.tolist())) - before
        assert set().union(*asked[calls:]) == new if before else len(asked) - calls <= 1
        before = set(zip(i.tolist(), j.tolist(), noise.tolist()))
