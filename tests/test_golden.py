"""Golden outputs: the commands' files on the real datasets, against recorded fingerprints.

Each case runs one command on ``../shared/data`` and compares what it wrote with
``golden_outputs.json``. Outputs are not compared byte for byte: the last bits of a
floating-point result depend on the CPU (numpy's SIMD paths and OpenBLAS's kernels
differ between an AVX-512 and an AVX2 machine), and the solvers that stop at a
tolerance (the golden-section search, the least-squares builds) carry such differences
up to their tolerance. So a case's fingerprint is

- ``layout``: the SHA-256 of every file's name and text with each number replaced by
  ``#`` (and the data and output folders, which outputs name, by placeholders): any change of format, order, header or count of values fails exactly;
- ``count``: how many numbers the case wrote, and ``digits``: the mean number of
  significant digits they were written with (a lost precision fails);
- ``sample``: 128 numbers at evenly spaced positions, compared one by one with
  ``|a - b| <= rtol * |b| + atol``;
- ``segments``: the numbers cut into 32 consecutive runs; per run the sum, a sum with
  fixed pseudo-random signs and the sum of magnitudes. A change anywhere moves these, and
  both sums must agree within ``rtol`` times the run's sum of magnitudes.

The tolerances are far above the differences measured between an AVX-512 machine and the
same machine run with numpy's AVX-512 (or AVX2) paths off and OpenBLAS on its Haswell (or
Sandybridge) kernels: the largest of those used 1/400 of its case's tolerance. They are
far below any change a refactoring bug makes (``rtol`` is a micrometre on a kilometre). A deliberate change of output re-records them:

    MAPJOIN_UPDATE_GOLDEN=1 python -m pytest tests/test_golden.py
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from cli_runner import run

GOLDEN = Path(__file__).with_name("golden_outputs.json")
UPDATE = os.environ.get("MAPJOIN_UPDATE_GOLDEN") == "1"

NUMBER = re.compile(rb"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
SAMPLES = 128
SEGMENTS = 32
RTOL, ATOL = 1e-6, 1e-10
# Cases whose result is only defined to a solver's stopping tolerance: the golden-section
# search stops on a bracket width (measured across CPUs: 1e-5 relative), and the iSAM build
# solves each map's least squares to convergence (2e-5 relative).
LOOSE = {"join-golden-solver": (1e-3, 1e-7), "build-isam-stream": (1e-3, 1e-7)}


MAP_SETS = ("535_data_5_local_maps", "8240_data_50_local_maps", "DLR_200_local_maps",
            "VicPark_200_local_maps", "VicPark_6898_local_maps")
SMALL_SETS = MAP_SETS[:3]


def _cases() -> dict[str, list[str]]:
    """Case name -> command line; ``{data}`` is the shared data folder, ``{out}`` a fresh folder."""
    cases: dict[str, list[str]] = {}
    for name in MAP_SETS:
        for strategy in ("sequential", "tree"):
            for mode in ("identity", "marginal", "information"):
                cases[f"join-{name}-{strategy}-{mode}"] = [
                    "join", f"{{data}}/{name}", "--strategy", strategy, "--covariance", mode,
                    "-o", "{out}/global.csv", "--report", "{out}/joins.csv"]
        cases[f"refine-{name}"] = ["refine", f"{{data}}/{name}", "-o", "{out}/exact.csv"]
    vicpark = "{data}/VicPark_200_local_maps"
    cases.update({
        "join-formats-yaml-json": ["join", vicpark, "-o", "{out}/global.yaml", "--report", "{out}/joins.json"],
        "join-formats-g2o-yaml": ["join", vicpark, "-o", "{out}/global.g2o", "--report", "{out}/joins.yaml"],
        "join-golden-solver": ["join", vicpark, "--solver", "golden", "-o", "{out}/global.csv",
                               "--report", "{out}/joins.csv"],
        "join-tree-jobs": ["join", "{data}/VicPark_6898_local_maps", "--strategy", "tree", "-j", "2",
                           "-o", "{out}/global.csv"],
        "join-refine": ["join", "{data}/DLR_200_local_maps", "--refine", "-o", "{out}/exact.yaml"],
        "refine-tree-start": ["refine", vicpark, "--start", "tree", "-o", "{out}/exact.csv"],
        "refine-no-covariances-yaml": ["refine", "{data}/535_data_5_local_maps", "--no-covariances",
                                       "-o", "{out}/exact.yaml"],
        "refine-linearslam": ["refine", "{data}/linearslam_txt/8240_data_50_local_maps", "-o", "{out}/exact.csv"],
        "build-vicpark": ["build", f"{vicpark}/VicPark_clean_data.mat", "-o", "{out}/maps/", "--maps", "20",
                          "--global-map", "{out}/batch.csv"],
        "build-isam-stream": ["build", "{data}/victoria_park_raw/victoria_park_isam.txt", "-o", "{out}/maps.yaml",
                              "--maps", "5"],
        "build-vicpark-csv-jobs": ["build", f"{vicpark}/VicPark_clean_data.mat", "-o", "{out}/maps.csv",
                                   "--poses-per-map", "400", "-j", "2"],
        "convert-linearslam-to-yaml": ["convert", "{data}/linearslam_txt/8240_data_50_local_maps",
                                       "-o", "{out}/maps/", "--to", "yaml"],
        "convert-vicpark-to-csv-stream": ["convert", vicpark, "-o", "{out}/maps.csv"],
        "simulate-folder": ["simulate", "-o", "{out}/sim/", "--maps", "30", "--seed", "7"],
        "simulate-csv-stream": ["simulate", "-o", "{out}/sim.csv", "--maps", "40", "--seed", "2",
                                "--steps-per-map", "6", "--truth", "{out}/truth.csv"],
    })
    for name in SMALL_SETS:
        for to in ("yaml", "csv", "mat", "linearslam"):
            cases[f"convert-{name}-to-{to}"] = ["convert", f"{{data}}/{name}", "-o", "{out}/maps/", "--to", to]
    return cases


CASES = _cases()


def _read(path: Path, places: dict[bytes, bytes]) -> tuple[bytes, np.ndarray, int]:
    """A file's layout (its text with numbers as ``#``), its numbers in order, and their digits.

    ``places`` maps the machine's folders (the data folder, the output folder) to
    placeholders: outputs name their sources by path, and CI clones elsewhere.
    """
    if path.suffix == ".mat":
        contents = scipy.io.loadmat(path)
        names = sorted(name for name in contents if not name.startswith("__"))
        arrays = [np.asarray(contents[name], dtype=float) for name in names]
        layout = repr([(name, array.shape) for name, array in zip(names, arrays)]).encode()
        values = np.concatenate([array.ravel(order="F") for array in arrays] or [np.empty(0)])
        return layout, values, 17 * values.size
    text = path.read_bytes()
    for folder, placeholder in places.items():
        text = text.replace(folder, placeholder)
    tokens = NUMBER.findall(text)
    return NUMBER.sub(b"#", text), np.array([float(token) for token in tokens]), sum(map(_digits, tokens))


def _digits(token: bytes) -> int:
    """Significant digits a number was written with: ``0.0125`` has 3, ``1.5e-07`` has 2."""
    mantissa = re.split(rb"[eE]", token)[0].lstrip(b"+-").replace(b".", b"").lstrip(b"0")
    return len(mantissa)


def _fingerprint(folder: Path, places: dict[bytes, bytes] | None = None) -> dict:
    """The fingerprint of every file below the folder (see the module docstring)."""
    layout = hashlib.sha256()
    numbers, digits = [], 0
    for path in sorted(folder.rglob("*")):
        if path.is_file():
            text, values, written = _read(path, places or {})
            digits += written
            layout.update(path.relative_to(folder).as_posix().encode() + b"\0" + text + b"\0")
            numbers.append(values)
    values = np.concatenate(numbers) if numbers else np.empty(0)
    signs = np.where((np.arange(values.size, dtype=np.uint64) * np.uint64(2654435761) >> np.uint64(16))
                     & np.uint64(1), 1.0, -1.0)
    segments = [[float(part.sum()), float((part * sign).sum()), float(np.abs(part).sum())]
                for part, sign in zip(np.array_split(values, SEGMENTS), np.array_split(signs, SEGMENTS))]
    positions = np.unique(np.linspace(0, values.size - 1, SAMPLES).round().astype(int)) if values.size else []
    return {"layout": layout.hexdigest(), "count": int(values.size),
            "digits": round(digits / max(values.size, 1), 3),
            "sample": [float(values[k]) for k in positions], "segments": segments}


def _differences(case: str, got: dict, recorded: dict) -> list[str]:
    """What differs between two fingerprints beyond the case's tolerance (empty: none)."""
    if got["layout"] != recorded["layout"] or got["count"] != recorded["count"]:
        return [f"layout or count of numbers changed ({got['count']} numbers, recorded {recorded['count']})"]
    rtol, atol = LOOSE.get(case, (RTOL, ATOL))
    found = []
    if abs(got["digits"] - recorded["digits"]) > 0.25:
        found.append(f"numbers written with {got['digits']} significant digits on average, "
                     f"recorded {recorded['digits']}")
    for k, (a, b) in enumerate(zip(got["sample"], recorded["sample"])):
        if not abs(a - b) <= rtol * abs(b) + atol:
            found.append(f"sampled number {k}: {a!r}, recorded {b!r}")
    for k, (mine, theirs) in enumerate(zip(got["segments"], recorded["segments"])):
        bound = rtol * theirs[2] + atol * (recorded["count"] / SEGMENTS + 1)
        if not all(abs(a - b) <= bound for a, b in zip(mine, theirs)):
            found.append(f"run {k} of {SEGMENTS}: sums {mine}, recorded {theirs}")
    return found


def _recorded() -> dict[str, dict]:
    return json.loads(GOLDEN.read_text()) if GOLDEN.exists() else {}


@pytest.mark.parametrize("case", sorted(CASES))
def test_outputs_match_the_recorded_ones(case, data_dir, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    args = [arg.format(data=data_dir, out=out) for arg in CASES[case]]
    result = run("-q", *args)
    assert result.exit_code == 0, result.output
    got = _fingerprint(out, {str(out).encode(): b"{out}", str(data_dir).encode(): b"{data}"})
    assert got["layout"] != hashlib.sha256().hexdigest(), f"{case} wrote nothing"
    if UPDATE:
        recorded = _recorded()
        recorded[case] = got
        GOLDEN.write_text(json.dumps(dict(sorted(recorded.items())), indent=1) + "\n")
        return
    assert case in _recorded(), f"{case} has no recorded fingerprint"
    differences = _differences(case, got, _recorded()[case])
    assert not differences, f"{case}: outputs differ from {GOLDEN.name}:\n" + "\n".join(differences[:10])


def _write_numbers(folder: Path, values: np.ndarray) -> dict:
    (folder / "values.csv").write_text("".join(f"{value!r}\n" for value in values.tolist()))
    return _fingerprint(folder)


def test_the_comparison_catches_a_changed_number_and_a_changed_layout(tmp_path):
    """The fingerprint itself: equal outputs pass; one number off by 1e-4, or one reformatted, fails."""
    rng = np.random.default_rng(1)
    values = rng.normal(size=5000) * 10.0 ** rng.integers(-6, 3, 5000)
    recorded = _write_numbers(tmp_path, values)
    assert _differences("any", _write_numbers(tmp_path, values), recorded) == []
    assert _differences("any", _write_numbers(tmp_path, values * (1 + 1e-9)), recorded) == []
    changed = values.copy()
    changed[int(np.argmax(np.abs(values)))] *= 1 + 1e-4
    assert _differences("any", _write_numbers(tmp_path, changed), recorded)
    (tmp_path / "values.csv").write_text("".join(f"{value:.6e}\n" for value in values.tolist()))
    assert _differences("any", _fingerprint(tmp_path), recorded)


def test_every_recorded_case_is_still_run():
    """A case dropped from the list would silently stop being checked."""
    assert set(_recorded()) == set(CASES)
