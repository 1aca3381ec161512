"""Triangular solves and the triangular inverse in numpy, which has neither (they are scipy.linalg's).

The dense backend (:mod:`.dense`) factorises the normal matrix by Cholesky, ``A = L L^T``, and then needs
``L^-1 b``, ``L^-T y`` (a step, the separator's rows of the factor) and ``L^-1`` itself (the marginal covariances,
docs/method.md#marginal-covariances). All three are written by blocks of :data:`BLOCK` unknowns,
``L = [[D_1, 0, ...], [L_21, D_2, 0, ...], ...]``, with the diagonal blocks' inverses ``D_j^-1`` made once per
matrix (:class:`Triangle`; :func:`block_inverses`, all blocks of several matrices inverted as one stack by
:func:`lower_inverses`, which also whitens the maps' covariances, :mod:`.groups`):

* ``L^-1 b``: ``x_j = D_j^-1 (b_j - sum_{i<j} L_ji x_i)``, block row by block row; ``L^-T y`` the same from the
  bottom, with the transposed blocks;
* ``L^-1``: by halves at a block boundary, ``[[L11, 0], [L21, L22]]^-1 = [[L11^-1, 0], [-L22^-1 L21 L11^-1,
  L22^-1]]``, down to single blocks, whose inverses are there.

All other work is matrix products, numpy's fastest kernel: the inverse costs ``n^3 / 3`` flops, as LAPACK's
``trtri``, where ``numpy.linalg.inv`` of the whole matrix takes ``2 n^3``. A block's inverse and a product,
rather than numpy's LU solve of each block (``numpy.linalg.solve``: a factorisation and two substitutions at
every solve), and a loop over block rows rather than recursive halving of a solve: measured at the dense
backend's sizes (2026-11-26, one OpenBLAS thread, load 1), 315 unknowns and 337 right-hand sides 1.1 ms
against the halving's 2.5 with LU leaves of 64, one right-hand side 0.04 ms (546 unknowns: 0.08) against 0.35
(0.57); the blocks' inverses once per factor, 0.35 ms for 39 blocks (numpy's stacked LU inverse: 0.64).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["BLOCK", "Triangle", "block_inverses", "lower_inverses"]

#: the unknowns of a diagonal block (the last one of a matrix may have fewer): 32 the fastest of 32, 64 and 128
#: measured for the dense backend's matrices (150-550 unknowns, 1-340 right-hand sides)
BLOCK = 32


def block_inverses(matrices: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Per lower triangular matrix (n, n) of ``matrices``: the inverses of its diagonal blocks of :data:`BLOCK`
    unknowns, (ceil(n / BLOCK), BLOCK, BLOCK), the last block (when n is no multiple of BLOCK) completed by the
    identity; lower triangular, exactly zero above the diagonal. All blocks of all matrices are inverted as one
    stack (:func:`lower_inverses`): a dense factor's interiors pay a few numpy calls, not a few per block."""
    m = BLOCK
    counts = [-(-len(L) // m) for L in matrices]
    blocks = np.zeros((sum(counts), m, m))
    blocks[:, np.arange(m), np.arange(m)] = 1.0                 # the identity where a last block ends early
    first = 0
    for L, count in zip(matrices, counts):
        n = len(L)
        full = n // m
        if full:
            rows = np.arange(full)[:, None] * m + np.arange(m)  # (full, m): each whole block's rows
            blocks[first:first + full] = L[rows[:, :, None], rows[:, None, :]]
        if full < count:
            blocks[first + full, :n - full * m, :n - full * m] = L[full * m:, full * m:]
        first += count
    inverses = lower_inverses(blocks) if len(blocks) else blocks
    return np.split(inverses, np.cumsum(counts)[:-1]) if counts else []


def lower_inverses(L: np.ndarray) -> np.ndarray:
    """Inverses of a stack of lower triangular matrices (G, d, d). Large ones (d >= 24) by
    halves: ``[[A, 0], [B, C]]^-1 = [[A^-1, 0], [-C^-1 B A^-1, C^-1]]``, the halves inverted
    the same way (0.3-0.6 of the time of LAPACK's general inverse, which does a full LU and
    its inverse, on stacks of 1000 to 10^4 matrices of 45-61 rows; benchmarks/README.md, "Time
    of refine at 10^4 maps"). Few small ones by LAPACK's solve (numpy's batched inverse) of the
    upper triangular transposes: partial pivoting finds nothing below the diagonal there, so
    no row moves and the factorisation leaves the matrix as it is. Many small ones row by
    row, the forward substitution vectorised over the stack. Each way keeps every zero block
    of the inverse exactly zero (as the pattern of J^T J, read from the information, needs);
    numpy's, so that a small exact join imports no scipy. The whitening of the maps' covariances
    (:mod:`.groups`) and the diagonal blocks of the dense backend's factors (:func:`block_inverses`)
    take their inverses here."""
    G, d = L.shape[0], L.shape[-1]
    if d >= 24:
        h = d // 2
        W = np.zeros_like(L)
        W[:, :h, :h] = lower_inverses(L[:, :h, :h])
        W[:, h:, h:] = lower_inverses(L[:, h:, h:])
        W[:, h:, :h] = -np.matmul(W[:, h:, h:], np.matmul(L[:, h:, :h], W[:, :h, :h]))
        return W
    if G < 4 * d:
        return np.linalg.inv(L.transpose(0, 2, 1)).transpose(0, 2, 1)
    W = np.zeros_like(L)
    reciprocal = 1.0 / np.diagonal(L, axis1=1, axis2=2)
    W[:, 0, 0] = reciprocal[:, 0]
    for j in range(1, d):
        W[:, j, :j] = np.matmul(L[:, j:j + 1, :j], W[:, :j, :j])[:, 0, :] * -reciprocal[:, j:j + 1]
        W[:, j, j] = reciprocal[:, j]
    return W


class Triangle:
    """A lower triangular matrix ``L`` (n, n) with ``inverses``, its diagonal blocks' (:func:`block_inverses`):
    what the solves with ``L`` and its inverse take. ``L`` is read, never written."""

    __slots__ = ("L", "inverses")

    def __init__(self, L: np.ndarray, inverses: np.ndarray):
        if L.ndim != 2 or L.shape[0] != L.shape[1] or len(inverses) != -(-len(L) // BLOCK):
            raise ValueError(f"a triangle of {L.shape} needs {-(-len(L) // BLOCK)} block inverses, got {len(inverses)}")
        self.L, self.inverses = L, inverses

    @classmethod
    def all_of(cls, matrices: Sequence[np.ndarray]) -> list[Triangle]:
        """Each lower triangular matrix of ``matrices`` with its blocks' inverses, made by one numpy call."""
        return [cls(L, inverses) for L, inverses in zip(matrices, block_inverses(matrices))]

    def _block(self, j: int, size: int) -> np.ndarray:
        """Block j's inverse, ``size`` rows (the last block's may be fewer than BLOCK)."""
        return self.inverses[j, :size, :size]

    def solve(self, b: np.ndarray, first: int = 0) -> np.ndarray:
        """``L^-1 b`` for ``b`` (n,) or (n, k), by forward substitution a block row at a time. With ``first``,
        ``b`` holds only the rows from ``first`` on, the rows before being zero, and so does the result (the
        rows before are zero in it too): the block rows before ``first``'s are skipped."""
        L, m = self.L, BLOCK
        n = len(L)
        start = first // m * m                          # the first block row not skipped
        if start < first:                                # its rows before first: zero
            b = np.concatenate([np.zeros((first - start, *b.shape[1:])), b])
        x = np.empty(b.shape)                           # rows start.. of the solution
        for j0 in range(start, n, m):
            j1 = min(j0 + m, n)
            rest = b[j0 - start:j1 - start]
            if j0 > start:
                rest = rest - L[j0:j1, start:j0] @ x[:j0 - start]
            x[j0 - start:j1 - start] = self._block(j0 // m, j1 - j0) @ rest
        return x[first - start:]

    def solve_transposed(self, y: np.ndarray) -> np.ndarray:
        """``L^-T y`` for ``y`` (n,) or (n, k), by back substitution a block row of ``L^T`` at a time."""
        L, m = self.L, BLOCK
        n = len(L)
        x = np.empty(y.shape)
        for j0 in range((n - 1) // m * m, -1, -m):
            j1 = min(j0 + m, n)
            rest = y[j0:j1] - L[j1:, j0:j1].T @ x[j1:] if j1 < n else y[j0:j1]
            x[j0:j1] = self._block(j0 // m, j1 - j0).T @ rest
        return x

    def inverse(self) -> np.ndarray:
        """``L^-1`` (lower triangular, exactly zero above the diagonal)."""
        out = np.zeros_like(self.L, dtype=float)
        if len(out):
            self._invert_into(0, len(out), out)
        return out

    def _invert_into(self, a: int, b: int, out: np.ndarray) -> None:
        """Write the inverse of ``L[a:b, a:b]`` (``a`` a block boundary) into ``out[a:b, a:b]``."""
        m = BLOCK
        blocks = -(-(b - a) // m)
        if blocks == 1:
            out[a:b, a:b] = self._block(a // m, b - a)
            return
        h = a + m * (blocks // 2)
        self._invert_into(a, h, out)
        self._invert_into(h, b, out)
        out[h:b, a:h] = -out[h:b, h:b] @ (self.L[h:b, a:h] @ out[a:h, a:h])
