"""The factor ``L D L^T`` of the normal matrix (SuperLU), which hands its triangle over once and frees itself.

SuperLU (scipy) factorises J^T J in the order given (the fill-reducing node order of
:func:`.sparse.fill_reducing_order`), in symmetric mode with the diagonal as pivots: ``L U``
with ``U = D L^T``, both triangles stored. :meth:`Factor.triangle` hands the selected
inversion (:func:`.sparse.diagonal_blocks`) the unit lower triangle and D, and frees the
factor's own storage first: at the optimum of a large problem the factor, copies of its
triangle and the inversion's blocks used to be held at once (benchmarks/README.md, "Memory
of refine at 10⁴ maps"). CHOLMOD's supernodal Cholesky was measured against it there and
not adopted: no faster and no smaller on these problems.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import scipy.sparse as sp

__all__ = ["SYMMETRIC_MODE", "Factor", "factorise"]

#: SuperLU's options for a symmetric matrix whose diagonal needs no pivot exchange
SYMMETRIC_MODE = {"diag_pivot_thresh": 0.0, "options": {"SymmetricMode": True}}


class Factor:
    """``A = L D L^T`` of a symmetric matrix by SuperLU: :meth:`solve` and, once, :meth:`triangle`.
    ``perm``: the order SuperLU factorised in (the identity unless it was asked for another)."""

    def __init__(self, lu):
        self._lu = lu
        self.perm = np.asarray(lu.perm_c)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``A^-1 rhs`` (a vector or a matrix of columns, in A's order)."""
        if self._lu is None:
            raise ValueError("the factor was handed over to the selected inversion (Factor.triangle)")
        return self._lu.solve(rhs)

    def triangle(self) -> tuple[sp.csc_matrix, np.ndarray]:
        """``(L, D)``: the unit lower triangle (CSC, its diagonal included) and the pivots, in the factor's
        order; SuperLU's own L and U are freed, so the factor can neither solve nor give them again."""
        lu, self._lu = self._lu, None
        if lu is None:
            raise ValueError("the factor was handed over already")
        if not np.array_equal(lu.perm_r, lu.perm_c):
            raise np.linalg.LinAlgError("SuperLU pivoted: not a symmetric factorisation")
        D = lu.U.diagonal()        # U = D L^T: its diagonal (U's copy freed before L's is made)
        L = lu.L
        return L, D


def factorise(matrix: sp.csc_matrix, permc_spec: str = "NATURAL") -> Factor:
    """The factor of the symmetric ``matrix`` (CSC, both triangles) in its given order (or SuperLU's
    ``permc_spec``); RuntimeError if it is exactly singular."""
    from scipy.sparse.linalg import splu  # on use: a small problem's dense backend (.dense) needs no scipy

    return Factor(splu(matrix, permc_spec=permc_spec, **SYMMETRIC_MODE))
