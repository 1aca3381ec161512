"""Reading many local maps at once: the batch path gives exactly the maps, errors and warnings
of reading and checking them one at a time."""

from __future__ import annotations

import itertools
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from hypothesis import given, settings
from hypothesis import strategies as st
from test_formats import assert_same, mapjoin_log, mat_bytes, scratch, warnings_of  # noqa: F401  (fixtures)

from mapjoin import io as mapio
from mapjoin.errors import InputError
from mapjoin.maps import LocalMap, StackedMaps

# ---------------------------------------------------------------------------------------
# The real folders


@pytest.mark.parametrize("folder, step", [("VicPark_200_local_maps", 1), ("VicPark_6898_local_maps", 9)])
def test_a_folder_reads_as_its_files_one_by_one(data_dir, mapjoin_log, folder, step):
    """Every map of VicPark 200; of VicPark 6898 every ninth and the two that I-SLSJF stabilises (a
    file read alone costs some 50 times more than one of a folder; the next test compares all)."""
    paths = mapio.resolve_inputs([str(data_dir / folder)])
    together = mapio.read_maps([str(data_dir / folder)])
    assert [local_map.name for local_map in together] == paths
    warned_together = warnings_of(mapjoin_log)
    mapjoin_log.clear()
    chosen = sorted({*range(0, len(paths), step), *(i for i, path in enumerate(paths)
                                                       if any(path in warning for warning in warned_together))})
    for i in chosen:
        [alone] = mapio.read_map_file(paths[i])
        assert_same(together[i], alone)
    assert warnings_of(mapjoin_log) == warned_together


@pytest.mark.parametrize("folder", ["VicPark_200_local_maps", "VicPark_6898_local_maps"])
def test_a_folder_reads_as_scipy_and_the_checking_constructor_make_its_maps(data_dir, folder):
    """An independent oracle: scipy's parser, I-SLSJF's stabilisation as documented, and
    ``LocalMap.from_covariance``, which checks each map on its own; equal bit for bit."""
    for local_map, path in zip(mapio.read_maps([str(data_dir / folder)]),
                               mapio.resolve_inputs([str(data_dir / folder)]), strict=True):
        raw = scipy.io.loadmat(path)
        state, covariance = raw["localmap_st"], raw["localmap_P"]
        if covariance.diagonal()[:3].min() < 1e-6:
            covariance[[0, 1, 2], [0, 1, 2]] += 1e-6
        k = int(Path(path).stem.split("_")[1])
        expected = LocalMap.from_covariance(path, k - 1, k, state[:3, 1], state[3::2, 0].astype(np.int64),
                                            state[3:, 1].reshape(-1, 2), covariance)
        assert_same(local_map, expected)
        assert not any(getattr(local_map, key).flags.writeable for key in
                       ("end_pose", "feature_ids", "features", "feature_variances", "pose_variances", "covariance"))


# ---------------------------------------------------------------------------------------
# Bad maps: the first bad file of a folder raises what reading it alone raises

DEFECTS = {  # defect -> what the error says (its field, what was expected)
    "nan": "expected finite numbers",
    "inf": "expected finite numbers",
    "asymmetric": "covariance: expected a symmetric matrix",
    "indefinite": "covariance: expected a positive definite matrix",
    "negative-variance": "expected positive variances",
    "duplicate-id": "feature_ids: duplicate id",
    "y-id": "on the x row but",
    "fractional-id": "expected a non-negative integer feature id",
    "pose-id": "expected id 0 on the three end-pose rows",
    "covariance-size": "localmap_P: expected",
    "truncated": "truncated .mat file",
}


@st.composite
def mat_maps(draw) -> tuple[np.ndarray, np.ndarray]:
    """``localmap_st`` and ``localmap_P`` of a valid map of 2 to 4 features, symmetric up to rounding or exactly."""
    m = draw(st.integers(2, 4))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    ids = np.sort(rng.choice(1000, m, replace=False))
    state = np.column_stack([np.r_[0, 0, 0, np.repeat(ids, 2)], rng.normal(size=3 + 2 * m) * 10])
    root = rng.normal(size=(3 + 2 * m, 3 + 2 * m))
    covariance = root @ root.T + np.eye(3 + 2 * m)
    if draw(st.booleans()):  # as I-SLSJF stored them: symmetric up to rounding
        covariance = covariance * (1 + 1e-15 * np.triu(rng.normal(size=covariance.shape), 1))
    return state, covariance


def with_defect(state: np.ndarray, covariance: np.ndarray, defect: str, draw) -> bytes:
    """The .mat file of a map with ``defect`` at a place ``draw`` picks."""
    state, covariance = state.copy(), covariance.copy()
    n = len(state)
    i, j = draw(st.lists(st.integers(0, n - 1), min_size=2, max_size=2, unique=True))
    if defect in ("nan", "inf"):
        value = np.nan if defect == "nan" else -np.inf
        if draw(st.booleans()):
            state[i, 1] = value
        else:
            covariance[i, j] = covariance[j, i] = value
    elif defect == "asymmetric":
        covariance[i, j] += 1e-3 * np.sqrt(covariance[i, i] * covariance[j, j]) + 1
    elif defect == "indefinite":
        covariance[i, j] = covariance[j, i] = 2 * np.sqrt(covariance[i, i] * covariance[j, j])
    elif defect == "negative-variance":
        covariance[i, i] = -10 * covariance.diagonal().max()
    elif defect == "duplicate-id":
        state[5:7, 0] = state[3, 0]
    elif defect == "y-id":
        state[4 + 2 * draw(st.integers(0, (n - 5) // 2)), 0] += 1
    elif defect == "fractional-id":
        state[3 + draw(st.integers(0, n - 4)), 0] += 0.5
    elif defect == "pose-id":
        state[draw(st.integers(0, 2)), 0] = 7
    elif defect == "covariance-size":
        covariance = covariance[:-1, :-1]
    data = mat_bytes(draw(st.booleans()), localmap_st=state, localmap_P=covariance)
    return data[:len(data) - draw(st.integers(1, 40))] if defect == "truncated" else data


FOLDERS = itertools.count()


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_the_first_bad_file_of_a_folder_raises_what_reading_it_alone_raises(scratch, data):
    maps = data.draw(st.lists(mat_maps(), min_size=2, max_size=6))
    bad = data.draw(st.integers(0, len(maps) - 1))
    defect = data.draw(st.sampled_from(sorted(DEFECTS)))
    folder = scratch / f"folder{next(FOLDERS)}"
    folder.mkdir()
    for k, (state, covariance) in enumerate(maps):
        if k == bad:
            content = with_defect(state, covariance, defect, data.draw)
        elif k > bad and data.draw(st.booleans()):  # a later bad file does not matter
            content = with_defect(state, covariance, data.draw(st.sampled_from(sorted(DEFECTS))), data.draw)
        else:
            content = mat_bytes(data.draw(st.booleans()), localmap_st=state, localmap_P=covariance)
        (folder / f"localmap_{k + 1}.mat").write_bytes(content)
    path = str(folder / f"localmap_{bad + 1}.mat")
    with pytest.raises(InputError) as alone:
        mapio.read_map_file(path)
    with pytest.raises(InputError) as together:
        mapio.read_maps([str(folder)])
    assert str(together.value) == str(alone.value)
    assert str(alone.value).startswith(path) and DEFECTS[defect] in str(alone.value)


def test_warnings_come_for_the_maps_read_before_the_error(tmp_path, mapjoin_log):
    state, covariance = np.array([[0, 1.0], [0, 2.0], [0, 0.1]]), np.diag([1e-7, 1.0, 1.0])
    still = mat_bytes(True, localmap_st=state, localmap_P=covariance)
    broken = mat_bytes(True, localmap_st=state, localmap_P=np.diag([1.0, 1.0, np.nan]))
    for order, warned in (((still, broken), 1), ((broken, still), 0)):
        folder = tmp_path / f"warned{warned}"
        folder.mkdir()
        for k, content in enumerate(order, 1):
            (folder / f"localmap_{k}.mat").write_bytes(content)
        mapjoin_log.clear()
        with pytest.raises(InputError, match="expected finite numbers"):
            mapio.read_maps([str(folder)])
        assert len(warnings_of(mapjoin_log)) == warned


def test_an_unreadable_file_comes_after_the_errors_of_the_files_before_it(tmp_path, monkeypatch):
    good = mat_bytes(True, localmap_st=np.array([[0, 1.0], [0, 2.0], [0, 0.1]]), localmap_P=np.eye(3))
    for k in (1, 2):
        (tmp_path / f"localmap_{k}.mat").write_bytes(good)
    read_bytes = mapio.paths._read_bytes

    def refuse_the_second(path: str) -> bytes:
        if path.endswith("localmap_2.mat"):
            raise PermissionError(13, "Permission denied")
        return read_bytes(path)

    monkeypatch.setattr(mapio.paths, "_read_bytes", refuse_the_second)
    with pytest.raises(InputError, match="localmap_2.mat: cannot read \\(Permission denied\\)"):
        mapio.read_maps([str(tmp_path)])
    (tmp_path / "localmap_1.mat").write_bytes(good[:-9])
    with pytest.raises(InputError, match="localmap_1.mat: truncated"):
        mapio.read_maps([str(tmp_path)])


# ---------------------------------------------------------------------------------------
# Stacked maps are checked as the constructor checks each


STACK_DEFECTS = {  # defect -> (field, what the error says)
    "nan-pose": ("end_pose", "expected finite numbers"),
    "inf-feature": ("features", "expected finite numbers"),
    "negative-id": ("feature_ids", "expected non-negative ids"),
    "duplicate-id": ("feature_ids", "duplicate id"),
    "zero-variance": ("feature_variances", "expected positive variances"),
    "nan-pose-variance": ("pose_variances", "expected finite numbers"),
    "inf-covariance": ("covariance", "expected finite numbers"),
    "asymmetric": ("covariance", "expected a symmetric matrix"),
    "indefinite": ("covariance", "expected a positive definite matrix"),
}


@st.composite
def stacks(draw) -> tuple[list[dict], set[int], str]:
    """The fields of a few maps of one size, some rows with a defect; and the first such row's defect."""
    m, count = draw(st.integers(2, 4)), draw(st.integers(1, 6))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    rows = []
    for r in range(count):
        root = rng.normal(size=(3 + 2 * m, 3 + 2 * m))
        covariance = root @ root.T + np.eye(3 + 2 * m)
        if draw(st.booleans()):
            covariance = covariance * (1 + 1e-15 * np.triu(rng.normal(size=covariance.shape), 1))
        rows.append(dict(name=f"map {r}", end_pose=rng.normal(size=3), feature_ids=np.sort(rng.choice(99, m, False)),
                         features=rng.normal(size=(m, 2)), feature_variances=rng.uniform(0.1, 1, m),
                         pose_variances=rng.uniform(0.1, 1, 2), covariance=covariance))
    bad = set(draw(st.lists(st.integers(0, count - 1), max_size=3)))
    first = None
    for r in sorted(bad):
        defect = draw(st.sampled_from(sorted(STACK_DEFECTS)))
        first = first or defect
        row, i = rows[r], draw(st.integers(0, m - 1))
        if defect == "nan-pose":
            row["end_pose"][i % 3] = np.nan
        elif defect == "inf-feature":
            row["features"][i, 1] = np.inf
        elif defect == "negative-id":
            row["feature_ids"][i] = -3
        elif defect == "duplicate-id":
            row["feature_ids"][i] = row["feature_ids"][(i + 1) % m]
        elif defect == "zero-variance":
            row["feature_variances"][i] = 0.0
        elif defect == "nan-pose-variance":
            row["pose_variances"][1] = np.nan
        elif defect == "inf-covariance":
            row["covariance"][i, i] = np.inf
        elif defect == "asymmetric":
            row["covariance"][i, i + 1] += 1.0
        else:  # a 2 x 2 principal minor with a negative determinant
            c = row["covariance"]
            c[i, i + 1] = c[i + 1, i] = 2 * np.sqrt(c[i, i] * c[i + 1, i + 1])
    return rows, bad, first


@settings(max_examples=300, deadline=None)
@given(stacks())
def test_a_stack_fails_at_its_first_bad_map_as_the_constructor_fails_on_it(case):
    rows, bad, defect = case
    stack = StackedMaps(*(np.array([row[key] for row in rows]) if key != "name" else [row[key] for row in rows]
                          for key in StackedMaps._fields))
    found = stack.first_invalid()
    if not bad:
        assert found is None
        for row, local_map in zip(rows, stack.local_maps([0] * len(rows), [1] * len(rows)), strict=True):
            assert_same(local_map, LocalMap(start_id=0, end_id=1, **row))  # symmetrised alike, bit for bit
        return
    first = min(bad)
    with pytest.raises(InputError) as alone:
        LocalMap(start_id=0, end_id=1, **rows[first])
    field, expected = STACK_DEFECTS[defect]
    assert found[0] == first and str(found[1]) == str(alone.value)
    assert alone.value.where == field and expected in str(alone.value)


# ---------------------------------------------------------------------------------------
# Import cost


def test_the_command_line_imports_neither_yaml_nor_package_metadata_until_needed():
    code = ("import sys, mapjoin.cli; print(sorted({'yaml', 'importlib.metadata'} & set(sys.modules)))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                            env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert result.stdout.strip() == "[]"


def test_checking_a_stack_changes_none_of_its_arrays_and_its_maps_hold_a_symmetrised_copy():
    """Covariances asymmetric by rounding are symmetrised in the maps only: the caller's arrays stay as they were."""
    covariance = np.diag([2.0, 2.0, 1.0, 3.0, 3.0])
    covariance[0, 1], covariance[1, 0] = 1e-9, 1.1e-9  # within SYMMETRY_TOLERANCE
    stack = StackedMaps(["m"], np.zeros((1, 3)), np.array([[7]]), np.ones((1, 1, 2)), np.ones((1, 1)),
                        np.ones((1, 2)), covariance[np.newaxis].copy())
    before = [None if array is None else array.copy() for array in stack[1:]]
    assert stack.first_invalid() is None
    [local_map] = stack.local_maps([0], [1])
    for array, original in zip(stack[1:], before):
        assert np.array_equal(array, original) and array.flags.writeable
    assert local_map.covariance[0, 1] == local_map.covariance[1, 0] == (1e-9 + 1.1e-9) / 2
    assert not local_map.covariance.flags.writeable
    given = covariance.copy()
    assert np.array_equal(LocalMap("m", 0, 1, [0, 0, 0], [7], [[1, 1]], [1.0], [1, 1], given).covariance,
                          local_map.covariance)
    assert np.array_equal(given, covariance)
