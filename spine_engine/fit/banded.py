"""Banded linear algebra of the fit: LAPACK upper band storage and the bordered (arrow) solve.

The vertebra unknowns (6 per vertebra) couple only neighbours, so their normal matrix A is banded
with half-bandwidth KD = 11, stored as ab[KD + i − j, j] = A[i, j] (LAPACK upper band storage).
The estimated projection parameters (a few per view) touch every landmark of their view: they form
a dense border B (n × p) and corner C (p × p). The system [[A, B], [Bᵀ, C]] h = −g is solved by
block elimination: S = C − Bᵀ A⁻¹ B (Schur complement),
    h_p = S⁻¹ (Bᵀ A⁻¹ g_A − g_p),   h_A = −A⁻¹ (g_A + B h_p),
with one band Cholesky factorisation of A (dpbtrf) and 1 + p band solves (dpbtrs): O(n·KD² + n·p·KD).
"""

from __future__ import annotations

from typing import NamedTuple, cast

import numpy as np
from numpy.typing import NDArray
from scipy.linalg.lapack import dpbtrf, dpbtrs, dpotrf, dpotrs

from .types import FloatArray

KD = 11
"""Half-bandwidth of the normal matrix: a segment couples two vertebrae of 6 unknowns each."""

UPPER3 = np.triu_indices(3)


def accumulate(bins: NDArray[np.intp], weights: FloatArray, minlength: int) -> FloatArray:
    """Sum of ``weights`` per bin (numpy's bincount, typed as the float array it returns)."""
    return cast(FloatArray, np.bincount(bins, weights, minlength=minlength))


def band_to_dense(ab: FloatArray) -> FloatArray:
    """Symmetric dense matrix from LAPACK upper band storage ab[KD + i − j, j] = H[i, j]."""
    kd = ab.shape[0] - 1
    n = ab.shape[1]
    H = np.zeros((n, n))
    for off in range(kd + 1):
        i = np.arange(n - off)
        H[i, i + off] = ab[kd - off, off:]
        H[i + off, i] = ab[kd - off, off:]
    return H


class BorderedSystem(NamedTuple):
    """Normal equations [[A, B], [Bᵀ, C]] with A in upper band storage (``ab``)."""

    ab: FloatArray
    """(KD + 1, n) band of A."""
    B: FloatArray
    """(n, p) border."""
    C: FloatArray
    """(p, p) corner."""

    def dense(self) -> FloatArray:
        """The whole symmetric matrix, dense (tests and small problems)."""
        A = band_to_dense(self.ab)
        return np.block([[A, self.B], [self.B.T, self.C]]) if self.C.size else A


def solve_bordered(
    ab: FloatArray, B: FloatArray, C: FloatArray, g: FloatArray
) -> FloatArray | None:
    """h solving [[A, B], [Bᵀ, C]] h = −g (block elimination, module docstring); None when A or the
    Schur complement is not positive definite. ``ab`` is overwritten."""
    n = ab.shape[1]
    p = C.shape[0]
    c, info = dpbtrf(ab, overwrite_ab=1)
    if info != 0:
        return None
    if p == 0:
        return cast(FloatArray, dpbtrs(c, -g[:, None])[0][:, 0])
    rhs = np.empty((n, 1 + p))
    rhs[:, 0] = g[:n]
    rhs[:, 1:] = B
    X = dpbtrs(c, rhs)[0]
    S = C - B.T @ X[:, 1:]
    # S is p × p with p ≤ 12: LAPACK's dense Cholesky (dpotrf, info > 0 when not definite) and
    # its solve L Lᵀ h_p = rhs (dpotrs), called directly (no wrapper or exception overhead)
    L, info = dpotrf(S, lower=1, overwrite_a=1)
    if info != 0:
        return None
    h_p = dpotrs(L, B.T @ X[:, 0] - g[n:], lower=1)[0]
    h = np.empty(n + p)
    h[:n] = -(X[:, 0] + X[:, 1:] @ h_p)
    h[n:] = h_p
    return h
