"""The rod's rows of the residual vector: strains of each segment and their derivatives.

Per segment i (rest length Δs_i), with φ_i = log(R_iᵀ R_{i+1}) = Δs_i u_i and
v_i = R_iᵀ (r_{i+1} − r_i)/Δs_i, six rows √(Δs_i α_i/2)(u_i − u0_i) then √(Δs_i β_i/2)(v_i − v0_i)
(E_I = their sum of squares, N·mm). Jacobian blocks over [δr_i, δθ_i, δr_{i+1}, δθ_{i+1}]:
    ∂u_i/∂δθ_{i+1} = J_r⁻¹(φ_i)/Δs_i,  ∂u_i/∂δθ_i = −J_l⁻¹(φ_i)/Δs_i,
    ∂v_i/∂δθ_i = hat(v_i),  ∂v_i/∂r_{i+1} = R_iᵀ/Δs_i = −∂v_i/∂r_i.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..rotations import hat, log_so3
from .types import FloatArray, RodParameters


class RodCache(NamedTuple):
    """Per-segment quantities of one configuration that the derivatives reuse."""

    Rt: FloatArray
    """(N−1, 3, 3) R_iᵀ."""
    phi: FloatArray
    """(N−1, 3) φ_i = log(R_iᵀ R_{i+1})."""
    v: FloatArray
    """(N−1, 3) v_i."""


class LocalJacobian(NamedTuple):
    """Per-segment Jacobians (N−1, 6, 12) and the pieces the second-order terms reuse."""

    J: FloatArray
    Jr_inv: FloatArray
    Jl_inv: FloatArray
    theta2: FloatArray
    d: FloatArray
    dp: FloatArray


def jr_inv_coefficients(theta2: FloatArray) -> tuple[FloatArray, FloatArray]:
    """d(θ) = 1/θ² − cot(θ/2)/(2θ) of J_r⁻¹ = I + ½Φ + dΦ², and d'(θ)/θ; Taylor series below θ = 0.1."""
    theta = np.sqrt(theta2)
    small = theta < 0.1
    t = np.where(small, 1.0, theta)
    t2 = t * t
    cot = 1.0 / np.tan(0.5 * t)
    d = np.where(
        small,
        1.0 / 12.0 + theta2 * (1.0 / 720.0 + theta2 * (1.0 / 30240.0 + theta2 / 1209600.0)),
        1.0 / t2 - 0.5 * cot / t,
    )
    dp = np.where(
        small,
        1.0 / 360.0 + theta2 * (1.0 / 7560.0 + theta2 * (1.0 / 201600.0 + theta2 / 5987520.0)),
        (-2.0 / t2 + 0.5 * cot / t + 0.25 * (1.0 + cot * cot)) / t2,
    )
    return d, dp


def jr_inverse(phi: FloatArray) -> FloatArray:
    """J_r⁻¹(φ) = I + ½ hat(φ) + d(θ) hat(φ)² for φ (k, 3): ∂ log(R̄ᵀ R exp(hat δ))/∂δ at δ = 0."""
    theta2 = np.einsum("ij,ij->i", phi, phi)
    d, _ = jr_inv_coefficients(theta2)
    S = d[:, None, None] * (phi[:, :, None] * phi[:, None, :])
    S.reshape(-1, 9)[:, ::4] += (1.0 - d * theta2)[:, None]
    return S + hat(0.5 * phi)


def check_params(params: RodParameters) -> int:
    """Number of vertebrae N; raises ValueError on inconsistent shapes or negative stiffness."""
    ds = np.asarray(params.ds)
    if ds.ndim != 1 or len(ds) < 2:
        raise ValueError(f"ds must have shape (N−1,) with N ≥ 3, got {ds.shape}")
    if not np.all(ds > 0.0):
        raise ValueError("rest lengths ds must be positive")
    for name in ("u0", "v0", "alpha", "beta"):
        shape = np.shape(getattr(params, name))
        if shape != (len(ds), 3):
            raise ValueError(f"{name} must have shape ({len(ds)}, 3), got {shape}")
    if np.any(np.asarray(params.alpha) < 0.0) or np.any(np.asarray(params.beta) < 0.0):
        raise ValueError("stiffnesses alpha and beta must be non-negative")
    return len(ds) + 1


class RodRows:
    """Rows, Jacobian and second-order terms of the rod's potential energy (module docstring)."""

    def __init__(self, params: RodParameters, prior_strength: float = 1.0):
        self.n = check_params(params)
        ns = self.n - 1
        ds = np.asarray(params.ds, dtype=float)
        self.ds = ds
        scale = np.sqrt(prior_strength)
        cu = scale * np.sqrt(0.5 * ds[:, None] * np.asarray(params.alpha, dtype=float))
        cv = scale * np.sqrt(0.5 * ds[:, None] * np.asarray(params.beta, dtype=float))
        self._au = cu / ds[:, None]
        self._bu = cu * np.asarray(params.u0, dtype=float)
        self._cv = cv
        self._cv_ds = cv / ds[:, None]
        self._bv = cv * np.asarray(params.v0, dtype=float)
        self._inv_ds = 1.0 / ds[:, None]
        self._Jloc = np.zeros((ns, 6, 12))
        self._Sloc = np.zeros((ns, 12, 12))

    def evaluate(self, r: FloatArray, R: FloatArray, out: FloatArray) -> RodCache:
        """Write the 6(N−1) rod rows into ``out``."""
        ns = self.n - 1
        Rt = np.swapaxes(R[:-1], 1, 2)
        phi = log_so3(Rt @ R[1:])
        v = (Rt @ (r[1:] - r[:-1])[:, :, None])[:, :, 0] * self._inv_ds
        rod = out[: 6 * ns].reshape(ns, 6)
        np.multiply(self._au, phi, out=rod[:, :3])
        rod[:, :3] -= self._bu
        np.multiply(self._cv, v, out=rod[:, 3:])
        rod[:, 3:] -= self._bv
        return RodCache(Rt, phi, v)

    def local_jacobian(self, cache: RodCache) -> LocalJacobian:
        """Fill the per-segment Jacobians (N−1, 6, 12) over [r_i, θ_i, r_{i+1}, θ_{i+1}]."""
        Rt, phi, v = cache
        theta2 = np.einsum("ij,ij->i", phi, phi)
        d, dp = jr_inv_coefficients(theta2)
        half_P = hat(0.5 * phi)
        # J_r⁻¹ = S + ½Φ and J_l⁻¹ = S − ½Φ = J_r⁻ᵀ, with S = I + dΦ² = (1 − dθ²) I + d φφᵀ.
        S = d[:, None, None] * (phi[:, :, None] * phi[:, None, :])
        S.reshape(-1, 9)[:, ::4] += (1.0 - d * theta2)[:, None]
        Jr_inv = S + half_P
        Jl_inv = S - half_P
        J = self._Jloc
        au = self._au[:, :, None]
        np.multiply(-au, Jl_inv, out=J[:, :3, 3:6])
        np.multiply(au, Jr_inv, out=J[:, :3, 9:12])
        cvds = self._cv_ds[:, :, None]
        np.multiply(-cvds, Rt, out=J[:, 3:, 0:3])
        np.multiply(cvds, Rt, out=J[:, 3:, 6:9])
        np.multiply(self._cv[:, :, None], hat(v), out=J[:, 3:, 3:6])
        return LocalJacobian(J, Jr_inv, Jl_inv, theta2, d, dp)

    def second_order(self, cache: RodCache, local: LocalJacobian, rho: FloatArray) -> FloatArray:
        """Σ_k ρ_k ∇²ρ_k per segment (N−1, 12, 12), upper blocks only (the rest is never read).

        With λ = ρ_u ⊙ √(Δs α/2)/Δs, K± = ±½ hat(λ) + d'/θ (Φ²λ) φᵀ + d (φλᵀ − 2λφᵀ + (φ·λ) I):
            θ_i θ_i: K₋ J_l⁻¹ + ½ hat(J_l⁻ᵀλ),  θ_{i+1} θ_{i+1}: K₊ J_r⁻¹ − ½ hat(J_r⁻ᵀλ),
            θ_{i+1} θ_i: −K₊ J_l⁻¹;
        with μ = ρ_v ⊙ √(Δs β/2): θ_i θ_i += ½(μvᵀ + vμᵀ) − (μ·v) I, θ_i r_{i±1} = ±hat(μ) R_iᵀ/Δs.
        """
        Rt, phi, v = cache
        _, Jr_inv, Jl_inv, theta2, d, dp = local
        lam = rho[:, :3] * self._au
        mu = rho[:, 3:] * self._cv
        pl = np.einsum("ij,ij->i", phi, lam)
        P2l = phi * pl[:, None] - theta2[:, None] * lam
        common = dp[:, None, None] * (P2l[:, :, None] * phi[:, None, :]) + d[:, None, None] * (
            phi[:, :, None] * lam[:, None, :] - 2.0 * lam[:, :, None] * phi[:, None, :]
        )
        common.reshape(-1, 9)[:, ::4] += (d * pl)[:, None]
        half_L = hat(0.5 * lam)
        K_plus = common + half_L
        K_minus = common - half_L
        S = self._Sloc
        # J_l⁻ᵀλ = J_r⁻¹λ and J_r⁻ᵀλ = J_l⁻¹λ.
        Jr_l = (Jr_inv @ lam[:, :, None])[:, :, 0]
        Jl_l = (Jl_inv @ lam[:, :, None])[:, :, 0]
        mv = mu[:, :, None] * v[:, None, :]
        tt = K_minus @ Jl_inv + hat(0.5 * Jr_l) + 0.5 * (mv + np.swapaxes(mv, 1, 2))
        tt.reshape(-1, 9)[:, ::4] -= np.einsum("ij,ij->i", mu, v)[:, None]
        S[:, 3:6, 3:6] = tt
        np.subtract(K_plus @ Jr_inv, hat(0.5 * Jl_l), out=S[:, 9:12, 9:12])
        np.negative(np.swapaxes(K_plus @ Jl_inv, 1, 2), out=S[:, 3:6, 9:12])
        C = (hat(mu) @ Rt) * self._inv_ds[:, :, None]
        S[:, 3:6, 6:9] = C
        np.negative(np.swapaxes(C, 1, 2), out=S[:, 0:3, 3:6])
        return S

    def strains(self, cache: RodCache) -> tuple[FloatArray, FloatArray]:
        """(u, v) of the configuration, rad/mm and dimensionless."""
        return cache.phi * self._inv_ds, cache.v.copy()
