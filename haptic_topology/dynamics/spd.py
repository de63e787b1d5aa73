"""Solves with a symmetric positive-definite matrix (the joint-space inertia ``D`` of eq. 1).

A Cholesky factor ``D = L L^T`` (LAPACK, through numpy) and two triangular solves, never an
explicit inverse. The triangular solves are compiled substitutions
(:func:`~haptic_topology.dynamics.compiled.cho_solve`): numpy has no triangular solve, and
its general ``solve`` factors the triangle again (LU with pivoting) at about 4 us of per-call
cost for the 3 x 3 to 6 x 6 systems of every LMI update. SciPy's ``cho_factor``/``cho_solve``
do the same but cost every node process a quarter of a second of import time.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

#: The compiled substitutions, loaded with the first solve (importing numba's cache costs a
#: process that never solves, e.g. a bag reader, about half a second).
_cho_solve: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None


def spd_factor(matrix: np.ndarray) -> np.ndarray:
    """The lower Cholesky factor ``L`` of ``matrix``; ``numpy.linalg.LinAlgError`` if the
    matrix is not positive definite."""
    return np.linalg.cholesky(matrix)


def spd_solve(factor: np.ndarray, rhs: Any) -> np.ndarray:
    """``X`` with ``L L^T X = rhs``, for ``factor = spd_factor(matrix)``; ``rhs`` a vector or
    a matrix of columns (n rows, as ``factor``)."""
    global _cho_solve
    if _cho_solve is None:
        from haptic_topology.dynamics.compiled import cho_solve
        _cho_solve = cho_solve
    b = np.asarray(rhs, dtype=float)
    n = factor.shape[0]
    if b.ndim not in (1, 2) or b.shape[0] != n:
        raise ValueError(f'spd_solve: rhs must have {n} rows (the factor is {n} x {n}), got '
                         f'shape {b.shape}')
    if b.ndim == 1:
        return _cho_solve(factor, b.reshape(n, 1)).reshape(n)
    return _cho_solve(factor, b)
