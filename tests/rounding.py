"""Tolerances from the arithmetic, not from one machine's last digits.

Two computations of one quantity that take different paths (numpy's BLAS against the compiled
engine, a matrix rebuilt here against one stored from another machine, the y plane's eigenproblem
against the z plane's) agree only to what rounding leaves of each. OpenBLAS picks its kernels
(Haswell, SkylakeX, Sandybridge, ...) when it loads, and each sums a product in its own order,
with or without fused multiply-adds: the digits below these bounds differ between CPUs. The bounds
are the standard ones (Higham, *Accuracy and Stability of Numerical Algorithms*, 2nd ed., 3.5 for
products; the LAPACK Users' Guide, 3rd ed., 4.7 and 4.10, for symmetric eigenproblems).
"""

import numpy as np
import scipy.linalg as sla

EPS = float(np.finfo(float).eps)


def gamma(n: int) -> float:
    """gamma_n = n u / (1 - n u), u the unit roundoff: the relative bound of n roundings."""
    u = EPS / 2
    return n * u / (1 - n * u)


def product_rounding(a: np.ndarray, b: np.ndarray, paths: int = 2) -> np.ndarray:
    """Elementwise bound on the difference of ``paths`` evaluations of a @ b in any summation
    order: each is within gamma_n |A| |B| of the exact product (n the inner dimension)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return paths * gamma(a.shape[-1]) * (np.abs(a) @ np.abs(b))


def assert_within(actual, expected, bound, what: str) -> None:
    """|actual - expected| <= bound elementwise, naming the worst entry and its bound."""
    actual, expected = np.asarray(actual, dtype=float), np.asarray(expected, dtype=float)
    bound = np.broadcast_to(np.asarray(bound, dtype=float), np.broadcast_shapes(actual.shape, expected.shape))
    excess = np.abs(actual - expected) - bound
    worst = np.unravel_index(int(np.argmax(excess)), excess.shape) if excess.ndim else ()
    assert excess[worst] <= 0.0, (
        f"{what}: differ by {abs(actual - expected)[worst]:.3g} at {worst}, beyond the rounding bound "
        f"{bound[worst]:.3g} ({actual[worst]!r} against {expected[worst]!r})")


def symmetric_pencil(stiffness: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """Eigenvalues of (K - lambda M), K symmetric and M positive definite, ascending."""
    return sla.eigh(stiffness, mass, eigvals_only=True)


def eigenvalue_rounding(lam: np.ndarray) -> np.ndarray:
    """Relative error bound of each eigenvalue of a symmetric-definite pencil from a backward
    stable solver: eps |lambda|_max / |lambda| (LAPACK Users' Guide 4.7: EPSMCH * ANORM)."""
    lam = np.asarray(lam, dtype=float)
    return EPS * np.abs(lam).max() / np.abs(lam)


def eigenvector_rounding(lam: np.ndarray, count: int) -> float:
    """Relative error bound of the first ``count`` eigenvectors of a symmetric-definite pencil with
    eigenvalues ``lam`` (ascending, all of them): eps |lambda|_max / the smallest gap from one of
    them to its neighbours (LAPACK Users' Guide 4.7: EPSMCH * ANORM / RCONDZ). What is built
    linearly from those vectors (a modal input or output matrix, its sampled form) carries the
    same relative error."""
    lam = np.asarray(lam, dtype=float)
    gaps = np.diff(lam[:count + 1])
    return EPS * np.abs(lam).max() / gaps.min()


def spectral_radius_rounding(matrix: np.ndarray) -> float:
    """Bound on the difference of two computations of the spectral radius of ``matrix``: LAPACK
    balances it (B = D^-1 A D) and its QR iteration is backward stable there, so the eigenvalue
    of largest modulus moves by at most kappa eps ||B||_2 in each, kappa its condition number
    (1 / |cos| of its left and right eigenvectors)."""
    balanced, _ = sla.matrix_balance(matrix)
    w, left, right = sla.eig(balanced, left=True, right=True)
    i = int(np.argmax(np.abs(w)))
    kappa = np.linalg.norm(left[:, i]) * np.linalg.norm(right[:, i]) / abs(left[:, i].conj() @ right[:, i])
    return 2 * kappa * EPS * float(np.linalg.norm(balanced, 2))
