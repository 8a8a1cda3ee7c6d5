"""Sparse symmetric positive-definite solves for the chordal solver and initialisation.

scipy ships no sparse Cholesky; SuperLU (``scipy.sparse.linalg.splu``) with the symmetric minimum-degree
ordering on AᵀA+A (``MMD_AT_PLUS_A``) and diagonal pivoting (``diag_pivot_thresh=0``, valid for SPD
matrices) behaves like a sparse LDLᵀ and was the fastest scipy option measured in
``benchmarks/solvers.py`` (see slam/graph/README.md for the figures).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from core.errors import GpslamError

__all__ = ["spd_solve", "spd_factor", "SOLVERS", "SingularSystemError"]

SOLVERS = ("splu_mmd", "splu_colamd", "spsolve")


class SingularSystemError(GpslamError, ValueError):
    """The normal equations are singular: the graph is disconnected or the gauge is not fixed."""


def spd_solve(H: sp.spmatrix, B: NDArray[np.float64], method: str = "splu_mmd") -> NDArray[np.float64]:
    """Solve ``H X = B`` for a sparse SPD *H* (``(n, n)``) and one or more right-hand sides *B*."""
    H = sp.csc_matrix(H)
    try:
        if method == "splu_mmd":
            lu = spla.splu(H, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                           options={"SymmetricMode": True})
            return lu.solve(np.asarray(B, dtype=float))
        if method == "splu_colamd":
            return spla.splu(H, permc_spec="COLAMD").solve(np.asarray(B, dtype=float))
        if method == "spsolve":
            X = spla.spsolve(H, B)
            return np.asarray(X).reshape(np.shape(B))
    except RuntimeError as exc:  # SuperLU: "Factor is exactly singular"
        raise SingularSystemError(f"singular normal equations ({exc}); is the graph connected?") from None
    raise ValueError(f"unknown sparse solver {method!r}; expected one of {SOLVERS}")


def spd_factor(H: sp.spmatrix, method: str = "splu_mmd", natural: bool = False):  # type: ignore[no-untyped-def]
    """Factorise a sparse SPD *H* once; the result has ``.solve(B)`` and ``.perm_c``.

    *natural*: *H* is already in a fill-reducing order (keep it: no new ordering is computed).
    """
    H = sp.csc_matrix(H)
    try:
        if natural:
            return spla.splu(H, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        if method == "splu_colamd":
            return spla.splu(H, permc_spec="COLAMD")
        return spla.splu(H, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    except RuntimeError as exc:
        raise SingularSystemError(f"singular normal equations ({exc}); is the graph connected?") from None
