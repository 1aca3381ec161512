"""Golden outputs: the commands' files, byte for byte, on the real datasets.

Each case runs one command on ``../shared/data`` and compares the SHA-256 of every file
it wrote with ``golden_outputs.json``. The hashes were recorded from main before the
package was reorganised (issue "one room per job"), so a refactoring that changes a
single byte of any output fails here. A deliberate change of output re-records them:

    MAPJOIN_UPDATE_GOLDEN=1 python -m pytest tests/test_golden.py

and the diff of ``golden_outputs.json`` then shows which outputs changed.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import pytest
from cli_runner import run

GOLDEN = Path(__file__).with_name("golden_outputs.json")
UPDATE = os.environ.get("MAPJOIN_UPDATE_GOLDEN") == "1"

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


def _digests(folder: Path) -> dict[str, str]:
    """Every file below the folder (relative path) -> SHA-256 of its bytes."""
    return {path.relative_to(folder).as_posix(): hashlib.sha256(path.read_bytes()).hexdigest()
            for path in sorted(folder.rglob("*")) if path.is_file()}


def _recorded() -> dict[str, dict[str, str]]:
    return json.loads(GOLDEN.read_text()) if GOLDEN.exists() else {}


@pytest.mark.parametrize("case", sorted(CASES))
def test_outputs_are_byte_identical_to_the_recorded_ones(case, data_dir, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    args = [arg.format(data=data_dir, out=out) for arg in CASES[case]]
    result = run("-q", *args)
    assert result.exit_code == 0, result.output
    digests = _digests(out)
    assert digests, f"{case} wrote nothing"
    if UPDATE:
        recorded = _recorded()
        recorded[case] = digests
        GOLDEN.write_text(json.dumps(dict(sorted(recorded.items())), indent=1) + "\n")
        return
    assert digests == _recorded().get(case), f"{case}: outputs differ from {GOLDEN.name}"


def test_every_recorded_case_is_still_run():
    """A case dropped from the list would silently stop being checked."""
    assert set(_recorded()) == set(CASES)
