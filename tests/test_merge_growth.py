"""The search without ids on maps that drift apart (mapjoin.growing, docs/method.md#merging step 5): the
correspondence grown over a bent overlap with local transforms, no false match where a kink spoils a local fit,
parts beyond a kink joined, simulated robots matched over the whole overlap, unrelated maps refused."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

import mapjoin
from mapjoin import JoinError, growing
from mapjoin.joining import join
from mapjoin.onestep import as_complex
from mapjoin.registration import chi_square_2, consensus
from mapjoin.simulation import simulate_robots

FRESH = 1_000_000
GATE = chi_square_2(0.999)


def bent_strip(seed: int, bend: float, count: int = 240, noise: float = 0.02):
    """Features scattered along a 120 m x 8 m strip (A), and the same features bent (B): the strip's
    direction turns by ``bend`` rad from one end to the other, as a map whose heading drifts would, then
    moved into a random frame. Errors ``noise`` m; variances ``noise^2``. Returns za, zb, the variances."""
    rng = np.random.default_rng(seed)
    along, across = np.sort(rng.uniform(0, 120, count)), rng.uniform(-4, 4, count)
    za = along + 1j * across
    heading = bend * along / 120  # the direction of the bent strip at each abscissa
    centre = np.concatenate([[0], np.cumsum(np.exp(1j * heading[:-1]) * np.diff(along))])
    bent = centre + 1j * np.exp(1j * heading) * across
    frame = np.exp(1j * rng.uniform(-math.pi, math.pi)) * bent + complex(*rng.uniform(-50, 50, 2))
    zb = frame + noise * (rng.normal(size=count) + 1j * rng.normal(size=count))
    za = za + noise * (rng.normal(size=count) + 1j * rng.normal(size=count))
    return za, zb, np.full(count, noise**2)


def grown(za, va, zb, vb, core: int):
    """``growing.grow`` from the ``core`` features at the strip's start (index i of A is index i of B)."""
    seed = np.arange(core)
    return growing.grow(cKDTree(np.column_stack([za.real, za.imag])), za, va, zb, vb, seed, seed, GATE)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), bend=st.floats(0.1, 0.6))
def test_a_bent_overlap_is_grown_from_one_end_without_false_matches(seed, bend):
    """A strip bent by 0.1-0.6 rad (metres off any rigid fit, against variances of 2 cm): from ten matches at
    one end the growth matches nearly all features, each to itself; the core's rigid transform alone would
    leave the far end metres off its gate."""
    za, zb, variances = bent_strip(seed, bend)
    a, b = grown(za, variances, zb, variances, 10)
    np.testing.assert_array_equal(a, b)
    assert len(b) >= 0.9 * len(zb)
    # the premise: one rigid transform through the first ten puts the far end outside its gate
    turn = np.angle(np.sum((za[:10] - za[:10].mean()) * np.conj(zb[:10] - zb[:10].mean())))
    placed = za[:10].mean() + np.exp(1j * turn) * (zb[-1] - zb[:10].mean())
    assert abs(placed - za[-1]) ** 2 > GATE * 2 * variances[-1]


def test_a_gate_that_chance_would_fill_matches_nothing(monkeypatch):
    """Six matches whose B positions are half a metre off a rigid fit (a kink) place a seventh B feature, 7 m
    beyond them, with a gate of about 2 m; one A feature lies in it, half a metre from where the fit puts the
    B feature, and no other (its true partner is not in A; the rest of A is a grid of 1 m spacing, 30 m
    away). A's density fills such a gate by chance: nothing is taken. Without that rule the lone A feature is
    matched, and so is every core match (whose gates are as wide)."""
    rng = np.random.default_rng(1)
    core_a = np.array([0, 1, 2, 0.5 + 1j, 1.5 + 1j, 1 + 2j]) * 2.0
    core_b = core_a + rng.normal(0, 0.5, 6) + 1j * rng.normal(0, 0.5, 6)
    grid = np.array([complex(x, y) for x in range(30, 50) for y in range(20)])
    za = np.concatenate([core_a, [2.5 + 8.8j], grid])
    zb = np.concatenate([core_b, [2 + 9j]])
    va, vb = np.full(len(za), 1e-4), np.full(len(zb), 1e-4)
    seed = np.arange(6)
    tree = cKDTree(np.column_stack([za.real, za.imag]))
    a, b = growing.grow(tree, za, va, zb, vb, seed, seed, GATE)
    assert len(b) == 0
    monkeypatch.setattr(growing, "MATCH_CHANCE", math.inf)
    a, b = growing.grow(tree, za, va, zb, vb, seed, seed, GATE)
    assert 6 in a[b == 6]


def robots(count: int, maps: int, seed: int):
    """``simulate_robots`` (default noise) joined, each robot's ids made its own (the world's ids are the truth
    behind ``% FRESH``)."""
    joined = [join(run.maps).global_map for run in simulate_robots(count, maps, seed=seed).robots]
    return [dataclasses.replace(m, feature_ids=m.feature_ids + r * FRESH, name=f"robot {r + 1}")
            for r, m in enumerate(joined)]


@pytest.mark.parametrize("maps,seed", [(20, 13), (30, 1), (100, 5)])
def test_drifted_robots_are_matched_over_the_whole_overlap(maps, seed):
    """Two robots' joined maps drift metres apart (far beyond their centimetre variances). One rigid transform
    matched a part (49 of 268 common features for (30, 1)) and refused (30, 1) (another part of the drifted
    maps counted as a rival); (20, 13) needs a part beyond a kink joined as close, (100, 5) grows past kinks
    from other parts. Now: sure, at least 80 % of the common features, none false (over seeds 0-15, about 1
    match in 400 is false: docs/method.md#merging)."""
    first, second = robots(2, maps, seed)
    found = consensus(as_complex(first.features), first.feature_variances, as_complex(second.features),
                      second.feature_variances)
    shared = len(np.intersect1d(first.feature_ids, second.feature_ids - FRESH))
    assert found.sure
    np.testing.assert_array_equal(first.feature_ids[found.a], second.feature_ids[found.b] - FRESH)
    assert len(found.a) >= 0.8 * shared
    assert mapjoin.merge([first, second], associate=True).report[0].common == len(found.a)


def test_a_growth_that_cycles_ends_with_the_pairs_its_cycle_always_holds(monkeypatch):
    """At a kink features are taken and dropped in turn: on two drifted robots (30 maps, seed 1) the growths
    return to an earlier state after a few rounds (2-state cycles). They end there, each with the pairs that
    every state of its cycle holds, in a few dozen rounds in all; without that they would run ``ROUNDS``
    rounds each and return whichever state came last."""
    first, second = robots(2, 30, 1)
    rounds = []
    placement = growing._local_placement

    def counted(*args):
        rounds.append(1)
        return placement(*args)

    monkeypatch.setattr(growing, "_local_placement", counted)
    found = consensus(as_complex(first.features), first.feature_variances, as_complex(second.features),
                      second.feature_variances)
    assert found.sure and len(rounds) < 100
    np.testing.assert_array_equal(first.feature_ids[found.a], second.feature_ids[found.b] - FRESH)


@pytest.mark.parametrize("maps,seed", [(20, 0), (20, 5), (20, 6), (20, 7), (20, 12), (50, 3)])
def test_unrelated_simulations_are_refused(maps, seed):
    """Robot 1 of one simulation and robot 2 of another (the same figure-eight, other features): no overlap,
    the merge is refused. A chance transform matches 5-11 features there and grows little; the other chance
    transforms, whose matches the correspondence does not hold, are its rivals (counting only the matches
    that contradict it accepts (20, 6) and (20, 12))."""
    first = robots(2, maps, seed)[0]
    other = robots(2, maps, seed + 1)[1]
    with pytest.raises(JoinError, match="^robot 2: no sure overlap"):
        mapjoin.merge([first, other], associate=True)
