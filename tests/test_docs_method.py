"""The variance propagation of ``docs/method.md#variance-propagation`` against the one-step Hessian.

Independent reference: the cost ``F(f, t, phi)`` of ``docs/method.md#one-step-problem``
written out term by term, its Hessian by central finite differences at the joined
optimum, and the covariance ``(Hessian / 2)^-1`` (F is twice the negative
log-likelihood). A two-map sequential join must report, for the joined pose, the heading
variance and half the trace of the position block of that covariance; a feature of the
second map seen only there gets ``var_t + var_z + |z|^2 var_phi / 2``, which differs from
the exact first-order value ``1/W + var_z + |z - m1|^2 var_phi / 2`` by ``(z . m1) var_phi``
(the t-phi correlation the placement leaves out), as the page says.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapjoin import LocalMap
from mapjoin.joining import join_sequential


def _rot(phi: float) -> np.ndarray:
    return np.array([[math.cos(phi), -math.sin(phi)], [math.sin(phi), math.cos(phi)]])


def _two_maps(seed: int):
    """Map 1 (origin to pose 1) and map 2 (pose 1 to pose 2), noisy, sharing ``common`` features."""
    rng = np.random.default_rng(seed)
    common, own = 5, 3
    truth = rng.uniform(-6, 6, (common + 2 * own, 2))
    pose1 = np.array([*rng.uniform(-2, 2, 2), rng.uniform(-1, 1)])
    pose2_local = np.array([*rng.uniform(-2, 2, 2), rng.uniform(-1, 1)])
    ids1 = np.arange(common + own)  # the first ``common`` ids are seen by both maps
    ids2 = np.r_[np.arange(common), np.arange(common + own, common + 2 * own)]
    var1 = rng.uniform(0.05, 0.5, len(ids1))
    var2 = rng.uniform(0.05, 0.5, len(ids2))
    z1 = truth[ids1] + rng.normal(size=(len(ids1), 2)) * np.sqrt(var1)[:, None]
    z2 = (truth[ids2] - pose1[:2]) @ _rot(pose1[2]) + rng.normal(size=(len(ids2), 2)) * np.sqrt(var2)[:, None]
    pose_var1 = np.array([rng.uniform(0.05, 0.5), rng.uniform(0.005, 0.05)])
    end1 = pose1 + rng.normal(size=3) * np.sqrt(pose_var1[[0, 0, 1]])
    map1 = LocalMap("m1", 0, 1, end1, ids1, z1, var1, pose_var1)
    map2 = LocalMap("m2", 1, 2, pose2_local, ids2, z2, var2, np.array([0.1, 0.01]))
    return map1, map2, common


def _hessian(fun, x: np.ndarray, step: float = 1e-4) -> np.ndarray:
    size = len(x)
    hessian = np.zeros((size, size))
    unit = np.eye(size) * step
    for i in range(size):
        for j in range(i, size):
            value = (fun(x + unit[i] + unit[j]) - fun(x + unit[i] - unit[j])
                     - fun(x - unit[i] + unit[j]) + fun(x - unit[i] - unit[j])) / (4 * step * step)
            hessian[i, j] = hessian[j, i] = value
    return hessian


@pytest.mark.parametrize("seed", range(8))
def test_two_map_join_variances_follow_the_one_step_hessian(seed):
    map1, map2, n = _two_maps(seed)
    z0, var0 = map1.features[:n], map1.feature_variances[:n]
    z1, var1 = map2.features[:n], map2.feature_variances[:n]
    o_xy, z_phi = map1.end_pose[:2], map1.end_pose[2]
    var_o, p_phi = map1.pose_variances

    def cost(x: np.ndarray) -> float:  # F of the one-step problem, term by term
        f, t, phi = x[:2 * n].reshape(n, 2), x[2 * n:2 * n + 2], x[-1]
        turned = z1 @ _rot(phi).T
        wrapped = (z_phi - phi + math.pi) % (2 * math.pi) - math.pi
        return float((((z0 - f) ** 2).sum(1) / var0).sum() + (((turned - (f - t)) ** 2).sum(1) / var1).sum()
                     + ((o_xy - t) ** 2).sum() / var_o + wrapped**2 / p_phi)

    joined = join_sequential([map1, map2], covariance="marginal").global_map
    feature_row = {int(i): r for r, i in enumerate(joined.feature_ids)}
    pose_row = {int(i): r for r, i in enumerate(joined.pose_ids)}
    t_star, phi_star = joined.poses[pose_row[1], :2], joined.poses[pose_row[1], 2]
    f_star = joined.features[[feature_row[int(i)] for i in map2.feature_ids[:n]]]
    x_star = np.r_[f_star.ravel(), t_star, phi_star]

    covariance = np.linalg.inv(_hessian(cost, x_star) / 2)
    var_phi = covariance[-1, -1]
    var_t = np.trace(covariance[2 * n:2 * n + 2, 2 * n:2 * n + 2]) / 2
    assert joined.pose_variances[pose_row[1], 1] == pytest.approx(var_phi, rel=1e-5)
    assert joined.pose_variances[pose_row[1], 0] == pytest.approx(var_t, rel=1e-5)

    # the weighted pairs of docs/method.md#weighted-sums: W and m1
    weights = np.r_[1 / (var0 + var1), 1 / var_o]
    total = weights.sum()
    m1 = (weights[:n, None] * z1).sum(0) / total
    assert var_t == pytest.approx(1 / total + (m1 @ m1) * var_phi / 2, rel=1e-5)

    tp = covariance[2 * n:, 2 * n:]  # (t, phi) block
    turn = _rot(phi_star + math.pi / 2)
    for z, var_z, feature_id in zip(map2.features[n:], map2.feature_variances[n:], map2.feature_ids[n:]):
        jacobian = np.c_[np.eye(2), turn @ z]  # d(t + R(phi) z) / d(t, phi)
        exact = np.trace(jacobian @ tp @ jacobian.T) / 2 + var_z
        assert exact == pytest.approx(1 / total + var_z + ((z - m1) @ (z - m1)) * var_phi / 2, rel=1e-5)
        reported = joined.feature_variances[feature_row[int(feature_id)]]
        code_t, code_phi = joined.pose_variances[pose_row[1]]  # the join's own var_t, var_phi
        assert reported == pytest.approx(code_t + var_z + (z @ z) * code_phi / 2, rel=1e-12)
        assert reported - exact == pytest.approx((z @ m1) * var_phi, rel=1e-4, abs=1e-9)
