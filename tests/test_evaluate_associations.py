"""``evaluate --associations``: an associating join's links counted against the true correspondence, its features
compared with the truth through it (``mapjoin.association.scored``, ``truth_of_found``), and the tables' boundary."""

from __future__ import annotations

import collections
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from cli_runner import run as cli_run
from test_outputs import run_with_stdout as run

from mapjoin import io as mapio
from mapjoin.association import scored, truth_of_found
from mapjoin.errors import InputError
from mapjoin.maps import Correspondence


def brute_force(found: list[int], true: list[int]) -> tuple[int, int, int]:
    """Links, missed and false by their definitions, feature by feature: a true feature seen n times has n - 1
    links; its sightings spread over k found features miss k - 1 of them; a found feature holding sightings of
    k true features makes k - 1 false links."""
    by_true: dict[int, set[int]] = collections.defaultdict(set)
    by_found: dict[int, set[int]] = collections.defaultdict(set)
    for f, t in zip(found, true):
        by_true[t].add(f)
        by_found[f].add(t)
    links = len(true) - len(set(true))
    return links, sum(len(s) - 1 for s in by_true.values()), sum(len(s) - 1 for s in by_found.values())


def table(found: list[int], maps: list[int] | None = None, name: str = "t") -> Correspondence:
    maps = maps or [1] * len(found)
    return Correspondence(np.array(maps), np.arange(len(found)), np.array(found), name=name)


def test_links_by_hand():
    """Map 1 sees true features 10 and 11, map 2 sees 10, 11 and 12: two true links."""
    true = Correspondence(np.array([1, 1, 2, 2, 2]), np.array([0, 1, 0, 1, 2]), np.array([10, 11, 10, 11, 12]))
    for found, expected in (([0, 1, 0, 1, 2], (2, 0, 0)),    # all right
                            ([0, 1, 0, 5, 2], (2, 1, 0)),    # 11 seen anew: one missed
                            ([0, 1, 0, 1, 0], (2, 0, 1))):   # 12 taken for 10: one false
        errors = scored(Correspondence(true.maps, true.local_ids, np.array(found)), true)
        assert tuple(errors) == expected
        assert errors.recall == 1 - expected[1] / 2


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 5), st.integers(0, 5)), min_size=1, max_size=40), st.randoms())
def test_scored_equals_the_count_by_definition_whatever_the_row_order(pairs, random):
    found, true = (list(column) for column in zip(*pairs))
    order = list(range(len(pairs)))
    random.shuffle(order)  # the tables need not list the input features in the same order
    maps = [1 + k % 3 for k in range(len(pairs))]
    local = [k // 3 for k in range(len(pairs))]
    shuffled = Correspondence(np.array(maps)[order], np.array(local)[order], np.array(found)[order])
    assert tuple(scored(shuffled, Correspondence(np.array(maps), np.array(local), np.array(true)))) == \
        brute_force(found, true)


def test_a_found_feature_stands_for_the_true_one_most_of_its_sightings_are():
    """Found 0 holds three sightings of 10 and one of 11; found 1 one each of 12 and 13 (a tie: the smaller)."""
    found, true = table([0, 0, 0, 0, 1, 1]), table([10, 10, 11, 10, 13, 12])
    ids, real = truth_of_found(found, true)
    assert ids.tolist() == [0, 1] and real.tolist() == [10, 12]


def test_the_input_feature_one_table_lacks_is_named_whatever_the_ids_size():
    """Local ids up to the 64-bit limit (a front end's hashes): the feature named is the one the other table lacks
    (keys packed into one integer, map x (largest id + 1) + id, overflow there)."""
    top = 2**63 - 1
    found = Correspondence(np.array([1, 1, 2]), np.array([0, top, top]), np.array([0, 1, 2]), name="found.csv")
    true = Correspondence(np.array([1, 1, 3]), np.array([0, top, top]), np.array([0, 1, 2]), name="true.csv")
    with pytest.raises(InputError, match=rf"^found.csv: has a row for map 2, local id {top}, which true.csv"):
        scored(found, true)


def test_tables_of_different_maps_are_refused_naming_the_found_table():
    with pytest.raises(InputError, match=r"^found.csv: lacks a row for map 1, local id 2"):
        scored(table([0, 1], name="found.csv"), table([0, 1, 2], name="true.csv"))
    with pytest.raises(InputError, match=r"^found.csv: has a row for map 2, local id 2, which true.csv does not have"):
        scored(table([0, 1, 2], [1, 1, 2], name="found.csv"), table([0, 1, 2], name="true.csv"))


def simulated_runs(folder, maps: str, seed: str):
    """One simulated run twice in ``folder``, with global ids (p/) and with ids local to each map (s/), each joined:
    the known-id join gp.csv and the associating join g.csv with its table a.csv."""
    for args in (["simulate", "-o", "p", "--maps", maps, "--seed", seed],
                 ["simulate", "-o", "s", "--maps", maps, "--seed", seed, "--local-ids"],
                 ["join", "p", "-o", "gp.csv"],
                 ["join", "s", "--associate", "--associations", "a.csv", "-o", "g.csv"]):
        code, _, stderr = run(folder, *args)
        assert code == 0, stderr
    return folder


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """:func:`simulated_runs` of 12 maps, seed 3."""
    return simulated_runs(tmp_path_factory.mktemp("evaluate"), "12", "3")


def evaluated(folder, *args) -> dict:
    code, stdout, stderr = run(folder, "evaluate", *args, "--json")
    assert code == 0, stderr
    return json.loads(stdout)


def test_the_true_table_through_a_known_id_join_changes_no_error(runs):
    """Evaluated through the true correspondence (found = true), the known-id join is compared feature by feature
    as by its ids: every number the same, and every link recovered."""
    plain = evaluated(runs, "gp.csv", "--truth", "p")
    through = evaluated(runs, "gp.csv", "--truth", "p", "--associations", "s/associations.csv",
                        "--true-associations", "s/associations.csv")
    assert through.pop("associations") == {"links": plain_links(runs), "missed": 0, "false": 0, "recall": 1.0}
    assert {**plain, "associations": None} == {**through, "associations": None}


def plain_links(folder) -> int:
    rows = np.loadtxt(folder / "s" / "associations.csv", delimiter=",", skiprows=1, dtype=np.int64)
    return len(rows) - len(np.unique(rows[:, 2]))


def test_an_associating_join_is_scored_and_compared_through_its_table(runs):
    """The links as counted by definition from the two CSV files; the features compared are the found ones whose
    sightings name a true feature, each against that feature's true position (computed here from the files)."""
    result = evaluated(runs, "g.csv", "--truth", "s")  # associations.csv beside the truth: not used without the option
    assert result["associations"] is None
    result = evaluated(runs, "g.csv", "--truth", "s", "--associations", "a.csv")
    found = np.loadtxt(runs / "a.csv", delimiter=",", skiprows=1, dtype=np.int64)
    true = np.loadtxt(runs / "s" / "associations.csv", delimiter=",", skiprows=1, dtype=np.int64)
    key = {(m, l): g for m, l, g in true.tolist()}
    links, missed, false = brute_force(found[:, 2].tolist(), [key[(m, l)] for m, l, _ in found.tolist()])
    assert (result["associations"]["links"], result["associations"]["missed"],
            result["associations"]["false"]) == (links, missed, false)
    global_map = mapio.read_global_map(str(runs / "g.csv"))
    truth = mapio.read_truth(str(runs / "s" / "truth.yaml"))
    votes: dict[int, collections.Counter] = collections.defaultdict(collections.Counter)
    for m, l, g in found.tolist():
        votes[g][key[(m, l)]] += 1
    position = dict(zip(truth.feature_ids.tolist(), truth.features.tolist()))
    errors = [np.hypot(*(np.array(xy) - position[min(votes[g], key=lambda t: (-votes[g][t], t))]))
              for g, xy in zip(global_map.feature_ids.tolist(), global_map.features.tolist())]
    assert result["features"] == len(errors)
    assert result["feature_rms"] == pytest.approx(np.sqrt(np.mean(np.square(errors))), rel=1e-12)
    assert result["feature_max"] == pytest.approx(max(errors), rel=1e-12)


@pytest.mark.parametrize("text,naming", [
    ("map,local_id,global_id\n1,0,0\n1,0,3\n", "bad.csv, line 3: map 1, local id 0 has a row already"),
    ("map,local_id,global_id\n0,0,0\n", "bad.csv, line 2, column map: expected an integer >= 1, got 0"),
    ("map,local_id,global_id\n1,0,x\n", "bad.csv, line 2, column global_id: expected a non-negative integer, got 'x'"),
    ("kind,id,x,y\n", "bad.csv, line 1: expected the header map,local_id,global_id"),
    ("map,local_id,global_id\n1,0,0\n", "bad.csv: lacks a row for map 1, local id 1"),
])
def test_a_bad_table_is_one_line_naming_the_file_and_line(runs, text, naming):
    (runs / "bad.csv").write_text(text)
    code, stdout, stderr = run(runs, "evaluate", "g.csv", "--truth", "s", "--associations", "bad.csv")
    lines = stderr.strip().splitlines()
    assert code == 1 and len(lines) == 1 and naming in lines[0], stderr
    assert stdout == ""


def test_the_yaml_table_reads_as_the_csv(runs):
    code, _, stderr = run(runs, "join", "s", "--associate", "--associations", "a.yaml", "-o", "g2.csv")
    assert code == 0, stderr
    csv_table, yaml_table = (mapio.read_correspondence(str(runs / name)) for name in ("a.csv", "a.yaml"))
    for column in ("maps", "local_ids", "global_ids"):
        assert np.array_equal(getattr(csv_table, column), getattr(yaml_table, column))


@pytest.mark.parametrize("args,message", [
    (["--true-associations", "s/associations.csv"], "--true-associations needs --associations"),
    (["--associations", "-", "--true-associations", "-"], "only one of MAP"),
])
def test_option_misuse_is_a_usage_error(runs, args, message):
    code, _, stderr = run(runs, "evaluate", "g.csv", "--truth", "s", *args)
    assert code == 2 and message in stderr


def test_without_a_true_table_beside_the_truth_it_must_be_named(runs):
    code, _, stderr = run(runs, "evaluate", "gp.csv", "--truth", "p", "--associations", "a.csv")
    assert code == 2 and "no p/associations.csv beside --truth; give --true-associations" in stderr


@pytest.fixture(scope="module")
def longer_runs(tmp_path_factory):
    """:func:`simulated_runs` of 30 maps, seed 4: the associating join's own numbering then differs from the truth's
    for most features (in 12 maps many of its first-sighting ids happen to be the truth's)."""
    return simulated_runs(tmp_path_factory.mktemp("evaluate30"), "30", "4")


def test_ids_that_are_not_the_truths_are_warned_of_once_naming_the_map(longer_runs, monkeypatch):
    """An associating join numbers its features itself: compared by id, its features meet unrelated true ones, and
    evaluate says so once (their errors differ between neighbours as much as they are large); through its table,
    and for the known-id join of the same run (whose errors, larger than the features' spacing, are a drift), it
    says nothing."""
    def evaluate(*args: str):
        with monkeypatch.context() as patch:
            patch.chdir(longer_runs)
            result = cli_run("evaluate", *args)  # not -q: the warning is the point
        assert result.exit_code == 0, result.output
        return result

    stderr = evaluate("g.csv", "--truth", "s").stderr
    assert stderr.count("warning") == 1
    assert "g.csv: " in stderr and "--associations" in stderr and "likely not the truth's" in stderr
    for args in (["g.csv", "--truth", "s", "--associations", "a.csv"], ["gp.csv", "--truth", "p"]):
        result = evaluate(*args, "--json")
        assert "warning" not in result.stderr, result.stderr


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), count=st.integers(1, 40), extra=st.integers(0, 40))
def test_features_nearer_another_true_one_are_counted_as_by_a_dense_search(seed, count, extra):
    """``Evaluation.nearer_another`` against every distance computed: a compared feature counts when some true
    feature lies strictly nearer to it than the one it is compared with."""
    from mapjoin.evaluation import _nearer_another

    rng = np.random.default_rng(seed)
    truth = rng.uniform(-10, 10, (count + extra, 2))
    compared = rng.integers(0, len(truth), count)
    features = truth[compared] + rng.normal(scale=rng.uniform(0.01, 5), size=(count, 2))
    distances = np.hypot(*(features[:, None, :] - truth[None, :, :]).transpose(2, 0, 1))
    expected = int(np.count_nonzero(distances.min(axis=1) < distances[np.arange(count), compared]))
    assert _nearer_another(features, truth, compared) == (expected if len(truth) >= 2 else 0)
