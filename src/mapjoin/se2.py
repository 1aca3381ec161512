"""SE(2) arithmetic: poses ``(x, y, phi)`` of a robot in the plane, and points seen from them.

A pose ``r = (t, phi)`` maps a point ``z`` of its own frame to ``t + R(phi) z`` in its parent
frame (docs/method.md#notation); the one-step problem's r1 is such a pose in the frame of r0.
Every function works on one pose or on arrays of them: the last axis holds ``(x, y, phi)``
(poses) or ``(x, y)`` (points) and the leading axes broadcast.

:func:`compose` and :func:`relative` leave the angle unwrapped (``phi1 + phi2``,
``phi - phi0``): callers that need the canonical range apply :func:`wrap`.
"""

from __future__ import annotations

import math
from typing import overload

import numpy as np

__all__ = ["compose", "relative", "rotation", "to_frame", "transform", "wrap"]


@overload
def wrap(angle: float) -> float: ...
@overload
def wrap(angle: np.ndarray) -> np.ndarray: ...
def wrap(angle):
    """Map angles (a float or an array) into [-pi, pi): the orientation residual of Theorem 1's link term.

    ``(angle + pi) % 2pi`` can round up to exactly 2pi for angles just below -pi; those are
    moved down by 2pi so that the result stays below pi.
    """
    wrapped = (angle + math.pi) % (2 * math.pi) - math.pi
    if isinstance(wrapped, float):
        return wrapped - 2 * math.pi if wrapped >= math.pi else wrapped
    return np.where(wrapped >= math.pi, wrapped - 2 * math.pi, wrapped)


def rotation(phi: float | np.ndarray) -> np.ndarray:
    """R(phi) = [[cos, -sin], [sin, cos]]: shape (2, 2) for one angle, (..., 2, 2) for an array."""
    c, s = np.cos(phi), np.sin(phi)
    return np.stack([np.stack([c, -s], axis=-1), np.stack([s, c], axis=-1)], axis=-2)


def transform(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points given in the frame of ``pose``, expressed in the pose's parent frame: ``t + R(phi) z``."""
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    x, y = points[..., 0], points[..., 1]
    return np.stack([pose[..., 0] + (c * x - s * y), pose[..., 1] + (s * x + c * y)], axis=-1)


def to_frame(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points of the parent frame seen from ``pose``: ``R(phi)^T (z - t)``, the inverse of :func:`transform`."""
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    dx, dy = points[..., 0] - pose[..., 0], points[..., 1] - pose[..., 1]
    return np.stack([c * dx + s * dy, c * dy - s * dx], axis=-1)


def compose(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """``first ⊕ second``: pose ``second``, given in the frame of ``first``, in ``first``'s parent frame."""
    xy = transform(first, second[..., :2])
    return np.concatenate([xy, (first[..., 2] + second[..., 2])[..., None]], axis=-1)


def relative(origin: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """``origin ⊖ poses``: ``poses`` (parent frame) expressed in the frame of ``origin``; inverse of :func:`compose`."""
    xy = to_frame(origin, poses[..., :2])
    return np.concatenate([xy, (poses[..., 2] - origin[..., 2])[..., None]], axis=-1)
