"""The faults injected into chains (mapjoin.faults): each changes exactly the value it names, in the map it names."""

from __future__ import annotations

import numpy as np
import pytest

from mapjoin.faults import FAULTS, corrupted
from mapjoin.simulation import simulate


@pytest.fixture(scope="module")
def chain():
    return list(simulate(12, seed=3).maps)


@pytest.mark.parametrize("fault", FAULTS)
@pytest.mark.parametrize("k", [1, 5, 11])
def test_only_map_k_changes_and_only_in_the_named_value(chain, fault, k):
    changed, number = corrupted(chain, k, fault)
    assert len(changed) == len(chain)
    assert all(a is b for i, (a, b) in enumerate(zip(chain, changed)) if i != k)
    before, after = chain[k], changed[k]
    earlier = np.concatenate([m.feature_ids for m in chain[:k]])
    common = [i for i, fid in enumerate(before.feature_ids) if fid in set(earlier.tolist())]
    if fault == "heading":
        assert number == k + 1
        np.testing.assert_allclose(after.end_pose - before.end_pose, [0.0, 0.0, 0.6], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(after.features, before.features)
        np.testing.assert_array_equal(after.feature_ids, before.feature_ids)
        return
    assert number == k
    np.testing.assert_array_equal(after.end_pose, before.end_pose)
    if fault == "feature":
        moved = np.flatnonzero(np.any(after.features != before.features, axis=1))
        assert moved.tolist() == [common[0]]
        np.testing.assert_allclose(after.features[moved[0]] - before.features[moved[0]], [5.0, 0.0])
        np.testing.assert_array_equal(after.feature_ids, before.feature_ids)
    else:
        swapped = np.flatnonzero(after.feature_ids != before.feature_ids)
        other = (common[0] + 1) % len(before.feature_ids)
        assert sorted(swapped.tolist()) == sorted({common[0], other})
        assert sorted(after.feature_ids.tolist()) == sorted(before.feature_ids.tolist())
        np.testing.assert_array_equal(after.features, before.features)


def test_bad_requests_are_refused(chain):
    with pytest.raises(ValueError, match="fault must be one of"):
        corrupted(chain, 1, "rotate")
    for k in (0, len(chain), -1):
        with pytest.raises(ValueError, match="k must be"):
            corrupted(chain, k, "heading")
