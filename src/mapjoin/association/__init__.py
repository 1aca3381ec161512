"""Data association: which features of an incoming map are features of the map it is joined onto.

Maps whose feature ids are local to each map (a front end's submaps) cannot be joined by id.
:func:`join_associated` joins them as :func:`mapjoin.joining.join` does, deciding before each
join (sequential and tree) which features of the right piece are features of the left one
(docs/method.md#data-association):

1. **Covariances.** Each right feature's uncertainty relative to the join's link is its 2 x 2 marginal
   covariance in its local map (the map's full covariance, which the spherical weights of the fast join
   are not: :func:`feature_covariances`), rotated into left's frame. Each left feature carries the
   covariances of its sightings fused as independent estimates: its uncertainty relative to the maps
   that saw it, whose common drift is left to the link's error (3).
2. **Prediction and gate.** Right's features ``z`` are predicted in left's frame through left's end pose
   ``(o, phi_o)``, the join's link: ``x = o + R(phi_o) z``. A link error ``(dt, dphi)`` moves the
   prediction by ``H (dt, dphi)``, ``H = [I, u]``, ``u = R'(phi_o) z``; a pair's innovation
   ``r = f - x`` has covariance ``S = s (C0 + C1) + H P_link H^T``. A pair is a candidate when
   ``r^T S^-1 r`` is within the ``gate`` quantile of a chi-square with 2 degrees of freedom
   (default 0.999: a true pair is refused once in a thousand).
   A tree join also associates its undrifted features alone, under the link's variance relative to its own map,
   and adds the pairs of features left unpaired (the junction rule, :mod:`mapjoin.association.junction`).
   A sequential join associates the right features left ambiguous again with the link's own map's features in the
   link's frame, relative to that map's end pose (:func:`end_relative`), the other unpaired ones as rivals (the link
   rule, :mod:`mapjoin.association.link_pairs`).
3. **Nearest neighbour, when clear.** A pair is taken when each of its features is the other's nearest
   candidate and each one's nearest *rival* is at least ``margin`` farther (squared Mahalanobis distance;
   default 9.2 = 2 ln 100: the nearest is a hundred times likelier). A rival is a candidate that is a
   different feature from the nearest one: seen in one map with it. Two candidates never seen in one map may
   be one feature mapped twice (an earlier miss), and taking the nearest then joins no two features; this
   stops a miss from making every later sighting of the feature ambiguous. Other right features with
   candidates are *ambiguous* and left new.
4. **Joint compatibility.** The pairs share the link's error, so they are tested together: the
   joint Mahalanobis distance of all their innovations (covariance ``blockdiag(s (C0 + C1)) + H P_link H^T``,
   evaluated in 3-D by the Woodbury identity) must be within the ``gate``
   quantile of a chi-square with ``2k`` degrees of freedom. When it is not, the largest jointly
   compatible subset is kept: by exhaustive search over every subset at once (as arrays) when at
   most :data:`EXHAUSTIVE_PAIRS` pairs remain (the optimum branch and bound would find), after
   removing, one at a time, the pair with the largest residual once the link is corrected
   while more remain. Pairs removed are *rejected* and their right features left new.
5. **Rounds.** The pairs give the link's correction and its posterior covariance ``P_link``, and the
   a-posteriori variance factor ``s``: the median of the pairs' squared residuals (Mahalanobis, after the
   correction) over the median of a chi-square with 2 degrees of freedom, robust to a few wrong pairs,
   at least 1, once the pairs have :data:`~mapjoin.association.rounds.MIN_DOF` degrees of freedom. Steps 2 to 4
   run again around the corrected prediction until the pairs repeat (at most :data:`ROUNDS` rounds), which removes
   the link's error and finds the pairs it had hidden (as ICP does).

6. **Loop closures** (:func:`match_with_drift`). Where a map meets features last seen many maps before, the
   chain's drift since then has moved them, relative to the link, by more than the gate and the features'
   spacing. Each feature's drift variance ``D`` since its last sighting (a right piece's feature: up to its
   first) comes from :mod:`mapjoin.association.feature_drift`, which the hooks fill as the joins are made (a
   sequential junction's posterior plus the share of its excess drift, :mod:`mapjoin.association.junction_drift`,
   that the pairs bear out, :mod:`mapjoin.association.drift_scale`); among the
   features steps 2 to 5 left unpaired, the candidates within the drift's gate vote, two pairs at a time, for
   the one rigid correction of the link that the drift made (:mod:`mapjoin.association.loop_votes`); a join whose
   best correction is clearly the best (:data:`LOOP_SUPPORT` right features, :data:`LOOP_CLEAR` times any other
   correction's agreement) associates its unpaired features again, steps 2 to 5 around the corrected link, and keeps
   a pair where it is clear under the correction with its drift relative to the voters, or under the link with its
   drift (:mod:`mapjoin.association.loop_scope`). Then the undrifted features the link's correction moved by more than
   their noise vote once more, the same way, each with the squared distance it moved its prediction as its spread:
   a correction set by drifted pairs is a drift of its own for the features near the link. A tree join whose drifted
   right features mostly missed the left features steps 2 to 5 predicted them near
   (:mod:`mapjoin.association.drift_evidence`) takes the maps' own dead reckoning into ``D`` as well (the junctions'
   posteriors leave it out) and the share of the junctions' excess its level's drifted pairs bear out; its bent right
   piece's other regions vote as no rival, and its closures' pairs are held under their correction only near its voters.
7. **A strained map so far** (:mod:`mapjoin.association.strain`). Before step 6, a pair of
   steps 2 to 5 whose left feature has drifted (``D`` at least the pair's noise) is left new when another left
   feature seen in one map with it lies within its drift (:data:`mapjoin.association.strain.DRIFT_MARGIN`): its
   small offset is no evidence then. ``D`` is taken the shorter way through the chain's ties (a join that matched
   :data:`TIE_SUPPORT` drifted feature ties its map to theirs; a tree join's ties are those inside its pieces)
   plus the strain of the joins that fused features partway between two estimates (a quarter of each pair's
   squared residual, per feature and per tie; :meth:`mapjoin.association.feature_drift.SightingDrift.settled`,
   :meth:`~mapjoin.association.feature_drift.SightingDrift.settled_after`).
8. **A lone drifted pair** (:mod:`mapjoin.association.lone`). After step 7, a pair whose drift is
   :data:`~mapjoin.association.lone.LONE_DRIFT` times its noise, in a join with fewer than
   :data:`~mapjoin.association.lone.CHECKED` such pairs (nothing confirms its drift), is left new when another left
   feature, even one never seen with the chosen one (its second copy), lies within half its drift
   (:data:`~mapjoin.association.lone.LONE_MARGIN`) and a rival seen with it is within ``margin`` under the drift.

9. **The join's own consistency** (:mod:`mapjoin.association.guard`, sequential joins). The one-step join of the
   pairs is solved; when it fails the chi-square check's gate and one pair's residual over its spherical variances
   lies beyond the association's gate under the join's robust variance factor, the join is associated again with
   every drift :data:`~mapjoin.association.guard.GUARD_DRIFT` times larger, which replaces the first association
   when it keeps at least half of its pairs (the report's ``guarded``: the pairs it left out). Once a guard left
   pairs out, the chain's drift is too small: every later join associates with it widened.

The accepted pairs are the join's common features; every other right feature becomes a new
feature of the global map. The global ids are numbered from 0 in order of first sighting:
by map, then by local id.

Cost: :func:`match_features` associates all the joins of a tree level at once (as the tree joins
them), and the sequential join is a batch of one; candidates are all pairs of a join up to
:data:`~mapjoin.association.gate.BRUTE_FORCE_PAIRS`, else found with a grid (:mod:`mapjoin.association.grid`).
Only a join whose pairs fail the joint test is searched on its own.

:func:`local_ids` turns a map set with global ids into one with ids local to each map and
returns the true correspondence (tests, benchmarks, ``simulate --local-ids``).

The rooms inside (docs/architecture.md), from the bottom up: :mod:`~mapjoin.association.covariance_blocks` (step 1),
:mod:`~mapjoin.association.gate` (steps 2 and 3, with :mod:`~mapjoin.association.grid` and
:mod:`~mapjoin.association.junction`), :mod:`~mapjoin.association.joint` (step 4), :mod:`~mapjoin.association.rounds`
(step 5), :mod:`~mapjoin.association.drifted` (steps 6 to 8, with :mod:`~mapjoin.association.feature_drift`,
:mod:`~mapjoin.association.drift_evidence`, :mod:`~mapjoin.association.loop_votes`,
:mod:`~mapjoin.association.loop_scope`, :mod:`~mapjoin.association.strain` and :mod:`~mapjoin.association.lone`),
:mod:`~mapjoin.association.guard` (step 9),
:mod:`~mapjoin.association.associator` (the hooks ``joining`` calls),
:mod:`~mapjoin.association.associated_join` (:func:`join_associated`) and :mod:`~mapjoin.association.correspondence`
(:func:`local_ids`). This package exports the public names.
"""

from __future__ import annotations

from .associated_join import (AssociatedJoin, AssociatedJoinRecord, AssociationCounts, FeatureAssociation,
                              join_associated)
from .associator import TIE_SUPPORT
from .correspondence import LinkErrors, correspondence_rows, link_errors, local_ids, scored, truth_of_found
from .covariance_blocks import blocks, end_relative, feature_covariances, fused, inverted, rotated
from .drifted import LOOP_CLEAR, LOOP_SUPPORT, match_with_drift
from .gate import DEFAULT_GATE, DEFAULT_MARGIN, sighting_bits
from .joint import EXHAUSTIVE_PAIRS
from .rounds import ROUNDS, Matches, match_features

__all__ = [
    "DEFAULT_GATE",
    "DEFAULT_MARGIN",
    "EXHAUSTIVE_PAIRS",
    "LOOP_CLEAR",
    "LOOP_SUPPORT",
    "ROUNDS",
    "TIE_SUPPORT",
    "AssociatedJoin",
    "AssociatedJoinRecord",
    "AssociationCounts",
    "FeatureAssociation",
    "LinkErrors",
    "Matches",
    "blocks",
    "correspondence_rows",
    "end_relative",
    "feature_covariances",
    "fused",
    "inverted",
    "join_associated",
    "link_errors",
    "local_ids",
    "match_features",
    "match_with_drift",
    "rotated",
    "scored",
    "sighting_bits",
    "truth_of_found",
]
