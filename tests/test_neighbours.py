"""mapjoin.neighbours.nearest against a full sort of every distance."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mapjoin import neighbours
from mapjoin.neighbours import nearest


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), points=st.integers(1, 30), candidates=st.integers(2, 30),
       k=st.integers(1, 4), itself=st.booleans(), block=st.sampled_from([1, 7, 1 << 22]))
def test_the_k_nearest_are_the_first_k_of_every_distance_sorted(seed, points, candidates, k, itself, block):
    """Whatever the block of rows, each point's k nearest candidates are the k smallest of its distances to all of
    them, computed here with numpy's hypot and a sort (itself left out when the candidates are the points)."""
    rng = np.random.default_rng(seed)
    c = rng.uniform(-50, 50, candidates) + 1j * rng.uniform(-50, 50, candidates)
    p = c if itself else rng.uniform(-50, 50, points) + 1j * rng.uniform(-50, 50, points)
    k = min(k, len(c) - int(itself))
    held, neighbours.BLOCK = neighbours.BLOCK, block
    try:
        index, squared = nearest(p, c, k, exclude=np.arange(len(p)) if itself else None)
    finally:
        neighbours.BLOCK = held
    distances = np.hypot((p[:, None] - c[None, :]).real, (p[:, None] - c[None, :]).imag)
    if itself:
        np.fill_diagonal(distances, np.inf)
    expected = np.sort(distances, axis=1)[:, :k]
    np.testing.assert_allclose(np.sort(np.sqrt(squared), axis=1), expected, rtol=1e-12)
    np.testing.assert_allclose(np.take_along_axis(distances, index, axis=1), np.sqrt(squared), rtol=1e-12)
