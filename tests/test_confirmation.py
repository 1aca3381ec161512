"""Stage 2 of the consistency test: failing joins confirmed on the exact least-squares problem."""

from __future__ import annotations

import csv
import dataclasses

import numpy as np
import pytest
import scipy.optimize
import scipy.stats
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin import io as mapio
from mapjoin.confirmation import Estimate, Pieces, confirm, increment, piece_bounds
from mapjoin.faults import corrupted
from mapjoin.joining import join
from mapjoin.maps import LocalMap
from mapjoin.simulation import simulate

SMALL_SETS = ("535_data_5_local_maps", "8240_data_50_local_maps", "DLR_200_local_maps", "VicPark_200_local_maps")


def _dense_optimum(maps: list[LocalMap]) -> tuple[float, int]:
    """chi^2 at the optimum of the run ``maps`` and its residuals minus unknowns, by dense least squares
    (scipy) on the maps' full covariances; the run's first start pose is the origin. Started from the
    maps dead-reckoned, each feature where it was first seen."""
    poses, features, pose = {}, {}, np.zeros(3)
    for m in maps:
        c, s = np.cos(pose[2]), np.sin(pose[2])
        rotation = np.array([[c, -s], [s, c]])
        for i, f in zip(m.feature_ids.tolist(), m.features):
            features.setdefault(i, pose[:2] + rotation @ f)
        pose = np.array([*(pose[:2] + rotation @ m.end_pose[:2]), pose[2] + m.end_pose[2]])
        poses[m.end_id] = pose
    pose_ids, feature_ids = list(poses), sorted(features)
    column = {i: 3 * len(pose_ids) + 2 * k for k, i in enumerate(feature_ids)}
    whitening = [np.linalg.inv(np.linalg.cholesky(m.covariance)) for m in maps]

    def residuals(x: np.ndarray) -> np.ndarray:
        out = []
        for m, w in zip(maps, whitening):
            base = x[3 * pose_ids.index(m.start_id):][:3] if m.start_id in poses else np.zeros(3)
            end = x[3 * pose_ids.index(m.end_id):][:3]
            c, s = np.cos(base[2]), np.sin(base[2])
            back = np.array([[c, s], [-s, c]])
            points = [end[:2]] + [x[column[i]:column[i] + 2] for i in m.feature_ids.tolist()]
            predicted = np.concatenate([back @ (p - base[:2]) for p in points])
            measured = np.concatenate([m.end_pose[:2], m.features.ravel()])
            error = np.concatenate([measured[:2] - predicted[:2], [np.remainder(m.end_pose[2] - end[2] + base[2]
                                                                               + np.pi, 2 * np.pi) - np.pi],
                                    measured[2:] - predicted[2:]])
            out.append(w @ error)
        return np.concatenate(out)

    start = np.concatenate([np.concatenate([poses[i] for i in pose_ids]),
                            np.concatenate([features[i] for i in feature_ids])])
    fit = scipy.optimize.least_squares(residuals, start, xtol=1e-15, ftol=1e-15, gtol=1e-15, method="lm")
    unknowns = 3 * len(pose_ids) + 2 * len(feature_ids)
    return float(2 * fit.cost), sum(3 + 2 * m.size for m in maps) - unknowns


@pytest.mark.parametrize("seed, bounds", [(0, (0, 3, 4)), (1, (0, 4, 5)), (2, (0, 2, 5)), (3, (1, 3, 6))])
def test_the_exact_increment_is_that_of_the_dense_least_squares_problems(seed, bounds):
    maps = list(simulate(6, seed=seed, steps_per_map=6, laps=0.5).maps)
    first, middle, stop = bounds
    exact = increment(Pieces(maps, join(maps).global_map), first, middle, stop)
    union, left, right = (_dense_optimum(maps[a:b]) for a, b in ((first, stop), (first, middle), (middle, stop)))
    assert exact.chi2 == pytest.approx(union[0] - left[0] - right[0], rel=1e-6, abs=1e-8)
    assert exact.dof == union[1] - left[1] - right[1]
    assert exact.union.cost == pytest.approx(union[0], rel=1e-7)


def _three_solves(maps: list[LocalMap], k: int) -> tuple[float, int]:
    """The exact statistic of sequential join k by its definition: chi2*(maps 1..k+1) - chi2*(maps 1..k) - 0 (the
    right piece, one map, fits itself), and its dof, from independent exact solves (``refine``, each from its own
    tree join)."""
    from mapjoin.refine import refine

    union, left = refine(maps[:k + 1], covariances=False), refine(maps[:k], covariances=False)
    assert union.converged and left.converged
    return union.cost - left.cost, (union.residuals - union.unknowns) - (left.residuals - left.unknowns)


def _counting_extensions(monkeypatch) -> list[bool]:
    """Whether each union of a one-map right piece came from the left piece's factor (refine.extension)."""
    from mapjoin.refine import extension

    served, extend = [], extension.extend

    def counted(*args, **kwargs):
        found = extend(*args, **kwargs)
        served.append(found is not None)
        return found

    monkeypatch.setattr(extension, "extend", counted)
    return served


@pytest.mark.parametrize("seed", [0, 1])
def test_a_sequential_joins_increment_is_that_of_three_independent_exact_solves(seed, monkeypatch):
    """At the joins after loop closures (those the fast statistic flags) of simulations, the increment, its union
    extended from the left piece's optimum where the chord steps converge, is the definition's: three
    independent exact solves (1e-6 relative; the same dof). Most unions are extended; the others (loop
    closures that move the map by metres) are solved whole."""
    served = _counting_extensions(monkeypatch)
    maps = list(simulate(120, seed=seed, laps=2.0).maps)
    fast = join(maps)
    pieces = Pieces(maps, fast.global_map)
    for record in [r for r in fast.report if r.flag][:6]:
        exact = increment(pieces, 0, record.join, record.join + 1)
        chi2, dof = _three_solves(maps, record.join)
        assert exact.converged
        assert exact.chi2 == pytest.approx(chi2, rel=1e-6)
        assert exact.dof == dof
    assert sum(served) >= 3


def test_dlrs_confirmed_join_is_extended_to_the_three_solves_increment(data_dir, monkeypatch):
    """DLR 200's join 181, the one the streamed join confirms: its union extended from the left piece's optimum
    (no solve of its own), its increment the three independent solves' (1e-6 relative)."""
    served = _counting_extensions(monkeypatch)
    maps = mapio.read_maps(str(data_dir / "DLR_200_local_maps"))
    fast = join(maps)
    record = fast.report[180]
    assert record.join == 181 and piece_bounds(maps, record, "sequential") == (0, 181, 182)
    exact = increment(Pieces(maps, fast.global_map), 0, 181, 182)
    chi2, dof = _three_solves(maps, 181)
    assert served == [True]
    assert exact.chi2 == pytest.approx(chi2, rel=1e-6) and exact.dof == dof


@settings(max_examples=40, deadline=None)
@given(st.lists(st.sets(st.integers(0, 12), min_size=1, max_size=6), min_size=2, max_size=6), st.data())
def test_the_exact_dof_is_twice_the_features_the_pieces_share(id_sets, data):
    """Residuals minus unknowns of the exact problems, counted by the code, against the count by hand:
    2 n for the n features the two pieces share (the one-step join's dof)."""
    rng = np.random.default_rng(len(id_sets))
    maps = []
    for k, ids in enumerate(id_sets):
        ids = np.array(sorted(ids), dtype=np.int64)
        size = 3 + 2 * len(ids)
        maps.append(LocalMap(f"m{k}", k, k + 1, np.array([1.0, 0.0, 0.1]), ids, rng.normal(size=(len(ids), 2)),
                             np.full(len(ids), 0.1), np.array([0.1, 0.01]), np.eye(size) * 0.1))
    middle = data.draw(st.integers(1, len(maps) - 1))
    first = data.draw(st.integers(0, middle - 1))
    stop = data.draw(st.integers(middle + 1, len(maps)))
    left = set().union(*id_sets[first:middle])
    right = set().union(*id_sets[middle:stop])
    result = join(maps[first:stop], strategy="sequential", gate=0.0)
    exact = increment(Pieces(maps[first:stop], result.global_map), 0, middle - first, stop - first)
    assert exact.dof == 2 * len(left & right)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.integers(0, 30), unique=True, max_size=12), st.lists(st.integers(0, 30), unique=True, max_size=12),
       st.integers(0, 2**32 - 1))
def test_two_estimates_put_together_keep_the_first_ones_shared_features(mine, theirs, seed):
    """Estimate.then, feature by feature (a dict and a loop): the second estimate moved by the first one's
    junction pose (rotation and translation written out), a feature both hold where the first has it."""
    rng = np.random.default_rng(seed)
    first = Estimate(np.array([1, 2]), rng.normal(size=(2, 3)), np.array(mine, dtype=np.int64),
                     rng.normal(size=(len(mine), 2)))
    second = Estimate(np.array([3]), rng.normal(size=(1, 3)), np.array(theirs, dtype=np.int64),
                      rng.normal(size=(len(theirs), 2)))
    x, y, phi = first.poses[1]
    rotation = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
    expected = {i: f for i, f in zip(theirs, second.features @ rotation.T + [x, y])}
    expected.update(zip(mine, first.features))
    both = first.then(second, 2)
    assert sorted(both.feature_ids.tolist()) == sorted(expected) and len(both.feature_ids) == len(expected)
    for i, f in zip(both.feature_ids.tolist(), both.features):
        np.testing.assert_allclose(f, expected[i], rtol=0, atol=1e-12)
    np.testing.assert_allclose(both.poses[2, :2], second.poses[0, :2] @ rotation.T + [x, y], rtol=0, atol=1e-12)


def test_the_exact_increment_is_chi_square_on_consistent_maps():
    """Every sequential join of a consistent simulation with loop closures, tested exactly: the p-values are
    uniform (the fast statistic fails here at the joins after each loop closure)."""
    maps = list(simulate(40, seed=7, laps=2.0).maps)
    result = join(maps)
    pieces = Pieces(maps, result.global_map)
    tests = [increment(pieces, *piece_bounds(maps, r, "sequential")) for r in result.report if r.dof > 0]
    p = scipy.stats.chi2.sf([t.chi2 for t in tests], [t.dof for t in tests])
    assert all(t.converged for t in tests)
    assert scipy.stats.kstest(p, "uniform").pvalue > 1e-3


@pytest.mark.parametrize("strategy", ["sequential", "tree"])
def test_the_pieces_are_the_joins_left_and_right_runs(data_dir, strategy):
    """The exact dof of each join's pieces equals the join's own dof: the pieces hold its common features."""
    maps = mapio.read_maps(str(data_dir / "8240_data_50_local_maps"))
    result = join(maps, strategy=strategy)
    pieces = Pieces(maps, result.global_map)
    for record in result.report[::7]:
        first, middle, stop = piece_bounds(maps, record, strategy)
        assert (maps[middle].start_id, maps[stop - 1].end_id) == (record.start_id, record.end_id)
        assert increment(pieces, first, middle, stop).dof == record.dof


def test_consistent_joins_after_loop_closures_are_no_longer_flagged():
    maps = list(simulate(200, seed=0, laps=2.0).maps)
    fast = join(maps)
    confirmed = join(maps, confirm=confirm)
    assert sum(r.flag for r in fast.report) >= 10  # the fast statistic's failures (measured: 17)
    assert sum(r.flag for r in confirmed.report) == 0
    assert [r.exact_p is not None for r in confirmed.report] == [r.flag for r in fast.report]
    assert np.array_equal(confirmed.global_map.features, fast.global_map.features)  # the map is not changed


def test_a_long_runs_loop_closures_are_confirmed_on_converged_solves():
    """Two laps of 1000 maps: from the fast sequential map the exact solve of maps 0..744 stopped after 100
    iterations at chi2 8962 (the optimum is 5712), and the joins it served stayed flagged as unconverged, with
    negative increments. Each piece solved from its own tree join converges; every increment is non-negative
    (an optimum cannot fall when measurements are added) and no consistent join stays flagged."""
    maps = list(simulate(1000, seed=0, laps=2.0, full_covariance=False).maps)
    fast = join(maps, on_inconsistent="warn")
    flagged = [r for r in fast.report if r.flag]
    assert len(flagged) >= 5  # the fast statistic's failures after the second lap's closures (measured: 8)
    pieces = Pieces(maps, fast.global_map)
    for record in flagged[:4]:
        exact = increment(pieces, *piece_bounds(maps, record, "sequential"))
        assert exact.union.converged and exact.left.converged
        assert exact.chi2 >= 0
    confirmed = [r for r in confirm(maps, fast, "sequential", 1e-10).report if r.join in {f.join for f in flagged}]
    assert sum(r.minima == 1 for r in confirmed) >= 5  # (join 745 has two minima: flagged always, not confirmed)
    assert all(r.exact_p is not None and not r.flag for r in confirmed if r.minima == 1)


def test_the_union_is_solved_from_its_pieces_not_from_the_distorted_fast_map():
    """Half a lap, seed 3: the last join closes the loop and the fast sequential map there leads the exact
    solve into a higher minimum (chi2 3443 instead of 3079: the increment 399 for 28 dof would flag a consistent
    join). From the pieces' optima the union reaches the optimum the exact join from the tree reaches."""
    from mapjoin.refine import refine

    maps = list(simulate(200, seed=3, laps=0.5).maps)
    result = join(maps)
    exact = increment(Pieces(maps, result.global_map), 0, 199, 200)
    assert exact.union.cost == pytest.approx(refine(maps, covariances=False).cost, rel=1e-9)
    assert exact.left.cost == pytest.approx(refine(maps[:199], covariances=False).cost, rel=1e-9)
    record = confirm(maps, result, "sequential", 1e-10).report[198]
    assert record.exact_p is not None and not record.flag


@pytest.mark.parametrize("name", SMALL_SETS)
@pytest.mark.parametrize("how", ["heading", "feature", "swap"])
def test_the_join_holding_a_corrupted_value_is_confirmed(data_dir, name, how):
    maps = mapio.read_maps(str(data_dir / name))
    chain, number = corrupted(maps, len(maps) // 2, how)
    record = join(chain, confirm=confirm).report[number - 1]
    assert record.flag and record.exact_p is not None and record.exact_p < 1e-10


@pytest.mark.parametrize("name", SMALL_SETS)
@pytest.mark.parametrize("how", ["heading", "feature", "swap"])
def test_a_tree_join_whose_pieces_hold_a_corrupted_value_stays_flagged(data_dir, name, how):
    maps = mapio.read_maps(str(data_dir / name))
    k = len(maps) // 2
    chain, _ = corrupted(maps, k, how)
    report = join(chain, strategy="tree", confirm=confirm).report
    holding = [r for r in report if r.flag and k in range(*piece_bounds(chain, r, "tree")[::2])]
    assert holding and (holding[0].minima == 2 or holding[0].exact_p < 1e-10)


@pytest.mark.parametrize("name", SMALL_SETS)
@pytest.mark.parametrize("strategy", ["sequential", "tree"])
def test_clean_datasets_flag_no_join_at_the_default_gate(data_dir, name, strategy):
    """At the default gate no clean join is flagged (the level's rate, 1e-10, implies none). DLR's level-1 tree
    joins 2 and 4 (two raw maps, exact chi2 93 for 8 and 74 for 12 dof: DLR's maps are optimistic by a factor
    of about 4) were flagged while the factor was online; the tree's factor now comes from the whole level."""
    maps = mapio.read_maps(str(data_dir / name))
    report = join(maps, strategy=strategy, confirm=confirm).report
    assert [(r.join, r.level) for r in report if r.flag] == []
    if (name, strategy) == ("DLR_200_local_maps", "tree"):
        assert min(r.variance_factor for r in report if r.level == 1) > 2.0  # the level's own factor, known


def test_past_the_budget_a_join_keeps_the_fast_flag(data_dir):
    maps = mapio.read_maps(str(data_dir / "DLR_200_local_maps"))
    fast = join(maps)
    none = confirm(maps, fast, "sequential", 1e-10, budget=0.0)
    assert none.report == fast.report
    some = confirm(maps, fast, "sequential", 1e-10, budget=0.5)  # join 71's two prefixes: 143 maps, over 100
    confirmed = [r.join for r in some.report if r.exact_p is not None]
    assert confirmed == [r.join for r in fast.report if r.flag][:1]


def test_skip_acts_on_the_confirmed_flags(data_dir):
    """With the skip policy the re-joined chains are confirmed too: the corrupted heading's map is joined by its
    features alone, and the clean loop closures the fast statistic flags are left as they are."""
    maps = mapio.read_maps(str(data_dir / "DLR_200_local_maps"))
    chain, number = corrupted(maps, 100, "heading")
    report = join(chain, on_inconsistent="skip", confirm=confirm).report
    assert [(r.join, r.action) for r in report if r.action != "joined"] == [(number, "features only")]
    assert not any(r.flag for r in report)


def test_the_streamed_join_reads_its_files_again_to_confirm(data_dir, tmp_path):
    """``mapjoin join FOLDER`` (streamed) confirms its flagged joins as the in-memory join does, bit for bit."""
    from cli_runner import run

    folder = data_dir / "DLR_200_local_maps"
    result = run("join", str(folder), "-o", str(tmp_path / "g.csv"), "--report", str(tmp_path / "r.csv"))
    assert result.exit_code == 0, result.output
    with open(tmp_path / "r.csv", newline="") as table:
        rows = list(csv.DictReader(table))
    expected = join(mapio.read_maps(str(folder)), confirm=confirm).report
    assert [row["flag"] for row in rows] == [str(r.flag) for r in expected]
    assert [row["exact_p"] for row in rows] == ["" if r.exact_p is None else repr(r.exact_p) for r in expected]
    assert sum(r.exact_p is not None for r in expected) == 1 and not any(r.flag for r in expected)  # join 181


@pytest.mark.parametrize("keep", [True, False])
def test_the_streamed_join_confirms_on_its_kept_maps_or_reads_them_again(data_dir, tmp_path, monkeypatch, keep):
    """The streamed join keeps its maps for the confirmation while they are few (DLR 200's: not read again, the
    reader made to fail), and reads them again past :data:`KEEP_VALUES`: the same report either way, the
    in-memory join's."""
    from cli_runner import run

    from mapjoin.cli import common
    from mapjoin.cli import join as join_command

    reads = []
    read_local_maps = common.read_local_maps
    monkeypatch.setattr(common, "read_local_maps", lambda *args: reads.append(args) or read_local_maps(*args))
    if not keep:
        monkeypatch.setattr(join_command, "KEEP_VALUES", 1000)   # DLR's first few maps
    folder = data_dir / "DLR_200_local_maps"
    result = run("join", str(folder), "-o", str(tmp_path / "g.csv"), "--report", str(tmp_path / "r.csv"))
    assert result.exit_code == 0, result.output
    assert len(reads) == (0 if keep else 1)
    with open(tmp_path / "r.csv", newline="") as table:
        rows = list(csv.DictReader(table))
    expected = join(mapio.read_maps(str(folder)), confirm=confirm).report
    assert [(row["flag"], row["exact_p"]) for row in rows] == [
        (str(r.flag), "" if r.exact_p is None else repr(r.exact_p)) for r in expected]


@settings(max_examples=30, deadline=None)
@given(st.lists(st.integers(0, 6), max_size=12), st.integers(0, 400))
def test_a_stream_keeps_its_maps_while_they_hold_at_most_the_limits_numbers(sizes, limit):
    """KeptMaps passes every map on, in order, and holds them all while their states and covariances hold at
    most ``limit`` numbers (3 + 2m + (3 + 2m)^2 each, counted here by hand), none once past it."""
    from mapjoin.streaming import KeptMaps

    maps = [LocalMap(f"m{k}", k, k + 1, np.zeros(3), np.arange(m, dtype=np.int64), np.zeros((m, 2)), np.ones(m),
                     np.ones(2), np.eye(3 + 2 * m)) for k, m in enumerate(sizes)]
    kept = KeptMaps(iter(maps), limit)
    passed = []
    for local_map in kept:
        passed.append(local_map)
        held = sum(3 + 2 * m + (3 + 2 * m) ** 2 for m in sizes[:len(passed)])
        assert ([id(m) for m in kept.maps] == [id(m) for m in passed]) if held <= limit else kept.maps is None
    assert passed == maps


def test_a_streamed_join_from_stdin_keeps_the_fast_flags_and_says_so(tmp_path):
    from cli_runner import run

    text = run("simulate", "-o", "-", "--maps", "200", "--seed", "0").stdout
    result = run("join", "-", "-o", str(tmp_path / "g.csv"), input=text)
    assert result.exit_code == 0
    assert "11 flagged joins tested by the fast statistic only" in result.output
    assert "its maps came from stdin" in result.output


def test_a_streamed_join_whose_input_changed_is_not_confirmed():
    from mapjoin.confirmation import confirm_streamed

    maps = list(simulate(200, seed=0).maps)
    result = join(maps)
    renamed = [dataclasses.replace(m, name=f"other-{k}") for k, m in enumerate(maps)]
    unchanged, why = confirm_streamed(result, lambda: renamed, 1e-10)
    assert unchanged is result and "its input changed" in why
    confirmed, why = confirm_streamed(result, lambda: maps, 1e-10)
    assert why is None and not any(r.flag for r in confirmed.report)
    assert confirm_streamed(result, None, 1e-10)[0] is result


def test_a_join_whose_exact_problems_exceed_the_cap_keeps_the_fast_flag(data_dir, monkeypatch):
    """A loop closure late in a long chain would need solves of the whole chain: past
    ``MAX_SOLVED`` maps in all it is left to the fast test, and smaller joins are still confirmed."""
    import mapjoin.confirmation as confirmation

    maps = mapio.read_maps(str(data_dir / "DLR_200_local_maps"))
    fast = join(maps, gate=1e-4)  # DLR's clean joins flagged at 1e-4: 3, 51, 181, 182, 194
    flagged = [r.join for r in fast.report if r.flag]
    assert len(flagged) > 1
    whole = confirm(maps, fast, "sequential", 1e-4)
    assert all(r.exact_p is not None for r in whole.report if r.join in flagged)
    monkeypatch.setattr(confirmation, "MAX_SOLVED", flagged[0] + 1)   # the first join's union: maps 0..k
    capped = confirm(maps, fast, "sequential", 1e-4)
    confirmed = [r.join for r in capped.report if r.exact_p is not None]
    assert confirmed == flagged[:1]
    assert all(r.flag for r in capped.report if r.join in flagged[1:])


@pytest.mark.parametrize("name", ["535_data_5_local_maps", "8240_data_50_local_maps", "DLR_200_local_maps"])
def test_a_confirmation_solves_with_the_whole_chains_backend(data_dir, name):
    """chain_backend counts the whole chain's unknowns as its exact problem does, and chooses as that problem's
    own ``auto`` would."""
    from mapjoin.confirmation import chain_backend
    from mapjoin.refine.problem import ExactProblem

    maps = mapio.read_maps([str(data_dir / name)])
    for count in (2, len(maps) // 3, len(maps)):
        assert chain_backend(maps[:count]) == ExactProblem(maps[:count]).backend


def test_the_confirmation_of_dlrs_first_loop_closures_is_the_same_with_either_backend(data_dir, monkeypatch):
    """The first 75 maps of DLR 200 (a dense chain: 701 unknowns) flag joins 3 and 51 at the fast stage at gate
    1e-4 (at 1e-10 its loop closures 71 and 72 did, until the fused estimates' bias, docs/method.md#drift); the
    exact statistics the dense backend gives them are the sparse backend's (1e-9 relative), and so are the
    verdicts (both cleared)."""
    from mapjoin import confirmation
    from mapjoin.confirmation import chain_backend

    maps = mapio.read_maps([str(data_dir / "DLR_200_local_maps")])[:75]
    fast = join(maps, gate=1e-4)
    assert chain_backend(maps) == "dense" and [r.join for r in fast.report if r.flag] == [3, 51]
    results = {}
    for backend in ("dense", "sparse"):
        monkeypatch.setattr(confirmation, "chain_backend", lambda _maps, chosen=backend: chosen)
        results[backend] = confirm(maps, fast, "sequential", 1e-4).report
    for dense, sparse in zip(results["dense"], results["sparse"]):
        assert dense.flag == sparse.flag
        if sparse.exact_chi2 is None:
            assert dense.exact_chi2 is None
        else:
            assert dense.exact_chi2 == pytest.approx(sparse.exact_chi2, rel=1e-9)
            assert dense.exact_p == pytest.approx(sparse.exact_p, rel=1e-6)
    assert [r.join for r in results["dense"] if r.exact_chi2 is not None] == [3, 51]
    assert not any(r.flag for r in results["dense"])
