"""How much of the junctions' excess drift the data bear out: ``D = D_posterior + s D_excess`` with ``s`` estimated
(docs/method.md#data-association, step 6).

The sequential join's drift ``D`` sums each junction's posterior; :mod:`mapjoin.association.junction_drift` gives
each junction a second, larger variance, the previous map's own uncertainty at the shared features, and the excess
of the one over the other. Which is right differs by data: on the default simulation the true pairs met again lie
where the excess puts them; on VicPark and DLR the posterior already overestimates the drift (their local maps'
covariances are conservative). So ``s`` in ``[0, 1]`` is estimated from the accepted pairs that drifted
(``D >= noise``, along the chain without a tie): each pair's squared offset ``r^2`` around the uncorrected link
is, under the model, exponential with mean ``2 sigma^2``, ``sigma^2 = n + l + D_posterior + s D_excess`` (noise,
the link's spread, the drift). The pairs were accepted inside gates, which truncate their offsets: steps 2-5
keep a pair within the gate of its noise and the link's spread (``r^2 <= g (n + l)``, around the link as the rounds
corrected it), and step 6 looks only at the features they left unpaired, keeping a share ``q`` of them (where a
loop closure is voted) within the gate of their drift as the join read it (``g (n + l + D)``). So a pair's density
is the exponential's times 1 inside the first bound and ``q`` between the two, over its integral,
``F(g (n + l)) + q (F(g (n + l + D)) - F(g (n + l)))``; ``s`` and ``q`` are estimated together (``q`` unknown: how
often loops close). Without the truncation the kept pairs say the drift is smaller than it is (the far ones were
never kept); with each pair truncated at one bound only (the first inside it, the second beyond it) the estimate
is biased upwards. A join's drifted pairs share one rigid correction (step 6): they are one observation of the
drift, not one each, so each pair's log-likelihood weighs ``1 / (the join's drifted pairs)`` (when each counted
alone, the 12 pairs of one closure of a 100-map simulation, whose drift the posterior happened to hold, set
``s = 0`` for the rest of its run). The maximum-likelihood ``s`` over a grid (0, and 10^-3 to 1 geometrically;
``q`` over 10^-3 to 1) is the estimate; before :data:`WARM_UP` joins with drifted pairs it is 1 (the junctions' own
uncertainty, an honest prior when nothing is known)."""

from __future__ import annotations

import numpy as np

__all__ = ["DriftScale", "WARM_UP"]

#: joins with drifted pairs observed before the estimate replaces the prior ``s = 1``
WARM_UP = 8
#: the estimate is made again once those joins grew by this share since it was last made (the schedule its
#: measurements were made with; the likelihood is kept as a running sum, so an estimate costs O(1))
GROWTH = 0.05
#: the values of ``s`` the likelihood is evaluated at
SCALES = np.concatenate([[0.0], np.geomspace(1e-3, 1.0, 61)])
#: the values of the share of the pairs beyond the ordinary gate that a loop closure keeps, estimated with ``s``
SHARES = np.geomspace(1e-3, 1.0, 16)


class DriftScale:
    """The running estimate of ``s``: :meth:`observe` adds a join's drifted pairs, :attr:`scale` is the estimate
    (``gate``: the association's chi-square level, whose 2-dof quantile bounds the accepted offsets); ``count`` is
    the joins observed with drifted pairs. Each pair's log-likelihood depends on its own columns only, so the
    weighted sum over the pairs so far (:attr:`likelihood`, one value per ``(s, q)`` of the grid) is added to as the
    joins come: each pair is evaluated once, where summing every pair again at each estimate cost O(pairs) each
    (about a tenth of the sequential association on VicPark and DLR)."""

    def __init__(self, gate: float):
        self.bound = -2.0 * np.log1p(-gate)  # chi-square(2) quantile at the gate's level
        self.likelihood = np.zeros((len(SCALES), len(SHARES)))
        self.count = 0
        self.estimated_at = 0
        self.scale = 1.0

    def observe(self, offset2: np.ndarray, noise: np.ndarray, posterior: np.ndarray, excess: np.ndarray,
                drift: np.ndarray, join: np.ndarray | None = None) -> bool:
        """The drifted accepted pairs of one join (``join`` None) or of a tree level's joins (``join``: each pair's):
        squared offsets ``r^2`` around the uncorrected link, ``noise`` (their noise plus the link's spread), the
        posterior and excess parts of their drift and the drift the join read (all half-traces); each join is one
        observation. Whether :attr:`scale` changed."""
        if len(offset2):
            join = np.zeros(len(offset2), np.intp) if join is None else np.unique(join, return_inverse=True)[1]
            pairs = np.bincount(join)
            self.likelihood += self._log_likelihood(offset2, noise, posterior, excess, drift, 1.0 / pairs[join])
            self.count += len(pairs)
        if self.count < WARM_UP or self.count < (1.0 + GROWTH) * self.estimated_at:
            return False
        self.estimated_at = self.count
        best = np.argmax(self.likelihood.ravel())
        scale = float(SCALES[best // len(SHARES)])
        changed, self.scale = scale != self.scale, scale
        return changed

    def _log_likelihood(self, offset2: np.ndarray, noise: np.ndarray, posterior: np.ndarray, excess: np.ndarray,
                        drift: np.ndarray, weight: np.ndarray) -> np.ndarray:
        """The pairs' log-likelihoods summed, each weighing ``weight`` (one over its join's pairs), at each ``(s, q)``
        of the grid (scales x shares): each pair's offset exponential with mean ``2 (n + D_posterior + s D_excess)``,
        its density 1 inside the first gate and ``q`` between the two, over its integral."""
        inner, outer = self.bound * noise, self.bound * (noise + drift)
        variance = noise + posterior + SCALES[:, None] * excess  # scales x pairs
        kept_inner, kept_outer = (-np.expm1(-bound / (2 * variance)) for bound in (inner, outer))
        exponential = (-np.log(variance) - offset2 / (2 * variance)) @ weight  # scales: no share in it
        beyond = np.sum(weight[offset2 > inner]) * np.log(SHARES)  # shares: the pairs past the first gate
        kept = kept_inner[:, None, :] + SHARES[None, :, None] * (kept_outer - kept_inner)[:, None, :]
        return exponential[:, None] + beyond[None, :] - np.log(kept) @ weight
