"""The factor ``L D L^T`` of the normal matrix, by CHOLMOD when it is installed, else by SuperLU.

Both factorise the matrix in the order it is given (the fill-reducing node order of
:func:`.sparse.fill_reducing_order`, postordered for supernodes), without pivoting:

* CHOLMOD (SuiteSparse, through scikit-sparse: the optional extra ``fast``), supernodal
  ``L L^T``, its symbolic analysis done once per pattern (:class:`Factoriser`). It stores
  one triangle and factorises a 10^4-map problem 1.5-3x faster than SuperLU
  (benchmarks/README.md, "Memory of refine at 10^4 maps"). It takes only positive definite
  matrices: a Newton matrix (J^T J plus the second-order term) that is not is refused as
  singular, and the solver falls back to Gauss-Newton's step for it.
* SuperLU (scipy), in symmetric mode with the diagonal as pivots: ``L U`` with ``U = D L^T``
  (both triangles stored), for any nonsingular matrix whose pivots need no exchange.

:meth:`Factor.triangle` hands the selected inversion (:func:`.sparse.diagonal_blocks`) the
unit lower triangle and D, and frees the factor's own storage first: at the optimum of a
large problem the factor, its triangle and the inversion's blocks would otherwise be held
at once.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Callable

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

__all__ = ["BACKENDS", "CHOLMOD_FROM", "Factor", "Factoriser", "default_backend"]

#: the backends, in order of preference
BACKENDS = ("cholmod", "superlu")
#: unknowns from which CHOLMOD is used when installed: below, importing it (about 0.1 s) costs more than it saves
CHOLMOD_FROM = 20_000
_SUPERLU = {"diag_pivot_thresh": 0.0, "options": {"SymmetricMode": True}}


def default_backend(unknowns: int) -> str:
    """CHOLMOD for problems of at least :data:`CHOLMOD_FROM` unknowns when scikit-sparse is installed, else SuperLU."""
    if unknowns >= CHOLMOD_FROM and importlib.util.find_spec("sksparse") is not None:
        return "cholmod"
    return "superlu"


class Factor:
    """``A = L D L^T`` of a matrix in its own order (``perm``: the order the backend used, the identity unless
    SuperLU was given another one): :meth:`solve` and, once, :meth:`triangle`."""

    def __init__(self, solve: Callable[[np.ndarray], np.ndarray], triangle: Callable[[], tuple],
                 perm: np.ndarray):
        self._solve, self._triangle, self.perm = solve, triangle, perm

    @classmethod
    def of_superlu(cls, lu) -> Factor:
        """A SuperLU factor in symmetric mode (``lu.perm_r`` must equal ``lu.perm_c``: no pivoting)."""
        holder = [lu]

        def triangle() -> tuple[sp.csc_matrix, np.ndarray]:
            lu = holder.pop()
            if not np.array_equal(lu.perm_r, lu.perm_c):
                raise np.linalg.LinAlgError("SuperLU pivoted: not a symmetric factorisation")
            D = lu.U.diagonal()        # U = D L^T: its diagonal, U's copy freed before L's is made
            L = lu.L
            del lu                     # SuperLU's own L and U
            return L, D

        return cls(lambda rhs: holder[0].solve(rhs), triangle, np.asarray(lu.perm_c))

    @classmethod
    def of_cholmod(cls, factor) -> Factor:
        """A CHOLMOD factor ``L L^T`` (scikit-sparse); its order ``P()`` is the natural one unless CHOLMOD
        postordered it differently."""
        holder = [factor]

        def triangle() -> tuple[sp.csc_matrix, np.ndarray]:
            L = holder.pop().L()       # the factor's storage freed on return
            L = sp.csc_matrix((L.data, L.indices, L.indptr), shape=L.shape)
            root = L.diagonal()
            L.data /= np.repeat(root, np.diff(L.indptr))   # unit diagonal: L D L^T with D = root^2
            return L, root * root

        return cls(lambda rhs: holder[0].solve_A(rhs), triangle, np.asarray(factor.P()))

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``A^-1 rhs`` (a vector or a matrix of columns, in A's order)."""
        return self._solve(rhs)

    def triangle(self) -> tuple[sp.csc_matrix, np.ndarray]:
        """``(L, D)``: the unit lower triangle (CSC, the diagonal included, possibly explicit zeros) and the
        pivots, in the factor's order; the factor can neither solve nor give them again after this."""
        return self._triangle()


class Factoriser:
    """Factorises matrices of one sparsity pattern with ``backend`` (:data:`BACKENDS`; None:
    :func:`default_backend`): CHOLMOD's symbolic analysis is made at the first matrix and kept."""

    def __init__(self, backend: str | None = None):
        if backend is not None and backend not in BACKENDS:
            raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
        self.backend = backend
        self._analysis = None

    def reads_lower(self, n: int) -> bool:
        """Whether the factorisation of an n x n matrix reads only its lower triangle (CHOLMOD: the slots above
        the diagonal may hold anything)."""
        return (self.backend or default_backend(n)) == "cholmod"

    def __call__(self, matrix: sp.csc_matrix) -> Factor:
        """The factor of the symmetric ``matrix`` (CSC; both triangles, or the lower one where
        :meth:`reads_lower`) in its given order; RuntimeError if it is singular (CHOLMOD: not positive
        definite)."""
        backend = self.backend or default_backend(matrix.shape[0])
        if backend == "superlu":
            return Factor.of_superlu(splu(matrix, permc_spec="NATURAL", **_SUPERLU))
        from sksparse.cholmod import CholmodError, analyze   # the optional extra: imported on use

        try:
            if self._analysis is None:
                self._analysis = analyze(matrix, mode="supernodal", ordering_method="natural")
            return Factor.of_cholmod(self._analysis.cholesky(matrix))
        except CholmodError as error:
            raise RuntimeError(f"CHOLMOD: {error}") from None
