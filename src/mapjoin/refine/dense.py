"""Dense linear algebra for the normal equations of a small exact join: numpy's LAPACK, not scipy's sparse solvers.

A whole ``mapjoin refine`` of a few hundred unknowns spends more on importing scipy.sparse
than on its arithmetic; numpy, already loaded, solves such a system densely in
milliseconds. :data:`DENSE_UNKNOWNS` is the crossover, measured on whole commands
(benchmarks/README.md, "Start-up"); :func:`backend_for` chooses by it.

The normal matrix is assembled once, as the CSC data of :class:`.sparse.BlockPattern`
(taken in the natural node order for this backend); :func:`factorise` scatters its lower
triangle into a dense matrix. The Gauss-Newton and Levenberg-Marquardt steps of
docs/method.md#solver solve it by Cholesky, ``A = L L^T`` (LAPACK's ``potrf``, which reads
the lower triangle only), and two triangular solves (:mod:`.triangular`: numpy has none, so
they are matrix products by halves); the marginal covariances
(docs/method.md#marginal-covariances) are the diagonal blocks of ``A^-1 = L^-T L^-1``, the
column blocks of ``L^-1`` (:func:`.triangular.lower_inverse`) multiplied with themselves, never
the whole inverse. A matrix Cholesky refuses (a Newton step's, which may be indefinite) is
solved by LU with partial pivoting (``numpy.linalg.solve``) as before. Measured at VicPark 200's
1198 unknowns (one OpenBLAS thread): a step 21 ms against the LU solve's 32 ms, the marginals
48 ms against the whole inverse's 146 ms.

The Schur complement onto the poses (features eliminated first) is no cheaper here: the feature
block is not block-diagonal, because a local map's full covariance couples all its features
(VicPark 200: a feature couples with 51 others on average, DLR 200 with 18), so eliminating the
features is a dense factorisation of that block: measured as fast as the whole Cholesky, not
faster (benchmarks/README.md, "Start-up").
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

import numpy as np

from .triangular import lower_inverse, solve_lower, solve_lower_transposed

if TYPE_CHECKING:
    from .sparse import BlockPattern

__all__ = ["BACKENDS", "DENSE_UNKNOWNS", "Backend", "DenseFactor", "backend_for", "diagonal_blocks", "factorise"]

Backend = Literal["auto", "dense", "sparse"]
BACKENDS: tuple[str, ...] = ("auto", "dense", "sparse")

#: problems with at most this many unknowns are solved densely under ``auto``: on whole refines of the first
#: maps of VicPark 200 and DLR 200 (benchmarks/startup.py --crossover, OpenBLAS on one thread as the command
#: runs it) the dense backend took 0.43-0.65 of the sparse one's wall time up to 592 unknowns, 0.72-0.91 from
#: 652 to 762, as long at 958-988 and longer from 1128 (1.16 at VicPark 200's 1198, 2.8 at DLR 200's 1698):
#: below that, importing scipy costs more than the dense arithmetic. (The first measurement, 150, had
#: OpenBLAS's two threads contending with a loaded machine.) A confirmation's solves take the whole chain's
#: backend (:func:`mapjoin.confirmation.chain_backend`).
DENSE_UNKNOWNS = 800


def backend_for(backend: Backend, unknowns: int) -> Literal["dense", "sparse"]:
    """The linear algebra of a problem of ``unknowns`` unknowns: ``backend`` itself, or under ``auto``
    dense up to :data:`DENSE_UNKNOWNS` and sparse beyond."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if backend == "auto":
        return "dense" if unknowns <= DENSE_UNKNOWNS else "sparse"
    return backend


class DenseFactor:
    """The normal matrix ``A`` of a step, dense (natural order), factorised: its Cholesky factor ``L``
    (lower), or None where Cholesky refused (``A`` not positive definite, as a Newton step's may be) and
    :meth:`solve` takes LU with partial pivoting instead. ``matrix``: ``A``'s lower triangle (zeros above)."""

    def __init__(self, matrix: np.ndarray):
        self.matrix = matrix
        try:
            self.cholesky: np.ndarray | None = np.linalg.cholesky(matrix)
        except np.linalg.LinAlgError:
            self.cholesky = None

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``A^-1 rhs``; RuntimeError if ``A`` is exactly singular (as SuperLU's factor raises)."""
        L = self.cholesky
        if L is not None:
            return solve_lower_transposed(L, solve_lower(L, rhs))
        try:
            return np.linalg.solve(_mirrored(self.matrix), rhs)
        except np.linalg.LinAlgError:
            raise RuntimeError("the normal matrix is exactly singular") from None


def _mirrored(lower: np.ndarray) -> np.ndarray:
    """The symmetric matrix whose lower triangle is ``lower``'s."""
    return np.tril(lower) + np.tril(lower, -1).T


def factorise(pattern: BlockPattern, data: np.ndarray) -> DenseFactor:
    """The dense factor of the symmetric matrix whose lower triangle is the CSC ``data`` of ``pattern`` (built in
    the natural node order, so that ``pattern.position`` is the identity; the slots above the diagonal are
    not read)."""
    n = pattern.n
    columns = np.repeat(np.arange(n), np.diff(pattern.indptr))
    lower = pattern.indices >= columns
    matrix = np.zeros((n, n))
    matrix[pattern.indices[lower], columns[lower]] = data[lower]
    return DenseFactor(matrix)


def diagonal_blocks(factor: DenseFactor, blocks: list[np.ndarray]) -> list[np.ndarray]:
    """Diagonal blocks of ``A^-1`` for each (k, s) array of unknowns in ``blocks``: (k, s, s) each. With the
    Cholesky factor, block ``b`` is ``L^-1[:, b]^T L^-1[:, b]`` (``A^-1 = L^-T L^-1``); else (``A`` not
    positive definite) from the whole inverse. Symmetrised: a covariance written as its upper triangle (CSV)
    must read back equal to one written whole (JSON, YAML)."""
    if factor.cholesky is None:
        inverse = np.linalg.inv(_mirrored(factor.matrix))
        found = [inverse[b[:, :, None], b[:, None, :]] for b in blocks]
    else:
        inverse = lower_inverse(factor.cholesky)
        found = []
        for b in blocks:
            columns = inverse[:, b]                  # (n, k, s)
            found.append(np.einsum("rki,rkj->kij", columns, columns))
    return [(f + f.transpose(0, 2, 1)) / 2 for f in found]
