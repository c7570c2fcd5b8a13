"""The rod's rows of the residual vector: strains of each segment and their derivatives.

Per segment i (rest length Δs_i), with φ_i = log(R_iᵀ R_{i+1}) = Δs_i u_i and
v_i = R_iᵀ (r_{i+1} − r_i)/Δs_i, six rows √(Δs_i α_i/2)(u_i − u0_i) then √(Δs_i β_i/2)(v_i − v0_i)
(E_I = their sum of squares, N·mm). Jacobian blocks over [δr_i, δθ_i, δr_{i+1}, δθ_{i+1}]:
    ∂u_i/∂δθ_{i+1} = J_r⁻¹(φ_i)/Δs_i,  ∂u_i/∂δθ_i = −J_l⁻¹(φ_i)/Δs_i,
    ∂v_i/∂δθ_i = hat(v_i),  ∂v_i/∂r_{i+1} = R_iᵀ/Δs_i = −∂v_i/∂r_i.

The derivatives are per-segment loops over 3×3 blocks, compiled by numba (``@njit(cache=True)``, as
PyElastica compiles its kernels; the machine code is cached on disk next to the module): with 16
segments a numpy formulation is ~100 calls on tiny arrays per iteration, all overhead. Kernels use
scalar ``math`` and element loops (no array slices), which keeps their first compile short.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from ..rotations import log_so3
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


@njit(cache=True)
def _jr_inv_pair(theta2: float) -> tuple[float, float]:
    """(d, d'/θ) of one angle (``jr_inv_coefficients``)."""
    t = math.sqrt(theta2)
    if t < 0.1:  # Taylor series
        d = 1.0 / 12.0 + theta2 * (1.0 / 720.0 + theta2 * (1.0 / 30240.0 + theta2 / 1209600.0))
        dp = 1.0 / 360.0 + theta2 * (1.0 / 7560.0 + theta2 * (1.0 / 201600.0 + theta2 / 5987520.0))
        return d, dp
    t2 = t * t
    cot = 1.0 / math.tan(0.5 * t)
    return 1.0 / t2 - 0.5 * cot / t, (-2.0 / t2 + 0.5 * cot / t + 0.25 * (1.0 + cot * cot)) / t2


@njit(cache=True)
def jr_inv_coefficients(theta2: FloatArray) -> tuple[FloatArray, FloatArray]:
    """d(θ) = 1/θ² − cot(θ/2)/(2θ) of J_r⁻¹ = I + ½Φ + dΦ², and d'(θ)/θ (1/rad⁴), for θ² (k,) in rad²;
    Taylor series below θ = 0.1."""
    d = np.empty_like(theta2)
    dp = np.empty_like(theta2)
    for i in range(len(theta2)):
        d[i], dp[i] = _jr_inv_pair(theta2[i])
    return d, dp


@njit(cache=True)
def _local_jacobian_kernel(
    Rt: FloatArray, phi: FloatArray, v: FloatArray, au: FloatArray, cv: FloatArray, cv_ds: FloatArray,
    J: FloatArray, Jr_inv: FloatArray, Jl_inv: FloatArray, theta2: FloatArray, d: FloatArray, dp: FloatArray,
) -> None:
    """Per segment i (``RodRows.local_jacobian``): θ² = φ·φ, (d, d'/θ), J_r⁻¹ = S + ½Φ and
    J_l⁻¹ = S − ½Φ with S = (1 − dθ²) I + d φφᵀ, and the blocks of J (rows u then v) over
    [r_i, θ_i, r_{i+1}, θ_{i+1}]: −a J_l⁻¹, a J_r⁻¹ (a = √(Δs α/2)/Δs, rad⁻¹·√(N·mm)), ∓c R_iᵀ/Δs
    and c hat(v_i) (c = √(Δs β/2)); the other entries of J are left as they are (zero)."""
    for i in range(phi.shape[0]):
        p0, p1, p2 = phi[i, 0], phi[i, 1], phi[i, 2]
        t2 = p0 * p0 + p1 * p1 + p2 * p2
        di, dpi = _jr_inv_pair(t2)
        theta2[i], d[i], dp[i] = t2, di, dpi
        for a in range(3):
            for b in range(3):
                Jr_inv[i, a, b] = di * phi[i, a] * phi[i, b]
            Jr_inv[i, a, a] += 1.0 - di * t2
            for b in range(3):
                Jl_inv[i, a, b] = Jr_inv[i, a, b]
        h0, h1, h2 = 0.5 * p0, 0.5 * p1, 0.5 * p2
        Jr_inv[i, 0, 1] -= h2
        Jr_inv[i, 0, 2] += h1
        Jr_inv[i, 1, 0] += h2
        Jr_inv[i, 1, 2] -= h0
        Jr_inv[i, 2, 0] -= h1
        Jr_inv[i, 2, 1] += h0
        Jl_inv[i, 0, 1] += h2
        Jl_inv[i, 0, 2] -= h1
        Jl_inv[i, 1, 0] -= h2
        Jl_inv[i, 1, 2] += h0
        Jl_inv[i, 2, 0] += h1
        Jl_inv[i, 2, 1] -= h0
        v0, v1, v2 = v[i, 0], v[i, 1], v[i, 2]
        for a in range(3):
            ua, cda = au[i, a], cv_ds[i, a]
            for b in range(3):
                J[i, a, 3 + b] = -ua * Jl_inv[i, a, b]
                J[i, a, 9 + b] = ua * Jr_inv[i, a, b]
                J[i, 3 + a, b] = -cda * Rt[i, a, b]
                J[i, 3 + a, 6 + b] = cda * Rt[i, a, b]
        J[i, 3, 3], J[i, 3, 4], J[i, 3, 5] = 0.0, -cv[i, 0] * v2, cv[i, 0] * v1
        J[i, 4, 3], J[i, 4, 4], J[i, 4, 5] = cv[i, 1] * v2, 0.0, -cv[i, 1] * v0
        J[i, 5, 3], J[i, 5, 4], J[i, 5, 5] = -cv[i, 2] * v1, cv[i, 2] * v0, 0.0


@njit(cache=True)
def _hat_entry(w: FloatArray, a: int, b: int) -> float:
    """hat(w)[a, b] = −ε_abk w_k: 0 on the diagonal, hat(w) = [[0, −w3, w2], [w3, 0, −w1], [−w2, w1, 0]]."""
    if a == b:
        return 0.0
    k = 3 - a - b
    return w[k] if (b - a) % 3 == 2 else -w[k]


@njit(cache=True)
def _second_order_kernel(
    Rt: FloatArray, phi: FloatArray, v: FloatArray, Jr_inv: FloatArray, Jl_inv: FloatArray,
    theta2: FloatArray, d: FloatArray, dp: FloatArray, rho: FloatArray,
    au: FloatArray, cv: FloatArray, inv_ds: FloatArray, S: FloatArray,
) -> None:
    """The upper blocks of Σ_k ρ_k ∇²ρ_k per segment into S (N−1, 12, 12) (``RodRows.second_order``
    gives the formulas); the other entries of S are left as they are (zero)."""
    lam = np.empty(3)
    mu = np.empty(3)
    P2l = np.empty(3)
    jr = np.empty(3)
    jl = np.empty(3)
    Kp = np.empty((3, 3))
    Km = np.empty((3, 3))
    for i in range(phi.shape[0]):
        for a in range(3):
            lam[a] = rho[i, a] * au[i, a]
            mu[a] = rho[i, 3 + a] * cv[i, a]
        pl = phi[i, 0] * lam[0] + phi[i, 1] * lam[1] + phi[i, 2] * lam[2]
        mv = mu[0] * v[i, 0] + mu[1] * v[i, 1] + mu[2] * v[i, 2]
        di, dpi, t2 = d[i], dp[i], theta2[i]
        for a in range(3):
            P2l[a] = phi[i, a] * pl - t2 * lam[a]
        for a in range(3):
            for b in range(3):
                common = dpi * (P2l[a] * phi[i, b]) + di * (phi[i, a] * lam[b] - 2.0 * lam[a] * phi[i, b])
                if a == b:
                    common += di * pl
                half_l = 0.5 * _hat_entry(lam, a, b)
                Kp[a, b] = common + half_l
                Km[a, b] = common - half_l
        # J_l⁻ᵀλ = J_r⁻¹λ and J_r⁻ᵀλ = J_l⁻¹λ
        for a in range(3):
            jr[a] = Jr_inv[i, a, 0] * lam[0] + Jr_inv[i, a, 1] * lam[1] + Jr_inv[i, a, 2] * lam[2]
            jl[a] = Jl_inv[i, a, 0] * lam[0] + Jl_inv[i, a, 1] * lam[1] + Jl_inv[i, a, 2] * lam[2]
        for a in range(3):
            for b in range(3):
                tt = 0.0
                pp = 0.0
                pm = 0.0
                for c in range(3):
                    tt += Km[a, c] * Jl_inv[i, c, b]
                    pp += Kp[a, c] * Jr_inv[i, c, b]
                    pm += Kp[b, c] * Jl_inv[i, c, a]
                tt += 0.5 * _hat_entry(jr, a, b) + 0.5 * (mu[a] * v[i, b] + v[i, a] * mu[b])
                if a == b:
                    tt -= mv
                S[i, 3 + a, 3 + b] = tt
                S[i, 9 + a, 9 + b] = pp - 0.5 * _hat_entry(jl, a, b)
                S[i, 3 + a, 9 + b] = -pm
        # C = hat(μ) R_iᵀ/Δs: θ_i r_{i+1}, and −Cᵀ: r_i θ_i
        for b in range(3):
            c0 = (mu[1] * Rt[i, 2, b] - mu[2] * Rt[i, 1, b]) * inv_ds[i, 0]
            c1 = (mu[2] * Rt[i, 0, b] - mu[0] * Rt[i, 2, b]) * inv_ds[i, 0]
            c2 = (mu[0] * Rt[i, 1, b] - mu[1] * Rt[i, 0, b]) * inv_ds[i, 0]
            S[i, 3, 6 + b], S[i, 4, 6 + b], S[i, 5, 6 + b] = c0, c1, c2
            S[i, b, 3], S[i, b, 4], S[i, b, 5] = -c0, -c1, -c2


def jr_inverse(phi: FloatArray) -> FloatArray:
    """J_r⁻¹(φ) = I + ½ hat(φ) + d(θ) hat(φ)² for φ (k, 3): ∂ log(R̄ᵀ R exp(hat δ))/∂δ at δ = 0,
    written as (1 − dθ²) I + d φφᵀ + ½ hat(φ) (``_jr_inverse_kernel``; θ² = φ·φ by ``einsum``)."""
    phi = np.ascontiguousarray(phi, dtype=float)
    out = np.empty((len(phi), 3, 3))
    _jr_inverse_kernel(phi, np.einsum("ij,ij->i", phi, phi), out)
    return out


@njit(cache=True)
def _jr_inverse_kernel(phi: FloatArray, theta2: FloatArray, out: FloatArray) -> None:
    """``jr_inverse`` per row: out_ab = d (φ_a φ_b) + (1 − d θ²) δ_ab ± ½ φ_c (the hat's entries)."""
    for i in range(phi.shape[0]):
        d, _ = _jr_inv_pair(theta2[i])
        diagonal = 1.0 - d * theta2[i]
        for a in range(3):
            for b in range(3):
                out[i, a, b] = d * (phi[i, a] * phi[i, b])
            out[i, a, a] += diagonal
        h0, h1, h2 = 0.5 * phi[i, 0], 0.5 * phi[i, 1], 0.5 * phi[i, 2]
        out[i, 0, 1] -= h2
        out[i, 0, 2] += h1
        out[i, 1, 0] += h2
        out[i, 1, 2] -= h0
        out[i, 2, 0] -= h1
        out[i, 2, 1] += h0


_UPPER12_A, _UPPER12_B = np.triu_indices(12)
"""Row and column of each upper-triangle entry of a 12×12 block (row by row, as ``problem`` assembles them)."""


@njit(cache=True)
def _normal_blocks_kernel(
    Rt: FloatArray, phi: FloatArray, v: FloatArray, rho: FloatArray,
    au: FloatArray, cv: FloatArray, cv_ds: FloatArray, inv_ds: FloatArray,
    upper_a: np.ndarray, upper_b: np.ndarray, second_order: bool,
    J: FloatArray, S: FloatArray, H: FloatArray, g: FloatArray, S_upper: FloatArray,
) -> None:
    """Per segment: J (``_local_jacobian_kernel``), the upper triangle of JᵀJ into H (N−1, 78), Jᵀρ into
    g (N−1, 12) and, when ``second_order``, the upper triangle of Σ_k ρ_k ∇²ρ_k (``_second_order_kernel``,
    through the 12×12 buffer S) into S_upper (N−1, 78); one compiled call per normal-equation assembly."""
    ns = phi.shape[0]
    Jr_inv = np.empty((ns, 3, 3))
    Jl_inv = np.empty((ns, 3, 3))
    theta2 = np.empty(ns)
    d = np.empty(ns)
    dp = np.empty(ns)
    _local_jacobian_kernel(Rt, phi, v, au, cv, cv_ds, J, Jr_inv, Jl_inv, theta2, d, dp)
    for i in range(ns):
        for k in range(len(upper_a)):
            a, b = upper_a[k], upper_b[k]
            acc = 0.0
            for r in range(6):
                acc += J[i, r, a] * J[i, r, b]
            H[i, k] = acc
        for a in range(12):
            acc = 0.0
            for r in range(6):
                acc += J[i, r, a] * rho[i, r]
            g[i, a] = acc
    if second_order:
        _second_order_kernel(Rt, phi, v, Jr_inv, Jl_inv, theta2, d, dp, rho, au, cv, inv_ds, S)
        for i in range(ns):
            for k in range(len(upper_a)):
                S_upper[i, k] = S[i, upper_a[k], upper_b[k]]


class RodNormal(NamedTuple):
    """The rod's share of the normal equations, per segment over [r_i, θ_i, r_{i+1}, θ_{i+1}]."""

    H: FloatArray
    """(N−1, 78) upper triangle of J_iᵀJ_i (rows of ``np.triu_indices(12)``), N·mm/mm² and the like."""
    g: FloatArray
    """(N−1, 12) J_iᵀρ_i."""
    S: FloatArray | None
    """(N−1, 78) upper triangle of Σ_k ρ_k ∇²ρ_k over the segment's rows, when asked for."""


def check_params(params: RodParameters) -> int:
    """Number of vertebrae N; raises ValueError on inconsistent shapes or negative stiffness."""
    ds = np.asarray(params.ds)
    if ds.ndim != 1 or len(ds) < 2:
        raise ValueError(f"ds must have shape (N−1,) with N ≥ 3, got {ds.shape}")
    if not (ds > 0.0).all():
        raise ValueError("rest lengths ds must be positive")
    for name in ("u0", "v0", "alpha", "beta"):
        shape = np.shape(getattr(params, name))
        if shape != (len(ds), 3):
            raise ValueError(f"{name} must have shape ({len(ds)}, 3), got {shape}")
    if (np.asarray(params.alpha) < 0.0).any() or (np.asarray(params.beta) < 0.0).any():
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
        Rt = R[:-1].swapaxes(1, 2)
        phi = log_so3(Rt @ R[1:])
        v = (Rt @ (r[1:] - r[:-1])[:, :, None])[:, :, 0] * self._inv_ds
        rod = out[: 6 * ns].reshape(ns, 6)
        np.multiply(self._au, phi, out=rod[:, :3])
        rod[:, :3] -= self._bu
        np.multiply(self._cv, v, out=rod[:, 3:])
        rod[:, 3:] -= self._bv
        return RodCache(Rt, phi, v)

    def local_jacobian(self, cache: RodCache) -> LocalJacobian:
        """Fill the per-segment Jacobians (N−1, 6, 12) over [r_i, θ_i, r_{i+1}, θ_{i+1}] (module
        docstring), with J_r⁻¹ = S + ½Φ and J_l⁻¹ = S − ½Φ = J_r⁻ᵀ, S = I + dΦ² = (1 − dθ²) I + d φφᵀ
        (one compiled pass over the segments)."""
        Rt, phi, v = cache
        ns = len(phi)
        Jr_inv = np.empty((ns, 3, 3))
        Jl_inv = np.empty((ns, 3, 3))
        theta2 = np.empty(ns)
        d = np.empty(ns)
        dp = np.empty(ns)
        _local_jacobian_kernel(Rt, phi, v, self._au, self._cv, self._cv_ds, self._Jloc, Jr_inv, Jl_inv, theta2, d, dp)
        return LocalJacobian(self._Jloc, Jr_inv, Jl_inv, theta2, d, dp)

    def second_order(self, cache: RodCache, local: LocalJacobian, rho: FloatArray) -> FloatArray:
        """Σ_k ρ_k ∇²ρ_k per segment (N−1, 12, 12), upper blocks only (the rest is never read).

        With λ = ρ_u ⊙ √(Δs α/2)/Δs, K± = ±½ hat(λ) + d'/θ (Φ²λ) φᵀ + d (φλᵀ − 2λφᵀ + (φ·λ) I):
            θ_i θ_i: K₋ J_l⁻¹ + ½ hat(J_l⁻ᵀλ),  θ_{i+1} θ_{i+1}: K₊ J_r⁻¹ − ½ hat(J_r⁻ᵀλ),
            θ_{i+1} θ_i: −K₊ J_l⁻¹;
        with μ = ρ_v ⊙ √(Δs β/2): θ_i θ_i += ½(μvᵀ + vμᵀ) − (μ·v) I, θ_i r_{i±1} = ±hat(μ) R_iᵀ/Δs.
        """
        _, Jr_inv, Jl_inv, theta2, d, dp = local
        Rt, phi, v = cache
        S = self._Sloc
        _second_order_kernel(Rt, phi, v, Jr_inv, Jl_inv, theta2, d, dp, rho, self._au, self._cv, self._inv_ds, S)
        return S

    def normal_blocks(self, cache: RodCache, rho: FloatArray, second_order: bool) -> RodNormal:
        """J_iᵀJ_i, J_iᵀρ_i and (when ``second_order``) Σ_k ρ_k ∇²ρ_k of every segment, upper triangles
        (``RodNormal``), for the rows ρ (N−1, 6) of ``cache``'s configuration: ``local_jacobian`` and
        ``second_order`` and their products in one compiled pass."""
        Rt, phi, v = cache
        ns = len(phi)
        H = np.empty((ns, len(_UPPER12_A)))
        g = np.empty((ns, 12))
        S_upper = np.empty((ns, len(_UPPER12_A))) if second_order else np.empty((0, 0))
        _normal_blocks_kernel(
            Rt, phi, v, rho, self._au, self._cv, self._cv_ds, self._inv_ds, _UPPER12_A, _UPPER12_B, second_order,
            self._Jloc, self._Sloc, H, g, S_upper,
        )
        return RodNormal(H, g, S_upper if second_order else None)

    def strains(self, cache: RodCache) -> tuple[FloatArray, FloatArray]:
        """(u, v) of the configuration, rad/mm and dimensionless."""
        return cache.phi * self._inv_ds, cache.v.copy()
