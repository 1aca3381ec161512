"""The simulator's output is stable: fixed seeds give the bytes they gave before it was made faster.

The digests were recorded at commit 7a05a2a (before the simulator built its world's visibility a chunk of
maps at a time and checked its maps as stacks), by the fingerprint below and by ``sha256sum`` of the
command's standard output. A change that alters them breaks users' reproducibility: it must bump a
documented version of the simulation instead (docs/commands.md, ``simulate``). The covariances come
from BLAS products and the poses from numpy's trigonometry, so a digest holds for one numpy and BLAS;
another may round the last bits differently. Each run therefore keeps one digest per environment it
was recorded in, every one made by the commit above (never by the code under test): the first under
the numpy of the recording, the second under numpy 2.4.6 with scipy-openblas 0.3.31 (2026-11-26, by
``git worktree add`` of 7a05a2a and the fingerprint below; that commit and the code of the day gave
the same digests there). A new environment gets its digests the same way.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
from cli_runner import run

from mapjoin.simulation import Simulation, simulate

#: name: (maps, keyword arguments, sha256 of :func:`fingerprint` per environment), recorded at 7a05a2a
LIBRARY_RUNS = {
    "default-20": (20, {},
        ("fb9a57e6e2903e011a5dba523be7993ff49b9dd9c138fb76031418436373382d",
         "a6a277d627a602323ab064dc889b4ddd1ca8501a69e8d0b3bf9942c99ed4145f")),
    "one-map": (1, dict(seed=5),
        ("3abb44593fb905d638cc310f37933f6723ee95fcb83dca25ff3afb08390bf468",
         "abbc7c4997d674e25a56ca1089c90cf51b001eb2ad39e6617e9fb8206c52303a")),
    "steps1-300": (300, dict(seed=11, steps_per_map=1),
        ("9770c75f89d00a9dfc9619643720fdef3c75e6a98d76b4e53c4c35ae5ae4cc7b",
         "9770c75f89d00a9dfc9619643720fdef3c75e6a98d76b4e53c4c35ae5ae4cc7b")),
    "chunks-1100": (1100, dict(seed=3, steps_per_map=4),
        ("347ee8f87c5d68fea939dba49f3109faf9db4dbc5a3603f313172a596124548d",
         "983a7c50ceb86254b8da0ba223a24e057565202f5c51a2e912f464715078f339")),
    "laps-3.7": (150, dict(seed=9, laps=3.7, steps_per_map=7),
        ("6c7bec25eca5c50c1174389d6260e511dbfbefd07736a1c310c0dc189cb1e139",
         "5d4c4cc2dab7553fd40fcab58bd28a5678e69b5547155b3ab9a83f06fec6d351")),
    "laps-0.5": (60, dict(seed=4, laps=0.5),
        ("d600b4ba215af99b96935e83601ceadc97dbb2f3f8b261dcec83e308232f9fd2",
         "7b73579356ea1fbf2eff94fa511e8fbf33965bd0787fa46ae0ea9b83779ca5f2")),
    "sparse-8": (80, dict(seed=2, min_shared=8, density=0.03),
        ("eae5d06f9589579a37abcdebafc16dae5d5611ad3631bd815f38a9592afbe25d",
         "882bb73c17098781a4503d3802c59119b1e9d9948d145307ae806babf2e2cc4d")),
    "no-world": (50, dict(seed=6, features=0),
        ("b5740e6fc72d775ffb23d68750a878c0716426b501899a0531250ead2af56a50",
         "6052965f307f61037ed638e7811e815adffe5260faae3fb51f08f94a8426fc4c")),
    "features-900": (70, dict(seed=8, features=900, laps=2.5),
        ("852e44477ebb20b0cec01448650d47b8e025e745f72aee652edeeb15f031bef8",
         "f2d17c7b2387e17ccd1448f61c621cdbe4e46baf3f17dec880c0e32a56196786")),
    "ranges": (90, dict(seed=10, sensor_range=9.0, min_range=2.0, step_length=1.5),
        ("f36332b7565109d69efe123e5c2deb6943dee994219f818663e635bc228ed113",
         "4791c5b8a8b61da5b0fe82558d704e60c71e2867098fa9d662e7a603ce1b9a3e")),
    "noiseless": (40, dict(seed=12, noiseless=True),
        ("eade68aff2144288a3c6fb1c070a791e5e1613e504998264378ec410b8e85bc0",
         "3ab8d519234805f496cbb29ca9751a2f4fb6d5ad629a3efe927b9dfa521c8213")),
    "spherical": (600, dict(seed=14, full_covariance=False),
        ("804675d80530d73fdba22a946e460b778ebd21b01a8c392e1dd2a523cdb2c794",
         "804675d80530d73fdba22a946e460b778ebd21b01a8c392e1dd2a523cdb2c794")),
    "no-guarantee": (45, dict(seed=15, min_shared=0, density=0.05),
        ("b90bd3f92cff9f978b85763082100124c5184345a2e23716d56f7334b913a077",
         "a75c4318b962f84702a4cd828d9561ff72901fa9c26f0c4eb394e6727e8a5e7f")),
    "small-lap-many": (400, dict(seed=16, steps_per_map=2, laps=40),
        ("58eeac43d368ac9d8089496c06f43537fd484d2ce6cad59a6d947db717836134",
         "ce9d850b18bde6606f198939f9f43ff1f2a8a2fcba49219acf4334decd80c3cc")),
}

#: ``mapjoin simulate -o - ARGS`` and the sha256 of its standard output per environment, recorded at 7a05a2a
COMMAND_RUNS = [
    ("--maps 3000 --seed 1 --no-covariances --format csv",
     ("9edd65430238ac49fb319107af82ad7e824e74c2ea41d0cee577b199823d071b",
      "210464f855e792150d1a0451171c2d18227b515768865c6b94357d6859b8754b")),
    ("--maps 200 --seed 2",
     ("3ba54a4c21c6a632601c7ab54b909c6f0b8de2b21b49576a574e1e25bd2787a4",
      "9ed3735c9a63fa36d12e6d06b8e07798a8506e51df0d4c2c28bc7558dce626db")),
    ("--maps 700 --seed 3 --steps-per-map 3 --format csv",
     ("7c55911f013b4aa4c66b877c3308a52297cc9029ea825d555ba4b88072f64dd8",
      "06d8588d17a1ed80e6367628a7fff11392d5e9d5fce2e4712306aaf3bd55f419")),
    ("--maps 300 --seed 4 --no-covariances",
     ("efe0fe2017dc25eb8f51dacb1c36f569b86d93aaf6d2ee350a5e5946277c3641",
      "445bddb384c748648e887d6d3c3423b4f02eeb0638f3d11d26365eb777077e63")),
]


def fingerprint(sim: Simulation) -> str:
    """sha256 of every map's name, ids and arrays (their bytes, in order) and of the truth's arrays."""
    digest = hashlib.sha256()
    for m in sim.maps:
        digest.update(f"{m.name},{m.start_id},{m.end_id};".encode())
        for field in ("end_pose", "feature_ids", "features", "feature_variances", "pose_variances", "covariance"):
            value = getattr(m, field)
            digest.update(b"-" if value is None else np.ascontiguousarray(value).tobytes())
    for field in ("feature_ids", "features", "pose_ids", "poses"):
        digest.update(np.ascontiguousarray(getattr(sim.truth, field)).tobytes())
    return digest.hexdigest()


@pytest.mark.parametrize("name", LIBRARY_RUNS)
def test_library_runs_are_bit_identical_to_the_recorded_ones(name):
    maps, kwargs, expected = LIBRARY_RUNS[name]
    assert fingerprint(simulate(maps, **kwargs)) in expected


@pytest.mark.parametrize("args, expected", COMMAND_RUNS, ids=[args for args, _ in COMMAND_RUNS])
def test_command_streams_are_byte_identical_to_the_recorded_ones(args, expected):
    result = run("simulate", "-o", "-", *args.split())
    assert result.exit_code == 0
    assert hashlib.sha256(result.stdout_bytes).hexdigest() in expected
