"""The hierarchical start of the exact solve (mapjoin.refine.hierarchy, docs/method.md#hierarchical-start):
the tree join with its top levels' pieces solved exactly before the level above joins them."""

from __future__ import annotations

import numpy as np
import pytest
from cli_runner import run
from hypothesis import given, settings
from hypothesis import strategies as st
from test_refine import refined_from_the_truth

from mapjoin import io as mapio
from mapjoin.joining import join_tree
from mapjoin.refine import STARTS, join_and_refine, refine
from mapjoin.refine.hierarchy import Settle
from mapjoin.refine.problem import ExactProblem
from mapjoin.refine.solver import STALL_ITERATIONS, minimise
from mapjoin.se2 import wrap
from mapjoin.simulation import simulate


def piece_optimum(maps) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The exact optimum of the chain ``maps`` alone, in the frame of its first start pose, found by minimise
    from the plain tree join of those maps: (poses, feature ids, features)."""
    problem = ExactProblem(maps)
    found = minimise(problem, problem.pack(join_tree(maps).global_map))
    assert found.converged, found.reason
    poses, features = problem.unpack(found.x)
    return poses, problem.feature_ids, features


@settings(max_examples=4, deadline=None)
@given(count=st.integers(20, 64), seed=st.integers(0, 10**6))
def test_settled_pieces_are_each_pieces_own_optimum(count, seed):
    """Simulated chains, the levels of at most 4 pieces settled to convergence: every piece the hook hands on
    (e.g. at 100 maps 4 pieces of 32, 32, 32, 4 maps, then 64 and 36) is the optimum of that piece's maps
    solved on their own from their own tree join, and the levels of more pieces (and the root) pass unchanged."""
    maps = simulate(count, seed=seed).maps
    ids = np.unique(np.concatenate([m.feature_ids for m in maps]))
    settle = Settle(maps, depth=2, iterations=100, tolerance=1e-12)
    seen = []

    def recording(pieces, level):
        settled = settle(pieces, level)
        assert (settled is pieces) == (pieces.count > 4 or pieces.count == 1)
        seen.append(settled)
        return settled

    join_tree(maps, settle=recording)
    assert [count for _, count, *_ in settle.levels] == [c for c in (4, 3, 2) if any(p.count == c for p in seen)]
    assert all(after <= before for _, _, before, after, _ in settle.levels)
    checked = 0
    for pieces in seen:
        if pieces.count > 4 or pieces.count == 1:
            continue
        for p, (first, last) in enumerate(zip(pieces.first.tolist(), pieces.last.tolist())):
            poses, feature_ids, features = piece_optimum(maps[first:last + 1])
            rows = pieces.feature_piece == p
            np.testing.assert_array_equal(ids[pieces.feature_ids[rows]], feature_ids)
            mine = np.column_stack([pieces.features[rows].real, pieces.features[rows].imag])
            np.testing.assert_allclose(mine, features, rtol=0, atol=1e-6)
            at = slice(first, last + 1)
            np.testing.assert_allclose(pieces.pose_xy[at].real, poses[:, 0], rtol=0, atol=1e-6)
            np.testing.assert_allclose(pieces.pose_xy[at].imag, poses[:, 1], rtol=0, atol=1e-6)
            np.testing.assert_allclose(wrap(pieces.pose_phi[at] - poses[:, 2]), 0.0, rtol=0, atol=1e-8)
            checked += 1
    assert checked == sum(count for _, count, *_ in settle.levels) >= 2


def test_the_hierarchical_start_converges_where_the_tree_start_creeps():
    """1000 maps (two laps) with three times the default heading noise (0.03 rad a step), seed 2: from the
    tree's start the solve creeps (100 iterations, chi^2 29061.7, not converged; 40 here), from the
    hierarchical start it reaches the optimum that a start at the ground truth reaches (28634.08, in 9);
    with no start given, the same after the tree's solve fails."""
    run_ = simulate(1000, seed=2, odometry_noise=(0.05, 0.02, 0.03))
    reference = refined_from_the_truth(run_)
    tree = join_and_refine(run_.maps, start="tree", covariances=False, max_iterations=40)
    hierarchical = join_and_refine(run_.maps, start="hierarchical", covariances=False)
    assert reference.converged and not tree.converged and tree.cost > reference.cost * (1 + 1e-3)
    assert hierarchical.converged and hierarchical.start == "hierarchical", hierarchical.reason
    assert hierarchical.cost == pytest.approx(reference.cost, rel=1e-9)
    np.testing.assert_allclose(hierarchical.global_map.features, reference.global_map.features, rtol=0, atol=1e-6)
    assert hierarchical.fast_join.global_map.provenance.strategy == "tree"
    # no start given: the default (tree) start's solve did not converge, so the hierarchical start is tried
    default = join_and_refine(run_.maps, covariances=False, max_iterations=40)
    assert default.converged and (default.start, default.abandoned) == ("hierarchical", "tree")
    assert default.cost == hierarchical.cost and default.initial_seconds > hierarchical.initial_seconds
    assert (tree.start, tree.abandoned) == ("tree", None)   # a start given is not replaced


def test_a_stalled_solve_from_the_tree_start_is_abandoned_early():
    """1000 maps with three times the default heading noise, seed 0: from the tree's start the solve creeps (gains
    of 0.9, 0.7, 0.6 ... from iteration 55 on). Watching for a stall it gives up at iteration 62 (the last ten
    steps lowered chi^2 by less than 9), and the 38 further iterations it would have taken until the limit lower
    chi^2 by less than 9 too: nothing the data resolve is lost. Not watching (a start given), it runs to the
    limit as before; with no start given, the default's fallback abandons the tree at the stall, not at 100."""
    run_ = simulate(1000, seed=0, odometry_noise=(0.05, 0.02, 0.03))
    fast = join_tree(run_.maps).global_map
    stalled = refine(run_.maps, fast, covariances=False, stall=True)
    limit = refine(run_.maps, fast, covariances=False)
    assert not stalled.converged and stalled.reason.startswith("stalled") and stalled.iterations < 100
    assert stalled.costs[-STALL_ITERATIONS - 1] - stalled.cost < 9.0 <= stalled.costs[-STALL_ITERATIONS - 2] - \
        stalled.cost    # the first iteration at which the rule holds
    assert not limit.converged and limit.iterations == 100 and limit.reason == "max iterations reached"
    assert limit.costs[:len(stalled.costs)] == stalled.costs       # the same steps up to the stall
    assert 0 <= stalled.cost - limit.cost < 9.0


@pytest.mark.parametrize("name, optimum", [("VicPark_200_local_maps", 3643.434939),
                                           ("DLR_200_local_maps", 11163.643406),
                                           ("8240_data_50_local_maps", 458.154366)])
def test_the_real_datasets_reach_their_optimum_from_the_hierarchical_start(data_dir, name, optimum):
    """The optimum the sequential and the tree's starts reach (benchmarks/README.md)."""
    maps = mapio.read_maps([str(data_dir / name)])
    hierarchical = join_and_refine(maps, start="hierarchical", covariances=False)
    assert hierarchical.converged and hierarchical.cost == pytest.approx(optimum, rel=1e-9)


def test_the_cli_starts_from_the_hierarchical_join_only_when_refining(simulated_folder, tmp_path):
    """The CLI's choices are the library's (it does not import them); the summary names the start; a join
    without the exact solve, or with --jobs, refuses it."""
    from mapjoin.cli import common

    assert common.STARTS == STARTS
    result = run("refine", simulated_folder, "--start", "hierarchical", "--no-covariances", "-o",
                 str(tmp_path / "a.csv"))
    assert result.exit_code == 0 and "), from the hierarchical join, " in result.stderr, result.stderr
    result = run("refine", simulated_folder, "--no-covariances", "--json", "-o", str(tmp_path / "d.csv"))
    assert '"start": "tree", "abandoned_start": null' in result.stdout, result.stdout   # converged from the tree
    result = run("join", simulated_folder, "--strategy", "hierarchical", "--refine", "--json", "-o",
                 str(tmp_path / "b.csv"))
    assert result.exit_code == 0 and '"strategy": "hierarchical", "abandoned_start": null' in result.stdout, \
        result.stdout
    for args in (["join", "--strategy", "hierarchical"], ["refine", "--start", "hierarchical", "--jobs", "2"]):
        result = run(*args[:1], simulated_folder, *args[1:], "-o", str(tmp_path / "c.csv"))
        assert result.exit_code == 2 and "Traceback" not in result.output, result.output
        assert not (tmp_path / "c.csv").exists()
    assert "add --refine" in run("join", simulated_folder, "--strategy", "hierarchical", "-o", "-").output


def test_settle_checks_its_arguments():
    maps = simulate(4, seed=0).maps
    with pytest.raises(ValueError, match="depth"):
        Settle(maps, depth=-1)
    with pytest.raises(ValueError, match="iterations"):
        Settle(maps, iterations=-1)
    with pytest.raises(ValueError, match="one process"):
        join_tree(maps, jobs=2, settle=Settle(maps))
    with pytest.raises(ValueError, match="unknown start"):
        join_and_refine(maps, start="upside-down")
