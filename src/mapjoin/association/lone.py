"""Drifted pairs that no other pair confirms: a lone drifted pair beside a second copy and a rival is left new.

Step 7 (:mod:`mapjoin.association.strain`) leaves a drifted pair new when a rival *seen in one map with the chosen
feature* lies within the drift. A rival never seen with it is not counted there, because it may be the chosen
feature mapped twice after a miss (docs/method.md#data-association, step 3). On DLR the last false links are of that
kind (benchmarks/README.md, "Data association"): a marker met again after about 1 m of drift lands 0.06-0.15 m from
an old marker *and* 0.1-0.5 m from that marker's duplicate, its true partner a metre away; and each is the only pair
of its join whose drift is large against its noise (50-500 times), the others being recent features. The drift is
one rigid correction for the features seen at one time (step 6), so drifted pairs confirm one another when there are
three (two fix a correction, the third checks it); a lone one (or one of two) is confirmed by nothing but its small
offset, which the drift makes chance where other features are near.

:func:`lone_drifted` names those pairs; :mod:`mapjoin.association` leaves one new when both another left feature, seen
with the chosen one or not, lies within half its drift (:data:`LONE_MARGIN`: a second copy, the map so far unsure
there) and a rival seen with it is not clear by the clear nearest neighbour's margin under the drift (both asked of
:func:`mapjoin.association.strain.drift_rivals`; docs/method.md#data-association, step 8). The copy alone would do on
the six measured cases, but on VicPark's 6898 small maps, whose drift is far wider, it leaves true pairs new.
"""

from __future__ import annotations

import numpy as np

__all__ = ["CHECKED", "LONE_DRIFT", "LONE_MARGIN", "lone_drifted"]

#: a pair is drifted for this rule when its drift ``D`` is at least this many times its noise (DLR's false pairs:
#: 49-480; at 1, VicPark's sequential join loses true pairs whose drift is about their noise)
LONE_DRIFT = 10.0
#: ... and lone when its join has fewer than this many such pairs (two fix a rigid correction, a third checks it)
CHECKED = 3
#: a lone drifted pair has a second copy when another left feature is nearer than this much farther, in squared
#: distance over the pair's drift and noise (DLR's false pairs: 0.007-0.2; 1 costs VicPark's sequential join 2 links)
LONE_MARGIN = 0.5


def lone_drifted(pair_join: np.ndarray, noise: np.ndarray, drift: np.ndarray, joins: int) -> np.ndarray:
    """Which pairs are drifted (``drift >= LONE_DRIFT * noise``; ``noise``, ``drift``: each pair's half-trace variance
    and drift ``D``) and lone: in a join (``pair_join``, values < ``joins``) with fewer than :data:`CHECKED` such
    pairs (a mask over the pairs)."""
    drift = np.asarray(drift, dtype=float)
    drifted = (drift > 0) & (drift >= LONE_DRIFT * np.asarray(noise, dtype=float))
    count = np.bincount(np.asarray(pair_join)[drifted], minlength=joins)
    return drifted & (count[pair_join] < CHECKED)
