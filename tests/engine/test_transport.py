"""Transport (§4.5): the thesis's worked example and the Neumann series against a direct solve."""

import numpy as np
import pytest
import scipy.sparse as sp

from cloudgraph.transport import transport


def test_thesis_worked_example():
    # §4.5.1 gives L' = [0.1, 0.28, 0.44, 0.54] (docs/method.md). The thesis's own figure was not at
    # hand; this four-node graph is a reconstruction that has exactly that result: node 1 lit
    # at 0.1 feeds node 2 (weight 0.8), which feeds nodes 3 and 4 (0.5 each).
    T = sp.csr_matrix(np.array([[0, 0, 0, 0], [0.8, 0, 0, 0], [0, 0.5, 0, 0], [0, 0.5, 0, 0]]))
    L_d = np.array([[0.1], [0.2], [0.3], [0.4]])
    L, iterations = transport(T, L_d, albedo=1.0, max_depth=-1, tol=0.0, method="neumann")
    np.testing.assert_allclose(L.ravel(), [0.1, 0.28, 0.44, 0.54], atol=1e-12)
    # The series ends once T^i L_d is zero: node 1 -> 2 -> {3, 4} is two products deep.
    assert iterations == 3
    # and the linear solve (the default for unbounded depth) finds the same
    L, _ = transport(T, L_d, albedo=1.0, max_depth=-1, tol=1e-12)
    np.testing.assert_allclose(L.ravel(), [0.1, 0.28, 0.44, 0.54], atol=1e-10)


@pytest.mark.parametrize("method", ["krylov", "neumann"])
def test_unbounded_depth_matches_the_linear_solve(method):
    rng = np.random.default_rng(1)
    n = 300
    C = sp.random(n, n, density=0.03, random_state=2, format="csr")
    C = sp.diags(0.95 / np.maximum(np.asarray(C.sum(axis=1)).ravel(), 1e-9)) @ C  # rows sum to 0.95
    L_d = rng.random((n, 3))
    albedo = np.array([1.0, 0.9, 0.5])
    L, _ = transport(C, L_d, albedo, max_depth=-1, tol=1e-10, method=method)
    for ch in range(3):
        exact = sp.linalg.spsolve(sp.eye(n) - C @ sp.diags(np.full(n, albedo[ch])), L_d[:, ch])
        np.testing.assert_allclose(L[:, ch], exact, rtol=1e-7)


@pytest.mark.parametrize("depth", [1, 2, 5])
def test_bounded_depth_sums_exactly_depth_terms(depth):
    rng = np.random.default_rng(3)
    C = sp.csr_matrix(rng.random((6, 6)) * 0.1)
    L_d = rng.random((6, 1))
    expected = sum(np.linalg.matrix_power(C.toarray() * 0.8, i) @ L_d for i in range(depth))
    L, iterations = transport(C, L_d, albedo=0.8, max_depth=depth)
    np.testing.assert_allclose(L, expected, rtol=1e-12)
    assert iterations == depth - 1


def test_zero_depth_gives_no_radiance():
    L, _ = transport(sp.eye(2, format="csr"), np.ones((2, 3)), 1.0, max_depth=0)
    assert not L.any()


def test_the_solver_needs_far_fewer_products_than_the_series_when_escape_is_rare():
    # A chain where a flight escapes with probability 0.002: the series shrinks by 0.998 a term.
    rng = np.random.default_rng(4)
    n = 2000
    C = sp.random(n, n, density=0.005, random_state=5, format="csr")
    C = sp.diags(0.998 / np.asarray(C.sum(axis=1)).ravel()) @ C
    L_d = np.repeat(rng.random((n, 1)), 3, axis=1)  # a grey light
    exact = sp.linalg.spsolve(sp.csc_matrix(sp.eye(n) - C), L_d[:, 0])
    L_k, products_k = transport(C, L_d, 1.0, tol=1e-6)
    L_n, products_n = transport(C, L_d, 1.0, tol=1e-6, method="neumann")
    # Measured: 23 products against 3,797; the solve is also the more accurate (1e-8 vs 5e-4).
    assert products_k * 20 < products_n
    np.testing.assert_allclose(L_k[:, 0], exact, rtol=1e-4)
    np.testing.assert_array_equal(L_k[:, 0], L_k[:, 1])  # equal channels are solved once
    assert np.abs(L_n[:, 0] / exact - 1).max() < 0.01
