"""Triangular solves and the triangular inverse in numpy, which has neither (they are scipy.linalg's).

The dense backend (:mod:`.dense`) factorises the normal matrix by Cholesky, ``A = L L^T``, and then needs
``L^-1 b``, ``L^-T y`` (a step) and ``L^-1`` itself (the marginal covariances, docs/method.md#marginal-covariances).
Both are written by recursive halving, ``L = [[L11, 0], [L21, L22]]``:

* ``L^-1 b``: ``x1 = L11^-1 b1``, ``x2 = L22^-1 (b2 - L21 x1)``; ``L^-T y`` the same from the bottom;
* ``L^-1 = [[L11^-1, 0], [-L22^-1 L21 L11^-1, L22^-1]]``,

down to blocks of at most :data:`LEAF` unknowns, which numpy's LU solve (``numpy.linalg.solve``) finishes at no
cost worth counting (the inverse's entries above the diagonal, zero but for rounding, are cleared). All other work is
matrix products, numpy's fastest kernel: the inverse costs ``n^3 / 3`` flops, as LAPACK's ``trtri``, where
``numpy.linalg.inv`` of the whole matrix takes ``2 n^3`` (measured at 1198 unknowns, one OpenBLAS thread:
Cholesky and this inverse 48 ms against ``inv``'s 146 ms; benchmarks/README.md, "Start-up").
"""

from __future__ import annotations

import numpy as np

__all__ = ["LEAF", "lower_inverse", "solve_lower", "solve_lower_transposed"]

#: the largest block solved by numpy's LU directly (above it, halving: the products dominate)
LEAF = 64


def solve_lower(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``L^-1 b`` for a lower triangular ``L`` (n, n) and ``b`` (n,) or (n, k): forward substitution by halves."""
    n = L.shape[0]
    if n <= LEAF:
        return np.linalg.solve(L, b)
    h = n // 2
    x1 = solve_lower(L[:h, :h], b[:h])
    return np.concatenate([x1, solve_lower(L[h:, h:], b[h:] - L[h:, :h] @ x1)])


def solve_lower_transposed(L: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``L^-T y`` for a lower triangular ``L`` (n, n) and ``y`` (n,) or (n, k): back substitution by halves."""
    n = L.shape[0]
    if n <= LEAF:
        return np.linalg.solve(L.T, y)
    h = n // 2
    x2 = solve_lower_transposed(L[h:, h:], y[h:])
    return np.concatenate([solve_lower_transposed(L[:h, :h], y[:h] - L[h:, :h].T @ x2), x2])


def lower_inverse(L: np.ndarray) -> np.ndarray:
    """``L^-1`` (lower triangular, zeros above the diagonal) of a lower triangular ``L`` (n, n)."""
    inverse = np.zeros_like(L, dtype=float)
    _invert_into(L, inverse)
    return inverse


def _invert_into(L: np.ndarray, out: np.ndarray) -> None:
    """Write ``L^-1`` into ``out`` (a view of the same shape, zero above the diagonal)."""
    n = L.shape[0]
    if n <= LEAF:
        out[...] = np.tril(np.linalg.solve(L, np.eye(n)))
        return
    h = n // 2
    _invert_into(L[:h, :h], out[:h, :h])
    _invert_into(L[h:, h:], out[h:, h:])
    out[h:, :h] = -out[h:, h:] @ (L[h:, :h] @ out[:h, :h])
