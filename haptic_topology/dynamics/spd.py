"""Solves with a symmetric positive-definite matrix (the joint-space inertia ``D`` of eq. 1).

A Cholesky factor ``D = L L^T`` and two triangular solves, never an explicit inverse. numpy
only: SciPy's ``cho_factor``/``cho_solve`` do the same but cost every node process a quarter of
a second of import time.
"""

from __future__ import annotations

import numpy as np


def spd_factor(matrix: np.ndarray) -> np.ndarray:
    """The lower Cholesky factor ``L`` of ``matrix``; ``numpy.linalg.LinAlgError`` if the
    matrix is not positive definite."""
    return np.linalg.cholesky(matrix)


def spd_solve(factor: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``X`` with ``L L^T X = rhs``, for ``factor = spd_factor(matrix)``; ``rhs`` a vector or
    a matrix of columns."""
    return np.linalg.solve(factor.T, np.linalg.solve(factor, rhs))
