"""Batched SO(3) kernels: hat/vee, exponential and logarithm maps, and their Jacobians.

Every function works on stacks: vectors have shape ``(..., 3)`` and matrices ``(..., 3, 3)``.
Angles are in radians. Notation: φ ∈ R³ is a rotation vector, θ = ‖φ‖, Φ = hat(φ).

Jacobian conventions (right-trivialised, as in Chirikjian and Sola et al.):
    exp(φ + δ) ≈ exp(φ) exp(J_r(φ) δ),       log(exp(φ) exp(δ)) ≈ φ + J_r⁻¹(φ) δ,
    exp(φ + δ) ≈ exp(J_l(φ) δ) exp(φ),       log(exp(δ) exp(φ)) ≈ φ + J_l⁻¹(φ) δ,
with J_l(φ) = J_r(−φ) = J_r(φ)ᵀ.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

_SMALL = 0.05
"""Below this angle (rad) the Jacobian coefficients use their Taylor series (truncation < 1e-17)."""

_NEAR_PI_COS = -0.7
"""Above θ = arccos(−0.7) ≈ 134° the logarithm takes the axis from the symmetric part of R."""

# hat(w).reshape(9) = _HAT @ w and vee(W) = _VEE @ W.reshape(9) (skew part), as constant matrices
# so that both are one matrix product on a stack.
_HAT = np.array(
    [[0, 0, 0], [0, 0, -1], [0, 1, 0], [0, 0, 1], [0, 0, 0], [-1, 0, 0], [0, -1, 0], [1, 0, 0], [0, 0, 0]],
    dtype=float,
)
_VEE = 0.5 * _HAT.T


def hat(w: ArrayLike) -> FloatArray:
    """Skew-symmetric matrix of ``w``: hat(w) @ x = w × x.

    hat(w) = [[0, −w3, w2], [w3, 0, −w1], [−w2, w1, 0]]; shape (..., 3) → (..., 3, 3).
    """
    w = np.asarray(w, dtype=float)
    return (w @ _HAT.T).reshape(*w.shape[:-1], 3, 3)


def vee(W: ArrayLike) -> FloatArray:
    """Inverse of ``hat``: the vector (W32, W13, W21) of a skew matrix, shape (..., 3, 3) → (..., 3).

    For a matrix that is not exactly skew it returns the vector of its skew part ½(W − Wᵀ).
    """
    W = np.asarray(W, dtype=float)
    return W.reshape(*W.shape[:-2], 9) @ _VEE.T


def _angle(phi: FloatArray) -> FloatArray:
    return np.sqrt(np.einsum("...i,...i->...", phi, phi))


@njit(cache=True)
def _exp_kernel(phi: FloatArray, out: FloatArray) -> None:
    """exp of each row of phi (k, 3) into out (k, 3, 3) (``exp_so3``)."""
    for n in range(phi.shape[0]):
        p0, p1, p2 = phi[n, 0], phi[n, 1], phi[n, 2]
        h = 0.5 * math.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
        half_sigma = 0.5 * (math.sin(h) / h if h > 0.0 else 1.0)
        w, x, y, z = math.cos(h), half_sigma * p0, half_sigma * p1, half_sigma * p2
        ww, xx, yy, zz = w * w, x * x, y * y, z * z
        out[n, 0, 0] = ww + xx - yy - zz
        out[n, 0, 1] = 2.0 * (x * y - w * z)
        out[n, 0, 2] = 2.0 * (x * z + w * y)
        out[n, 1, 0] = 2.0 * (x * y + w * z)
        out[n, 1, 1] = ww - xx + yy - zz
        out[n, 1, 2] = 2.0 * (y * z - w * x)
        out[n, 2, 0] = 2.0 * (x * z - w * y)
        out[n, 2, 1] = 2.0 * (y * z + w * x)
        out[n, 2, 2] = ww - xx - yy + zz


def exp_so3(phi: ArrayLike) -> FloatArray:
    """Rodrigues' formula exp(Φ) = cos θ I + (sin θ/θ) Φ + ((1 − cos θ)/θ²) φφᵀ, shape (..., 3) → (..., 3, 3).

    Evaluated through the unit quaternion q = (w, x, y, z) = (cos(θ/2), sin(θ/2) φ/θ) with sin(θ/2)/θ
    computed as a ratio that has no cancellation at any θ > 0 (and ½ at θ = 0), so it is exact for
    small angles without a Taylor branch; R is the quadratic form of q,
        R = [[w²+x²−y²−z², 2(xy−wz), 2(xz+wy)], [2(xy+wz), w²−x²+y²−z², 2(yz−wx)],
             [2(xz−wy), 2(yz+wx), w²−x²−y²+z²]]
    (one compiled loop over the stack).
    """
    phi = np.asarray(phi, dtype=float)
    flat = np.ascontiguousarray(phi.reshape(-1, 3))
    out = np.empty((len(flat), 3, 3))
    _exp_kernel(flat, out)
    return out.reshape(*phi.shape[:-1], 3, 3)


def cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """a × b over the last axis (length 3), broadcast as ``np.cross``, whose axis handling costs more
    than the product itself on the engine's small arrays."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


@njit(cache=True)
def _log_kernel(R: FloatArray, out: FloatArray) -> None:
    """log of each rotation R (k, 3, 3) into out (k, 3) (``log_so3``)."""
    for n in range(R.shape[0]):
        w0 = 0.5 * (R[n, 2, 1] - R[n, 1, 2])
        w1 = 0.5 * (R[n, 0, 2] - R[n, 2, 0])
        w2 = 0.5 * (R[n, 1, 0] - R[n, 0, 1])
        c = 0.5 * (R[n, 0, 0] + R[n, 1, 1] + R[n, 2, 2]) - 0.5
        s = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        theta = math.atan2(s, c)
        if c >= _NEAR_PI_COS:
            f = theta / s if s > 0.0 else 1.0
            out[n, 0], out[n, 1], out[n, 2] = f * w0, f * w1, f * w2
            continue
        j = 0
        best = -math.inf
        for i in range(3):
            mii = (R[n, i, i] - c) / (1.0 - c)
            if mii > best:
                best, j = mii, i
        norm = math.sqrt(best)
        a0 = (0.5 * (R[n, 0, j] + R[n, j, 0]) - (c if j == 0 else 0.0)) / (1.0 - c) / norm
        a1 = (0.5 * (R[n, 1, j] + R[n, j, 1]) - (c if j == 1 else 0.0)) / (1.0 - c) / norm
        a2 = (0.5 * (R[n, 2, j] + R[n, j, 2]) - (c if j == 2 else 0.0)) / (1.0 - c) / norm
        sign = -1.0 if a0 * w0 + a1 * w1 + a2 * w2 < 0.0 else 1.0
        out[n, 0], out[n, 1], out[n, 2] = sign * theta * a0, sign * theta * a1, sign * theta * a2


def log_so3(R: ArrayLike) -> FloatArray:
    """Rotation vector φ with exp(hat φ) = R and θ = ‖φ‖ ∈ [0, π]; shape (..., 3, 3) → (..., 3).

    θ = atan2(‖w‖, (tr R − 1)/2) with w = vee(R) = sin θ · axis, which is accurate at every angle,
    and φ = (θ / sin θ) w. Near π (cos θ < −0.7), where sin θ → 0, the axis a is taken from the
    symmetric part instead: aaᵀ = (½(R + Rᵀ) − cos θ I)/(1 − cos θ), the column of largest
    diagonal entry normalised, with its sign chosen so that a·w ≥ 0. At θ = π exactly both
    signs are valid and either may be returned (one compiled loop over the stack).
    """
    R = np.asarray(R, dtype=float)
    flat = np.ascontiguousarray(R.reshape(-1, 3, 3))
    out = np.empty((len(flat), 3))
    _log_kernel(flat, out)
    return out.reshape(*R.shape[:-2], 3)


def _jr_coefficients(theta: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(1 − cos θ)/θ² (as ½ sinc²(θ/2), exact) and (θ − sin θ)/θ³ (Taylor series below ``_SMALL``)."""
    t2 = theta * theta
    small = theta < _SMALL
    safe = np.where(small, 1.0, theta)
    b = 0.5 * np.sinc(theta / (2.0 * np.pi)) ** 2
    series = 1.0 / 6.0 + t2 * (-1.0 / 120.0 + t2 * (1.0 / 5040.0 - t2 / 362880.0))
    c = np.where(small, series, (safe - np.sin(safe)) / (safe * safe * safe))
    return b, c


def _jr_inv_coefficient(theta: FloatArray) -> FloatArray:
    """1/θ² − cot(θ/2)/(2θ) = 1/θ² − (1 + cos θ)/(2θ sin θ), with its Taylor series below ``_SMALL``."""
    t2 = theta * theta
    small = theta < _SMALL
    safe = np.where(small, 1.0, theta)
    exact = 1.0 / (safe * safe) - 0.5 / (safe * np.tan(0.5 * safe))
    series = 1.0 / 12.0 + t2 * (1.0 / 720.0 + t2 * (1.0 / 30240.0 + t2 / 1209600.0))
    return np.where(small, series, exact)


def right_jacobian(phi: ArrayLike) -> FloatArray:
    """J_r(φ) = I − ((1 − cos θ)/θ²) Φ + ((θ − sin θ)/θ³) Φ²; shape (..., 3) → (..., 3, 3)."""
    phi = np.asarray(phi, dtype=float)
    b, c = _jr_coefficients(_angle(phi))
    P = hat(phi)
    return np.eye(3) - b[..., None, None] * P + c[..., None, None] * (P @ P)


def right_jacobian_inv(phi: ArrayLike) -> FloatArray:
    """J_r⁻¹(φ) = I + ½Φ + (1/θ² − (1 + cos θ)/(2θ sin θ)) Φ²; shape (..., 3) → (..., 3, 3).

    Finite for θ < 2π (singular at 2π); log_so3 returns θ ≤ π.
    """
    phi = np.asarray(phi, dtype=float)
    d = _jr_inv_coefficient(_angle(phi))
    P = hat(phi)
    return np.eye(3) + 0.5 * P + d[..., None, None] * (P @ P)


def left_jacobian_inv(phi: ArrayLike) -> FloatArray:
    """J_l⁻¹(φ) = J_r⁻¹(−φ) = I − ½Φ + (1/θ² − (1 + cos θ)/(2θ sin θ)) Φ²; (..., 3) → (..., 3, 3)."""
    return right_jacobian_inv(-np.asarray(phi, dtype=float))


def vector_norms(x: FloatArray) -> FloatArray:
    """‖x‖ over the last axis, in x's units: √ of add.reduce of x·x, the arithmetic (and the bits)
    of ``np.linalg.norm(x, axis=-1)`` without its Python wrapper (it shows in the per-job setup)."""
    return np.sqrt(np.add.reduce(x * x, axis=-1))


def rotation_between(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """The smallest rotation taking the direction of ``a`` onto that of ``b``, (..., 3) → (..., 3, 3).

    For unit â, b̂ with c = â × b̂ and cos θ = â·b̂: R = cos θ I + hat(c) + c cᵀ/(1 + cos θ)
    (axis c, angle atan2(‖c‖, cos θ)). When some pair is within 25° of opposite, where that
    division loses accuracy, the axis-angle form is used, with any axis perpendicular to â for
    exactly opposite vectors.
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    a, b = np.broadcast_arrays(a / vector_norms(a)[..., None], b / vector_norms(b)[..., None])
    Ha = hat(a)
    c = (Ha @ b[..., None])[..., 0]
    cos = np.einsum("...i,...i->...", a, b)
    if (cos > -0.9).all():
        out = (c / (1.0 + cos)[..., None])[..., :, None] * c[..., None, :] + hat(c)
        out.reshape(*out.shape[:-2], 9)[..., ::4] += cos[..., None]
        return out
    s = _angle(c)
    theta = np.arctan2(s, cos)
    phi = (theta / np.where(s > 0.0, s, 1.0))[..., None] * c
    opposite = (s < 1e-12) & (cos < 0.0)
    if np.any(opposite):
        ao = a[opposite]
        trial = np.where(np.abs(ao[:, :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
        perp = (hat(ao) @ trial[:, :, None])[:, :, 0]
        phi[opposite] = np.pi * perp / np.linalg.norm(perp, axis=-1, keepdims=True)
    return exp_so3(phi)


def slerp(R0: ArrayLike, R1: ArrayLike, t: ArrayLike) -> FloatArray:
    """Geodesic interpolation R0 exp(t log(R0ᵀ R1)); t = 0 gives R0 and t = 1 gives R1.

    ``R0``, ``R1`` broadcast against ``t[..., None, None]``; t is dimensionless.
    """
    R0 = np.asarray(R0, dtype=float)
    R1 = np.asarray(R1, dtype=float)
    t = np.asarray(t, dtype=float)
    phi = log_so3(R0.swapaxes(-1, -2) @ R1)
    return R0 @ exp_so3(t[..., None] * phi)
