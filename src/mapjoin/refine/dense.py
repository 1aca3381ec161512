"""Dense linear algebra for the normal equations of a small exact join: numpy's LAPACK, not scipy's sparse solvers.

A whole ``mapjoin refine`` of a few hundred unknowns spends more on importing scipy.sparse
than on its arithmetic; numpy, already loaded, solves such a system densely in
milliseconds. :data:`DENSE_UNKNOWNS` is the crossover, measured on whole commands
(benchmarks/README.md, "Start-up"); :func:`backend_for` chooses by it.

The normal matrix is assembled once, as the CSC data of :class:`.sparse.BlockPattern`
(taken in the natural node order for this backend); :func:`factorise` scatters it into a
dense matrix. The Gauss-Newton, Levenberg-Marquardt and Newton steps of
docs/method.md#solver solve it by LU with partial pivoting (``numpy.linalg.solve``: the
matrix of a Newton step may be indefinite), and the marginal covariances
(docs/method.md#marginal-covariances) are the diagonal blocks of its inverse. Cholesky would not
save time here: numpy has no triangular solve, so a Cholesky solve or inverse needs general LU
solves with the factor on top of the factorisation (measured slower at 300-1198 unknowns,
benchmarks/README.md, "Start-up").
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

import numpy as np

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
    """The normal matrix ``A`` of a step, dense (natural order): :meth:`solve` factorises and solves
    it in one LAPACK call, which is all a step needs (one right-hand side)."""

    def __init__(self, matrix: np.ndarray):
        self.matrix = matrix

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``A^-1 rhs``; RuntimeError if ``A`` is exactly singular (as SuperLU's factor raises)."""
        try:
            return np.linalg.solve(self.matrix, rhs)
        except np.linalg.LinAlgError:
            raise RuntimeError("the normal matrix is exactly singular") from None


def factorise(pattern: BlockPattern, data: np.ndarray) -> DenseFactor:
    """The dense factor of the matrix whose CSC ``data`` has ``pattern`` (built in the natural node order,
    so that ``pattern.position`` is the identity)."""
    n = pattern.n
    columns = np.repeat(np.arange(n), np.diff(pattern.indptr))
    matrix = np.zeros((n, n))
    matrix[pattern.indices, columns] = data
    return DenseFactor(matrix)


def diagonal_blocks(factor: DenseFactor, blocks: list[np.ndarray]) -> list[np.ndarray]:
    """Diagonal blocks of ``A^-1`` for each (k, s) array of unknowns in ``blocks``: (k, s, s) each, from the
    whole inverse (what a selected inversion avoids for large problems costs little here), symmetrised: an
    LU inverse is symmetric only to rounding, and a covariance written as its upper triangle (CSV) must read
    back equal to one written whole (JSON, YAML)."""
    inverse = np.linalg.inv(factor.matrix)
    inverse = (inverse + inverse.T) / 2
    return [inverse[b[:, :, None], b[:, None, :]] for b in blocks]
