"""The chain's drift between a feature's sightings and a join's link, as the association's joins are made.

The gate of :mod:`mapjoin.association` compares a right feature with a left one through the join's link (left's
end pose). A left feature last seen many maps before the link is known relative to *that* map, not to the link:
the joins in between placed the maps with errors that add up (docs/method.md#drift). Where a map closes a loop,
the true pairs' residuals carry this drift and fall out of a gate that only knows the features' own covariances
(docs/method.md#data-association, step 1). :class:`SightingDrift` gives each feature the drift variance ``D`` of
:func:`mapjoin.drift.drift_variance` over the junctions between its last sighting and the link (a left feature)
or between the link and its first sighting (a right feature of a tree join): ``D`` is added to the feature's
2 x 2 covariance in the gate and in the joint test.

It is filled as the joins are made, O(1) per feature and per junction: the chain dead-reckoned once
(:class:`mapjoin.drift.ChainDrift`: only its local shape matters, for lever arms), the prefix sums of the
junctions' posteriors ``v, p, p Re x, p Im x, p |x|^2`` as each join is made, and per feature (by the
associator's compact id) the map and dead-reckoned position of its first and last sighting.

The junctions' posteriors are the chain's drift only where the maps' own dead reckoning adds nothing to them: in
the default ``information`` covariance mode they are conditional variances, and on a simulation whose maps' covariances
are exact they are 100-200 times below each map's own end-pose variance, the drift its dead reckoning adds before the
next junction. :meth:`SightingDrift.dead_reckoned` adds those (the maps' marginal end-pose variances, :attr:`reckoned`)
for the tree joins whose association shows the chain drifted (:mod:`mapjoin.association.drift_evidence`).

A loop closure ties the chain: once a join has matched drifted features last seen around map ``m``, the link is
known relative to map ``m`` as well as to its predecessor. :meth:`SightingDrift.tie` records such a tie and
:meth:`SightingDrift.settled` gives a feature's drift over the shorter way, directly or through one tie
(docs/method.md#data-association, step 7).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..drift import ChainDrift, drift_variance

__all__ = ["SightingDrift"]


@dataclass(frozen=True)
class SightingDrift:
    """The drift sums of a chain of ``N`` maps and its features' first and last sightings (arrays filled in place).

    ``chain``: the maps dead-reckoned (pose ``m`` is map ``m``'s start, ``m + 1`` its end); ``sums`` (N + 2 x 5):
    row ``i`` the sums over the junctions ``< i`` whose posterior is known (:meth:`placed`; junction ``i`` is pose
    ``i``, where map ``i`` starts); per compact feature id: ``first_map``/``last_map`` and their dead-reckoned
    positions ``first_point``/``last_point``."""

    chain: ChainDrift
    sums: np.ndarray
    first_map: np.ndarray
    first_point: np.ndarray
    last_map: np.ndarray
    last_point: np.ndarray
    #: per feature: how far its last sighting disagreed with its estimate when they were fused (a variance; 0 if
    #: new): after a loop closure the fused features sit partway between two estimates metres apart
    strain: np.ndarray
    #: the chain's ties (old map, junction, strain), in the order they were made (:meth:`tie`)
    ties: list[tuple[int, int, float]] = field(default_factory=list)
    #: the ties as arrays (old maps, junctions, strains), made again once ties were added (:meth:`tie_arrays`)
    made_ties: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list, repr=False,
                                                                       compare=False)
    #: the prefix sums (rows as :attr:`sums`) of each map's own end-pose variance placed at its end junction: the drift
    #: its dead reckoning adds (:meth:`dead_reckoned`); zeros when the maps' pose variances are not given
    reckoned: np.ndarray | None = field(default=None, repr=False, compare=False)
    #: the prefix sums of the junctions' excess drift over their posteriors (:meth:`placed`), of which ``sums``
    #: holds the share ``scale[0]`` (:meth:`rescaled`; docs/method.md#data-association, step 6)
    excess: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    scale: np.ndarray = field(default_factory=lambda: np.ones(1))

    @classmethod
    def of(cls, end_poses: np.ndarray, capacity: int, pose_variances: np.ndarray | None = None) -> SightingDrift:
        """A chain of maps with these end poses (N x 3, each in its map's start frame), no junction placed yet,
        room for ``capacity`` feature ids (:meth:`grown` makes more); ``pose_variances`` (N x 2: each map's marginal
        end-pose variance relative to its start, spherical position and heading) give :attr:`reckoned`."""
        chain = ChainDrift.of(end_poses, np.zeros(0, np.intp), np.zeros(0), np.zeros(0))
        size = max(capacity, 1)
        reckoned = np.zeros((len(chain.poses) + 1, 5))
        if pose_variances is not None and len(pose_variances) > 1:  # junction j (map j's start) ends map j - 1
            own = np.asarray(pose_variances, dtype=float).reshape(-1, 2)[:-1]
            reckoned = ChainDrift.of(end_poses, np.arange(1, len(own) + 1), own[:, 0], own[:, 1]).sums
        return cls(chain, np.zeros((len(chain.poses) + 1, 5)), np.zeros(size, np.intp), np.zeros(size, complex),
                   np.zeros(size, np.intp), np.zeros(size, complex), np.zeros(size), reckoned=reckoned,
                   excess=np.zeros((len(chain.poses) + 1, 5)))

    def dead_reckoned(self) -> SightingDrift:
        """The same chain and sightings (the arrays and ties shared, not copied) whose junctions also carry the maps'
        own dead-reckoned drift (:attr:`reckoned`, as the junctions are placed now): every ``D`` it gives adds, over
        the junctions it sums, the end-pose variances of the maps that end there."""
        return dataclasses.replace(self, sums=self.sums + self.reckoned)

    def posterior(self) -> SightingDrift:
        """The same chain and sightings whose junctions carry their posteriors alone, without the share of their excess
        (:meth:`rescaled`): the drift of a tree join whose pieces did not drift beyond it
        (:mod:`mapjoin.association.drift_evidence`)."""
        return dataclasses.replace(self, sums=self.sums - self.scale[0] * self.excess)

    def grown(self, capacity: int) -> SightingDrift:
        """The same with room for at least ``capacity`` feature ids (the tree hands out new ids at every level)."""
        extra = max(capacity - len(self.first_map), 0)
        if not extra:
            return self
        extra = max(extra, len(self.first_map))
        return SightingDrift(self.chain, self.sums, *(np.concatenate([a, np.zeros(extra, a.dtype)]) for a in
                                                       (self.first_map, self.first_point, self.last_map,
                                                        self.last_point, self.strain)), self.ties,
                             reckoned=self.reckoned, excess=self.excess, scale=self.scale)

    def placed(self, junctions: np.ndarray | int, t_variance: np.ndarray | float, phi_variance: np.ndarray | float,
               excess: tuple[float, float] = (0.0, 0.0)) -> None:
        """Joins placed these ``junctions`` (pose indices, each once) with these posterior variances: the prefix
        sums from the lowest of them on gain their terms (in place). One junction (an int, the sequential join's)
        is one row of terms, in floats, with the ``excess`` (translation, turn) of its drift over its posterior
        (:mod:`mapjoin.association.junction_drift`), of which the sums take the share :attr:`scale`."""
        if isinstance(junctions, (int, np.integer)):
            x = complex(self.chain.poses[junctions])
            for sums, (t, p) in ((self.excess, excess), (self.sums, (float(t_variance) + self.scale[0] * excess[0],
                                                                     float(phi_variance) + self.scale[0] * excess[1]))):
                sums[junctions + 1:] += (t, p, p * x.real, p * x.imag, p * (x.real * x.real + x.imag * x.imag))
            return
        junctions = np.atleast_1d(np.asarray(junctions, dtype=np.intp))
        if not len(junctions):
            return
        x = self.chain.poses[junctions]
        for sums, (t, p) in ((self.excess, excess), (self.sums, (t_variance + self.scale[0] * np.asarray(excess[0]),
                                                                 phi_variance + self.scale[0] * np.asarray(excess[1])))):
            p = np.atleast_1d(p) * np.ones(len(x))
            rows = np.column_stack([np.atleast_1d(t) * np.ones(len(x)), p, p * x.real, p * x.imag,
                                    p * (x.real**2 + x.imag**2)])
            if len(junctions) == 1:  # the sequential join: one junction at a time
                sums[junctions[0] + 1:] += rows[0]
                continue
            terms = np.zeros((len(sums), 5))
            np.add.at(terms, junctions + 1, rows)
            sums[:] += np.cumsum(terms, axis=0)

    def rescaled(self, scale: float) -> None:
        """The sums hold the share ``scale`` of the junctions' excess drift from now on (in place, O(maps))."""
        self.sums[:] += (scale - self.scale[0]) * self.excess
        self.scale[0] = scale

    def excess_before(self, ids: np.ndarray, link_map: int) -> np.ndarray:
        """The excess drift (:meth:`placed`, at ``scale`` 1) of left features ``ids`` relative to the end of map
        ``link_map``, over the junctions after their last sighting, as :meth:`before` sums their drift."""
        return drift_variance(self.excess[link_map + 1] - self.excess[self.last_map[ids] + 1], self.last_point[ids])

    def excess_after(self, ids: np.ndarray, link_map: np.ndarray) -> np.ndarray:
        """The excess drift (:meth:`placed`, at ``scale`` 1) of right features ``ids`` of a tree join relative to the
        end of map ``link_map``, over the junctions up to their first sighting, as :meth:`after` sums their drift."""
        return drift_variance(self.excess[self.first_map[ids] + 1] - self.excess[link_map + 2], self.first_point[ids])

    def seen(self, ids: np.ndarray, maps: np.ndarray | int, points: np.ndarray) -> None:
        """New features ``ids`` seen by ``maps`` (one each, or one for all) at ``points`` (each in its map's frame):
        first and last sighting."""
        reckoned = self.chain.dead_reckoned(maps, points)
        self.first_map[ids], self.first_point[ids] = maps, reckoned
        self.last_map[ids], self.last_point[ids] = maps, reckoned
        self.strain[ids] = 0.0

    def seen_again(self, ids: np.ndarray, maps: np.ndarray | int, points: np.ndarray,
                   strain: np.ndarray | float = 0.0) -> None:
        """Features ``ids`` seen again by later ``maps`` at ``points``, ``strain`` from their estimates (squared
        distances): their last sighting."""
        self.last_map[ids], self.last_point[ids] = maps, self.chain.dead_reckoned(maps, points)
        self.strain[ids] = strain

    def merged(self, ids: np.ndarray, others: np.ndarray) -> None:
        """Features ``ids`` found to be features ``others`` seen by later maps (a tree's right piece): the
        later ones' last sightings become theirs."""
        self.last_map[ids], self.last_point[ids] = self.last_map[others], self.last_point[others]

    def copied(self, ids: np.ndarray, others: np.ndarray) -> None:
        """Features ``ids`` are features ``others`` renamed: their sightings."""
        for array in (self.first_map, self.first_point, self.last_map, self.last_point, self.strain):
            array[ids] = array[others]

    def before(self, ids: np.ndarray | slice, link_map: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        """``D`` of left features ``ids`` relative to the end of map ``link_map`` (their piece's last map: one, or one
        per feature), over the junctions after their last sighting up to that map's start, and the heading variance
        those junctions add (the sum of their ``p``)."""
        sums = self.sums[link_map + 1] - self.sums[self.last_map[ids] + 1]
        return drift_variance(sums, self.last_point[ids]), sums[:, 1]

    def across_link(self, ids: np.ndarray, link_map: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Left features ``ids`` against right features at ``points`` (one each, in the frame of map ``link_map + 1``,
        the map after the link) where both maps saw them, for step 6 (docs/method.md#data-association): each pair's
        squared offset between the last sighting and the point, both dead-reckoned (so map ``link_map``'s own
        estimate of the feature through its own end pose, against the next map's: no fused estimate, no join in
        between), and its variance beyond the pair's noise, the end-pose variance of map ``link_map`` there
        (:attr:`reckoned`); infinite for a feature another map saw last."""
        here = self.chain.dead_reckoned(link_map + 1, points)
        offset2 = np.abs(self.last_point[ids] - here) ** 2
        own = np.broadcast_to(self.reckoned[link_map + 2] - self.reckoned[link_map + 1], (len(here), 5))
        return offset2, np.where(self.last_map[ids] == link_map, drift_variance(own, here), np.inf)

    def after(self, ids: np.ndarray, link_map: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``D`` of right features ``ids`` relative to the end of map ``link_map`` (the left piece's last map),
        over the junctions from the right piece's second map up to their first sighting, and their heading
        variance."""
        sums = self.sums[self.first_map[ids] + 1] - self.sums[link_map + 2]
        return drift_variance(sums, self.first_point[ids]), sums[:, 1]

    def between(self, first: np.ndarray, second: np.ndarray, points: np.ndarray) -> np.ndarray:
        """``D`` over the junctions between maps ``first`` and ``second`` (either order along the chain) at the
        dead-reckoned ``points``, broadcast together: the sums from the lower map's end to the higher's, as
        :meth:`before` takes them from a sighting to a link. The ways through the chain's ties (:meth:`settled`,
        :meth:`settled_after`, :func:`mapjoin.association.loop_scope.chain_drift`) are made of such pieces."""
        low, high = np.minimum(first, second), np.maximum(first, second)
        shape = np.broadcast(low, high, points).shape
        sums = self.sums[high + 1] - self.sums[low + 1]
        return drift_variance(np.broadcast_to(sums, (*shape, 5)).reshape(-1, 5),
                              np.broadcast_to(points, shape).ravel()).reshape(shape)

    def tie_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The chain's ties as arrays: old maps, junctions, strains (the ties added since the last call appended to
        the arrays then made: O(new ties), not O(ties), per join)."""
        made = len(self.made_ties[0][0]) if self.made_ties else 0
        if made != len(self.ties):
            ties = np.array(self.ties[made:], dtype=float).reshape(-1, 3)
            added = (ties[:, 0].astype(np.intp), ties[:, 1].astype(np.intp), ties[:, 2])
            self.made_ties[:] = [tuple(np.concatenate([before, after]) for before, after in zip(self.made_ties[0], added))
                                 if made else added]
        return self.made_ties[0]

    def tie(self, old_map: int, junction: int, strain: float) -> None:
        """A join placed map ``junction`` (its start) by matching features last seen around map ``old_map``, whose
        estimates disagreed by ``strain`` (a variance: the join fused them partway and placed the map between):
        from then on, the link is also known through that map, up to the strain (in place)."""
        self.ties.append((int(old_map), int(junction), float(strain)))

    def settled(self, ids: np.ndarray, link_map: np.ndarray | int, start: np.ndarray | int = 0,
                level: np.ndarray | float | None = None, direct: np.ndarray | None = None) -> np.ndarray:
        """``D`` of left features ``ids`` relative to the end of map ``link_map`` (one, or one per feature) over the
        shorter way: the junctions since their last sighting (:meth:`before`), or, through a tie ``(m, c)`` made
        between map ``start`` and the link (the left piece's maps: the sequential join's start at 0), the junctions
        between their last sighting and map ``m`` (either way along the chain) and those from ``c`` up to the link
        (the feature moved with map ``m``'s place to map ``c``'s, a translation) plus the tie's strain; and, either
        way, the feature's own :attr:`strain`. O(ties) per feature: the callers ask it for a join's pairs only.

        The callers only compare ``D`` with a ``level`` (a pair's noise): given it, the ties are searched only for
        the features whose direct ``D`` plus strain reaches it (the shorter way is no longer); the others' direct
        ``D`` plus strain is below it, as is their ``D`` (``level=np.inf``: the direct way plus strain for all, an upper
        bound). ``direct``: the features' ``D`` of :meth:`before` relative to the same ``link_map``, when the caller has
        it (the sequential join asks it of every feature before the join)."""
        ids = np.asarray(ids, dtype=np.intp)
        seen, point = self.last_map[ids], self.last_point[ids]
        best = drift_variance(self.sums[np.asarray(link_map, dtype=np.intp) + 1] - self.sums[seen + 1], point) \
            if direct is None else direct.copy()
        strain = self.strain[ids]
        drifted = best > 0  # a feature seen by the link's map has no shorter way
        if level is not None:
            drifted &= best + strain >= level
        drifted = drifted.nonzero()[0] if self.ties else drifted[:0]
        if len(drifted):  # every (drifted feature, tie) at once
            old_map, junction, tie_strain = self.tie_arrays()
            link, first = (np.asarray(value, dtype=np.intp) for value in (link_map, start))  # one, or one per feature
            link, first = (value[drifted] if value.ndim else value + np.zeros(len(drifted), np.intp)
                           for value in (link, first))
            seen, point = seen[drifted], point[drifted]
            there = self.between(seen[:, None], old_map, point[:, None])
            moved = point[:, None] - self.chain.poses[old_map] + self.chain.poses[junction]
            since = self.sums[link + 1][:, None, :] - self.sums[junction + 1][None, :, :]
            through = tie_strain + there + drift_variance(since.reshape(-1, 5), moved.ravel()).reshape(
                len(seen), len(old_map))
            inside = (junction <= link[:, None]) & (junction >= first[:, None]) & (old_map >= first[:, None])
            best[drifted] = np.minimum(best[drifted], np.where(inside, through, np.inf).min(axis=1))
        return best + strain

    def settled_after(self, ids: np.ndarray, link_map: np.ndarray, end: np.ndarray,
                      level: np.ndarray | float | None = None) -> np.ndarray:
        """``D`` of right features ``ids`` of a tree join (:meth:`after`) over the shorter way: directly, or through a
        tie ``(m, c)`` inside the right piece (maps ``link_map + 1`` to ``end``), the junctions from the piece's start
        to map ``m`` (at the feature moved by map ``c``'s place to map ``m``'s), the tie's strain, and the junctions
        between map ``c`` and the feature's first sighting (either way); plus the feature's own :attr:`strain`. As
        :meth:`settled`, with a ``level`` the ties are searched only where the direct way reaches it (``np.inf``:
        nowhere, the direct way plus strain, an upper bound)."""
        ids = np.asarray(ids, dtype=np.intp)
        first, point = self.first_map[ids], self.first_point[ids]
        best = drift_variance(self.sums[first + 1] - self.sums[link_map + 2], point)
        strain = self.strain[ids]
        drifted = best > 0
        if level is not None:
            drifted &= best + strain >= level
        drifted = drifted.nonzero()[0] if self.ties else drifted[:0]
        if len(drifted):
            old_map, junction, tie_strain = self.tie_arrays()
            first, point, link, last = first[drifted], point[drifted], link_map[drifted], end[drifted]
            there = self.between(first[:, None], junction, point[:, None])
            moved = point[:, None] - self.chain.poses[junction] + self.chain.poses[old_map]
            since = self.sums[old_map + 1][None, :, :] - self.sums[link + 2][:, None, :]  # masked below unless inside
            through = tie_strain + there + drift_variance(since.reshape(-1, 5), moved.ravel()).reshape(
                len(first), len(old_map))
            inside = (old_map >= link[:, None] + 1) & (junction <= last[:, None])
            best[drifted] = np.minimum(best[drifted], np.where(inside, through, np.inf).min(axis=1))
        return best + strain
