"""``dynamics.spd``: solves with the joint-space inertia through its Cholesky factor, the
triangular solves compiled."""

from __future__ import annotations

import numpy as np
import pytest

from haptic_topology.dynamics.spd import spd_factor, spd_solve


@pytest.mark.parametrize('n', [1, 3, 6, 100])
def test_spd_solve_solves_vectors_and_columns_in_any_layout(n: int) -> None:
    rng = np.random.default_rng(n)
    a = rng.normal(size=(n, n))
    d = a @ a.T + n * np.eye(n)
    factor = spd_factor(d)
    b = rng.normal(size=n)
    cols = rng.normal(size=(6, n)).T            # a transposed view, as J_h^T
    x = spd_solve(factor, b)
    xs = spd_solve(factor, cols)
    assert x.shape == (n,) and xs.shape == (n, 6)
    np.testing.assert_allclose(d @ x, b, rtol=0, atol=1e-12 * np.abs(b).max() * n)
    np.testing.assert_allclose(d @ xs, cols, rtol=0, atol=1e-12 * np.abs(cols).max() * n)
    # Column by column the same numbers as a single column, and a list is taken as a vector.
    np.testing.assert_array_equal(xs[:, 2], spd_solve(factor, cols[:, 2].copy()))
    np.testing.assert_array_equal(spd_solve(factor, b.tolist()), x)


def test_spd_solve_is_exact_on_a_diagonal_and_refuses_a_wrong_shape() -> None:
    factor = spd_factor(np.diag([4.0, 9.0, 16.0]))
    np.testing.assert_array_equal(spd_solve(factor, [4.0, 9.0, 16.0]), [1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match=r'rhs must have 3 rows \(the factor is 3 x 3\), got '
                                         r'shape \(2,\)'):
        spd_solve(factor, np.ones(2))
    with pytest.raises(ValueError, match=r'got shape \(3, 1, 1\)'):
        spd_solve(factor, np.ones((3, 1, 1)))
    with pytest.raises(np.linalg.LinAlgError):
        spd_factor(np.diag([1.0, -1.0]))
