"""Registration of the discrete Cosserat rod to radiograph landmarks (Li et al., CAIP 2009).

Minimises E = E_f + E_I over the positions and rotations of the interior vertebrae 1..N−2, with
vertebra 0 (T1) and N−1 (L5) fixed exactly:

    E_I = ½ Σ_i Δs_i Σ_k [α_ik (u_ik − u0_ik)² + β_ik (v_ik − v0_ik)²]          (N·mm)
    E_f = Σ_views w Σ_k ‖(P(r_{idx_k}) − p_k) / s‖²                             (N·mm)

with P the weak perspective p = s·(e_c·r, e_r·r) + T. Dividing the image residual by s measures
it in patient mm, so the 3D result does not depend on the image scale or translation.

Two optional kinds of observation per view join E_f (``ViewData``; both touch one vertebra):

    offsets   w Σ_q (e_c·(r_j + R_j o_q) − (c_q − T_c)/s)²       (N·mm; o_q body-frame offset, mm)
    tilts     Σ_m w_m α_m²,  α_m = ∠(ĉ_m, E R_j e)               (N·mm; w_m in N·mm/rad²)

with c_q the image column of a point fixed in vertebra j (a pedicle centre, the inferior endplate
midpoint of its corners), ĉ_m the observed image direction of a vertebra's
transverse axis (e.g. from its four corners) and e the body-frame director the view's column
axis shows (d1 on a PA view). Formulas and derivatives: ``RegistrationProblem``.

E = ‖ρ‖² for the stacked residual vector ρ = (√(Δs α/2)(u − u0), √(Δs β/2)(v − v0),
√w (P r − p)/s), minimised by a damped Newton / Levenberg–Marquardt method with the analytic
Jacobian and second derivatives of ρ (``RegistrationProblem``). Parameters are ordered per
interior vertebra j = 1..N−2 as [δr_j (3, mm), δθ_j (3, rad)], and a step updates
r_j ← r_j + δr_j, R_j ← R_j exp(hat δθ_j) (a right, body-frame rotation increment).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg.lapack import dpbtrf, dpbtrs

from .rotations import exp_so3, hat, log_so3, rotation_between, slerp

FloatArray = NDArray[np.float64]
Pose = tuple[ArrayLike, ArrayLike]
"""(position (3,) in mm, rotation (3, 3) with the directors as columns) of a boundary vertebra."""

XTOL_MM = 1e-6
"""Convergence: a Gauss–Newton/Newton step moving no position by more than this (mm) ..."""
XTOL_RAD = 1e-8
"""... and no rotation by more than this (rad) ends the search (``RegistrationProblem.solve``)."""
FTOL = 1e-10
"""Convergence: a step predicted to lower E by at most FTOL·E + ETOL ends the search."""
ETOL = 1e-12
"""Convergence: absolute part of that energy tolerance, N·mm (for E near zero)."""

_DATA_WEIGHT = 1e6
"""initial_configuration: weight of the landmarks against the smoothing of the displacements."""
_LAMBDA_DOWN = 0.1
"""Largest decrease of the damping after a step of ideal gain ratio (Nielsen's rule has 1/3)."""
_LAMBDA0 = 1e-8
"""Initial Marquardt damping, relative to the diagonal of JᵀJ."""
_LAMBDA_GN = 1e-3
"""Damping below which a step is a Gauss–Newton step, for the stationarity test."""
_LAMBDA_MAX = 1e12
"""Damping at which the search gives up on decreasing E further."""


@dataclass(frozen=True)
class ViewData:
    """One radiograph, with its landmarks already converted to detector mm."""

    name: str
    """View name, "pa" or "lateral"."""
    indices: np.ndarray
    """(k,) int: vertebra index 0..N−1 of each landmark."""
    points: np.ndarray
    """(k, 2) image points (column, row), detector mm."""
    e_c: np.ndarray
    """(3,) patient-space unit vector of the image column direction."""
    e_r: np.ndarray
    """(3,) patient-space unit vector of the image row direction."""
    scale: float
    """Weak-perspective magnification s (dimensionless)."""
    translation: np.ndarray
    """(2,) weak-perspective translation T, detector mm."""
    weight: float
    """Fitting weight w, N/mm."""
    offset_indices: np.ndarray | None = None
    """(q,) int: vertebra index of each offset-point observation (optional)."""
    offset_vectors: np.ndarray | None = None
    """(q, 3) the point in the vertebra's body frame, o = (o1, o2, o3) along (d1, d2, d3), mm."""
    offset_columns: np.ndarray | None = None
    """(q,) image column of each point, detector mm (only the column, across the spine, is fitted)."""
    tilt_indices: np.ndarray | None = None
    """(m,) int: vertebra index of each tilt observation (optional)."""
    tilt_directions: np.ndarray | None = None
    """(m, 2) observed image direction (column, row) of the vertebra's transverse axis; any length > 0."""
    tilt_weights: np.ndarray | None = None
    """(m,) weight w_m of each tilt observation, N·mm/rad²."""
    tilt_director: np.ndarray | None = None
    """(3,) body-frame director e whose projection the tilts observe (e.g. (1, 0, 0) = d1 on PA)."""

    @property
    def n_offsets(self) -> int:
        return 0 if self.offset_indices is None else len(self.offset_indices)

    @property
    def n_tilts(self) -> int:
        return 0 if self.tilt_indices is None else len(self.tilt_indices)


@dataclass(frozen=True)
class RodParameters:
    """Rest shape and stiffness of the rod; N−1 segments."""

    ds: np.ndarray
    """(N−1,) rest lengths Δs, mm."""
    u0: np.ndarray
    """(N−1, 3) rest angular strains, rad/mm."""
    v0: np.ndarray
    """(N−1, 3) rest linear strains (dimensionless)."""
    alpha: np.ndarray
    """(N−1, 3) bending (α1, α2) and twisting (α3) stiffness, N·mm²."""
    beta: np.ndarray
    """(N−1, 3) shear (β1, β2) and axial (β3) stiffness, N."""


@dataclass(frozen=True)
class FitOutput:
    """Result of ``fit``."""

    positions: np.ndarray
    """(N, 3) vertebra positions, mm (LPS)."""
    rotations: np.ndarray
    """(N, 3, 3) rotations, directors as columns."""
    u: np.ndarray
    """(N−1, 3) angular strains, rad/mm."""
    v: np.ndarray
    """(N−1, 3) linear strains."""
    energy_fit: float
    """E_f, N·mm."""
    energy_internal: float
    """E_I, N·mm."""
    iterations: int
    """Accepted (Newton / Levenberg–Marquardt) steps."""
    converged: bool
    """Whether a convergence criterion of ``RegistrationProblem.solve`` was met."""
    residuals_mm: dict[str, np.ndarray]
    """Per view name, (k,) distance between landmark and projected vertebra in patient mm."""
    offset_residuals_mm: dict[str, np.ndarray] = field(default_factory=dict)
    """Per view name with offset points, (q,) signed column residual e_c·(r + R o) − (c − T_c)/s, patient mm."""
    tilt_residuals_deg: dict[str, np.ndarray] = field(default_factory=dict)
    """Per view name with tilts, (m,) signed angle α from the observed to the model's axis, degrees."""


def _check_params(params: RodParameters) -> int:
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


def _shape(a: np.ndarray | None) -> tuple[int, ...]:
    return () if a is None else tuple(np.shape(a))


def _check_view(view: ViewData, n: int) -> None:
    idx = np.asarray(view.indices)
    pts = np.asarray(view.points)
    if idx.ndim != 1 or pts.shape != (len(idx), 2):
        raise ValueError(f"view {view.name!r}: indices (k,) and points (k, 2) expected, got {idx.shape}, {pts.shape}")
    if len(idx) and (idx.min() < 0 or idx.max() >= n):
        raise ValueError(f"view {view.name!r}: landmark indices must lie in 0..{n - 1}")
    if not view.scale > 0.0:
        raise ValueError(f"view {view.name!r}: scale must be positive, got {view.scale}")
    if not view.weight >= 0.0:
        raise ValueError(f"view {view.name!r}: weight must be non-negative, got {view.weight}")
    if view.n_offsets:
        q = view.n_offsets
        pi = np.asarray(view.offset_indices)
        if (
            pi.ndim != 1
            or _shape(view.offset_vectors) != (q, 3)
            or _shape(view.offset_columns) != (q,)
        ):
            raise ValueError(f"view {view.name!r}: offset indices (q,), vectors (q, 3) and columns (q,) expected")
        if pi.min() < 0 or pi.max() >= n:
            raise ValueError(f"view {view.name!r}: offset indices must lie in 0..{n - 1}")
    if view.n_tilts:
        m = view.n_tilts
        ti = np.asarray(view.tilt_indices)
        if ti.ndim != 1 or _shape(view.tilt_directions) != (m, 2) or _shape(view.tilt_weights) != (m,):
            raise ValueError(f"view {view.name!r}: tilt indices (m,), directions (m, 2) and weights (m,) expected")
        if ti.min() < 0 or ti.max() >= n:
            raise ValueError(f"view {view.name!r}: tilt indices must lie in 0..{n - 1}")
        if _shape(view.tilt_director) != (3,):
            raise ValueError(f"view {view.name!r}: tilts need a tilt_director (3,)")
        if np.any(np.linalg.norm(np.asarray(view.tilt_directions, dtype=float), axis=1) <= 0.0):
            raise ValueError(f"view {view.name!r}: tilt directions must be non-zero")
        if np.any(~(np.asarray(view.tilt_weights, dtype=float) >= 0.0)):
            raise ValueError(f"view {view.name!r}: tilt weights must be non-negative")


def _pose(pose: Pose, name: str) -> tuple[FloatArray, FloatArray]:
    r = np.array(pose[0], dtype=float)
    R = np.array(pose[1], dtype=float)
    if r.shape != (3,) or R.shape != (3, 3):
        raise ValueError(f"{name} must be (position (3,), rotation (3, 3)), got {r.shape}, {R.shape}")
    return r, R


_KD = 11
"""Half-bandwidth of the normal matrix: a segment couples two vertebrae of 6 unknowns each."""


def _jr_inv_coefficients(theta2: FloatArray) -> tuple[FloatArray, FloatArray]:
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


_UPPER3 = np.triu_indices(3)


def _accumulate(bins: NDArray[np.intp], weights: FloatArray, minlength: int) -> FloatArray:
    """Sum of ``weights`` per bin (numpy's bincount, typed as the float array it returns)."""
    return cast(FloatArray, np.bincount(bins, weights, minlength=minlength))


@lru_cache(maxsize=8)
def _band_layout(n: int) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """Index tables of the per-segment 12×12 blocks in band storage, for N = n vertebrae.

    Returns the flat positions of the upper-triangle entries in a 12×12 block, their bins in two
    stacked band matrices (KD + 1, 6n) (Gauss–Newton part, then second-order part), and the bins
    of the 12 gradient entries of each segment in a vector of 6n.
    """
    n_ext = 6 * n
    a, b = np.triu_indices(12)
    seg = np.arange(n - 1)[:, None]
    bins = ((_KD + a - b) * n_ext + 6 * seg + b).ravel()
    hbins = np.concatenate((bins, bins + (_KD + 1) * n_ext))
    gbins = (6 * seg + np.arange(12)).ravel()
    for table in (hbins, gbins):
        table.flags.writeable = False
    return a * 12 + b, hbins, gbins


class RegistrationProblem:
    """Residual vector ρ, its analytic Jacobian and the Newton normal equations, for fixed data.

    Residual layout (E = ‖ρ‖², N·mm): for each segment i = 0..N−2 six rows,
    √(Δs_i α_i/2)(u_i − u0_i) then √(Δs_i β_i/2)(v_i − v0_i); then, view after view and landmark
    after landmark, the two rows √w (P r_idx − p)/s (patient mm · √(N/mm)).

    Columns: 6(j−1)..6(j−1)+2 are δr_j (mm) and 6(j−1)+3..6(j−1)+5 are δθ_j (rad) for
    j = 1..N−2, with the perturbation r_j + δr_j, R_j exp(hat δθ_j) (see ``retract``).

    Jacobian blocks, with φ_i = log(R_iᵀ R_{i+1}) = Δs_i u_i:
        ∂u_i/∂δθ_{i+1} = J_r⁻¹(φ_i)/Δs_i,  ∂u_i/∂δθ_i = −J_l⁻¹(φ_i)/Δs_i,
        ∂v_i/∂δθ_i = hat(v_i),  ∂v_i/∂r_{i+1} = R_iᵀ/Δs_i = −∂v_i/∂r_i,
        ∂(P r − p)/s / ∂r = [e_c; e_r] (constant).
    Each segment touches two neighbouring vertebrae and each landmark one, so the normal matrix
    is banded (half-bandwidth 11) and is assembled and factored in LAPACK band storage.

    Optional rows after the landmarks (``ViewData``), each touching one vertebra j:

    * an offset point (pedicle centre, inferior endplate midpoint), one row
      ρ = √w (e_c·(r_j + R_j o) − (c − T_c)/s) (patient mm · √(N/mm)):
        ∂ρ/∂δr_j = √w e_c,  ∂ρ/∂δθ_j = o × (R_jᵀ √w e_c),
        ∇²_θθ ρ = ½(ω oᵀ + o ωᵀ) − (ω·o) I with ω = R_jᵀ √w e_c;
    * a tilt, one row ρ = √w_m α (rad · √(N·mm)), α = atan2(ĉ × a, ĉ·a) the signed angle from the
      observed unit direction ĉ to the projected director a = E R_j e (E = [e_c; e_r]):
        ∂a/∂δθ_j = A with rows e × (R_jᵀ E_k), k = column, row;  ∂α/∂a = a⊥/|a|², a⊥ = (−a_row, a_col);
        ∂ρ/∂δθ_j = √w_m Aᵀ a⊥/|a|²;
        ∇²_θθ ρ = √w_m (Aᵀ H_a A + ½(ω eᵀ + e ωᵀ) − (ω·e) I), ω = R_jᵀ Eᵀ a⊥/|a|², and H_a the
        Hessian of atan2(a_row, a_col): [[2xy, y² − x²], [y² − x², −2xy]]/|a|⁴, (x, y) = a.
    (With a right perturbation R exp(hat δθ), ∂(R exp(hat δθ) b)/∂δθ = −R hat(b) and the second
    derivative of cᵀR exp(hat δθ) b is ½(ω bᵀ + b ωᵀ) − (ω·b) I with ω = Rᵀc.)
    """

    def __init__(self, params: RodParameters, views: list[ViewData] | tuple[ViewData, ...], top: Pose, bottom: Pose):
        n = _check_params(params)
        for view in views:
            _check_view(view, n)
        names = [view.name for view in views]
        if len(set(names)) != len(names):
            raise ValueError(f"view names must be distinct, got {names}")
        self.n = n
        self.n_params = 6 * (n - 2)
        self.views = tuple(views)
        self.top = _pose(top, "top")
        self.bottom = _pose(bottom, "bottom")
        self.params = params
        ns = n - 1
        n_ext = 6 * n
        ds = np.asarray(params.ds, dtype=float)
        self.ds = ds
        cu = np.sqrt(0.5 * ds[:, None] * np.asarray(params.alpha, dtype=float))
        cv = np.sqrt(0.5 * ds[:, None] * np.asarray(params.beta, dtype=float))
        self._au = cu / ds[:, None]
        self._bu = cu * np.asarray(params.u0, dtype=float)
        self._cv = cv
        self._cv_ds = cv / ds[:, None]
        self._bv = cv * np.asarray(params.v0, dtype=float)
        self._inv_ds = 1.0 / ds[:, None]

        # Fit rows: ρ_f = √w (E r_idx − (p − T)/s), E = [e_c; e_r].
        idx, E1, t1, sw, slices = [], [], [], [], {}
        start = 0
        for view in self.views:
            k = len(view.indices)
            idx.append(np.asarray(view.indices, dtype=int))
            E = np.stack((np.asarray(view.e_c, dtype=float), np.asarray(view.e_r, dtype=float)))
            E1.append(np.broadcast_to(E, (k, 2, 3)))
            t1.append((np.asarray(view.points, dtype=float) - np.asarray(view.translation, dtype=float)) / view.scale)
            sw.append(np.full(k, np.sqrt(float(view.weight))))
            slices[view.name] = slice(start, start + k)
            start += k
        self._fit_idx = np.concatenate(idx) if idx else np.zeros(0, dtype=int)
        self._fit_E1 = np.concatenate(E1) if E1 else np.zeros((0, 2, 3))
        self._fit_t1 = np.concatenate(t1) if t1 else np.zeros((0, 2))
        sqrt_w = np.concatenate(sw) if sw else np.zeros(0)
        self._fit_E = sqrt_w[:, None, None] * self._fit_E1
        self._fit_ET = np.ascontiguousarray(np.swapaxes(self._fit_E, 1, 2))
        self._fit_target = sqrt_w[:, None] * self._fit_t1
        self._fit_slices = slices
        self.n_fit = 2 * start
        self._init_extras(n_ext)
        self.n_residuals = 6 * ns + self.n_fit + self.n_offsets + self.n_tilts
        self._buffers = [np.empty(self.n_residuals), np.empty(self.n_residuals)]

        # Band storage (upper, LAPACK): ab[KD + I − J, J] = H[I, J] for J − KD ≤ I ≤ J, over an
        # extended index 6·vertebra + k that includes the fixed ends, sliced off after assembly.
        self._n_ext = n_ext
        self._band_size = (_KD + 1) * n_ext
        self._upper, self._hbins, gbins_rod = _band_layout(n)
        fit_cols = (6 * self._fit_idx[:, None] + np.arange(3)).ravel()
        self._gbins = np.concatenate((gbins_rod, fit_cols))
        fa, fb = _UPPER3
        HfT = (self._fit_ET @ self._fit_E).reshape(-1, 9)[:, 3 * fa + fb]
        fJ = 6 * self._fit_idx[:, None] + fb
        fbins = (_KD + fa - fb) * n_ext + fJ
        ab_fit = _accumulate(fbins.ravel(), HfT.ravel(), minlength=self._band_size)
        self._ab_fit = ab_fit.reshape(_KD + 1, n_ext)[:, 6:-6].copy()

        self._Jloc = np.zeros((ns, 6, 12))
        self._Sloc = np.zeros((ns, 12, 12))
        self._m = n - 2

    def _init_extras(self, n_ext: int) -> None:
        """Stack the offset-point and tilt observations of every view, and their band/gradient bins."""
        p_idx, p_o, p_ec, p_t, p_sw = [], [], [], [], []
        t_idx, t_e, t_E, t_c, t_sw = [], [], [], [], []
        self._ped_slices: dict[str, slice] = {}
        self._tilt_slices: dict[str, slice] = {}
        q0 = m0 = 0
        for view in self.views:
            sw = np.sqrt(float(view.weight))
            e_c = np.asarray(view.e_c, dtype=float)
            if view.n_offsets:
                q = view.n_offsets
                p_idx.append(np.asarray(view.offset_indices, dtype=int))
                p_o.append(np.asarray(view.offset_vectors, dtype=float))
                p_ec.append(np.broadcast_to(e_c, (q, 3)))
                p_sw.append(np.full(q, sw))
                columns = np.asarray(view.offset_columns, dtype=float)
                p_t.append((columns - float(np.asarray(view.translation, dtype=float)[0])) / view.scale)
                self._ped_slices[view.name] = slice(q0, q0 + q)
                q0 += q
            if view.n_tilts:
                m = view.n_tilts
                E = np.stack((e_c, np.asarray(view.e_r, dtype=float)))
                d = np.asarray(view.tilt_directions, dtype=float)
                t_idx.append(np.asarray(view.tilt_indices, dtype=int))
                t_e.append(np.broadcast_to(np.asarray(view.tilt_director, dtype=float), (m, 3)))
                t_E.append(np.broadcast_to(E, (m, 2, 3)))
                t_c.append(d / np.linalg.norm(d, axis=1)[:, None])
                t_sw.append(np.sqrt(np.asarray(view.tilt_weights, dtype=float)))
                self._tilt_slices[view.name] = slice(m0, m0 + m)
                m0 += m
        self.n_offsets = q0
        self.n_tilts = m0
        self._ped_idx = np.concatenate(p_idx) if p_idx else np.zeros(0, dtype=int)
        self._ped_o = np.concatenate(p_o) if p_o else np.zeros((0, 3))
        self._ped_e1 = np.concatenate(p_ec) if p_ec else np.zeros((0, 3))
        self._ped_t1 = np.concatenate(p_t) if p_t else np.zeros(0)
        ped_sw = np.concatenate(p_sw) if p_sw else np.zeros(0)
        self._ped_ec = ped_sw[:, None] * self._ped_e1
        self._ped_target = ped_sw * self._ped_t1
        self._tilt_idx = np.concatenate(t_idx) if t_idx else np.zeros(0, dtype=int)
        self._tilt_e = np.concatenate(t_e) if t_e else np.zeros((0, 3))
        self._tilt_E = np.concatenate(t_E) if t_E else np.zeros((0, 2, 3))
        self._tilt_c = np.concatenate(t_c) if t_c else np.zeros((0, 2))
        self._tilt_sw = np.concatenate(t_sw) if t_sw else np.zeros(0)
        idx = np.concatenate((self._ped_idx, self._tilt_idx))
        self._x_idx = idx
        a6, b6 = np.triu_indices(6)
        self._x_upper6 = a6 * 6 + b6
        self._x_hbins = ((_KD + a6 - b6) * n_ext + 6 * idx[:, None] + b6).ravel()
        a3, b3 = _UPPER3
        self._x_upper3 = a3 * 3 + b3
        self._x_sbins = ((_KD + a3 - b3) * n_ext + 6 * idx[:, None] + 3 + b3).ravel()
        self._x_gbins = (6 * idx[:, None] + np.arange(6)).ravel()

    def _evaluate_extras(self, r: FloatArray, R: FloatArray, out: FloatArray) -> None:
        """Write the offset-point and tilt rows of ρ into ``out`` (its tail after the landmark rows)."""
        start = 6 * (self.n - 1) + self.n_fit
        q = self.n_offsets
        if q:
            Ro = (R[self._ped_idx] @ self._ped_o[:, :, None])[:, :, 0]
            out[start : start + q] = np.einsum("ij,ij->i", self._ped_ec, r[self._ped_idx] + Ro) - self._ped_target
        if self.n_tilts:
            a = self._tilt_projection(R)
            c = self._tilt_c
            cross = c[:, 0] * a[:, 1] - c[:, 1] * a[:, 0]
            dot = c[:, 0] * a[:, 0] + c[:, 1] * a[:, 1]
            out[start + q :] = self._tilt_sw * np.arctan2(cross, dot)

    def _tilt_projection(self, R: FloatArray) -> FloatArray:
        """a = E R_j e (m, 2): the image direction of each observed vertebra's director."""
        return (self._tilt_E @ (R[self._tilt_idx] @ self._tilt_e[:, :, None]))[:, :, 0]

    def _extra_jacobian(self, R: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Rows (q + m, 6) of ∂ρ/∂[δr_j, δθ_j] of the offset-point and tilt observations, and what the
        second derivatives reuse: ω of the offset points (q, 3), A (m, 2, 3) and a⊥/|a|² (m, 2) of the tilts."""
        q, m = self.n_offsets, self.n_tilts
        J = np.zeros((q + m, 6))
        omega_p = np.einsum("nji,nj->ni", R[self._ped_idx], self._ped_ec) if q else np.zeros((0, 3))
        if q:
            J[:q, :3] = self._ped_ec
            J[:q, 3:] = np.cross(self._ped_o, omega_p)
        A = np.zeros((m, 2, 3))
        ga = np.zeros((m, 2))
        if m:
            Rs = R[self._tilt_idx]
            W = np.einsum("nji,nkj->nki", Rs, self._tilt_E)  # W[n, k] = R_jᵀ E_k
            A = np.cross(self._tilt_e[:, None, :], W)
            a = self._tilt_projection(R)
            ga = np.stack((-a[:, 1], a[:, 0]), axis=1) / np.einsum("ij,ij->i", a, a)[:, None]
            J[q:, 3:] = self._tilt_sw[:, None] * np.einsum("nki,nk->ni", A, ga)
        return J, omega_p, A, ga

    def _extra_second_order(
        self, R: FloatArray, rho: FloatArray, omega_p: FloatArray, A: FloatArray, ga: FloatArray
    ) -> FloatArray:
        """ρ ∇²_θθ ρ of each offset-point and tilt row (q + m, 3, 3); formulas in the class docstring."""
        q, m = self.n_offsets, self.n_tilts
        S = np.zeros((q + m, 3, 3))
        eye = np.eye(3)

        def rotational(omega: FloatArray, b: FloatArray) -> FloatArray:
            outer = omega[:, :, None] * b[:, None, :]
            return 0.5 * (outer + np.swapaxes(outer, 1, 2)) - np.einsum("ij,ij->i", omega, b)[:, None, None] * eye

        if q:
            S[:q] = rho[:q, None, None] * rotational(omega_p, self._ped_o)
        if m:
            a = self._tilt_projection(R)
            x, y = a[:, 0], a[:, 1]
            r4 = np.einsum("ij,ij->i", a, a) ** 2
            Ha = np.empty((m, 2, 2))
            Ha[:, 0, 0] = 2.0 * x * y / r4
            Ha[:, 1, 1] = -Ha[:, 0, 0]
            Ha[:, 0, 1] = Ha[:, 1, 0] = (y * y - x * x) / r4
            omega_t = np.einsum("nji,nkj,nk->ni", R[self._tilt_idx], self._tilt_E, ga)
            hess = np.swapaxes(A, 1, 2) @ Ha @ A + rotational(omega_t, self._tilt_e)
            S[q:] = (rho[q:] * self._tilt_sw)[:, None, None] * hess
        return S

    def _extra_normal_equations(
        self, res: FloatArray, R: FloatArray, second_order: bool
    ) -> tuple[FloatArray, FloatArray | None, FloatArray]:
        """Band JᵀJ, band Σ ρ∇²ρ (or None) and Jᵀρ of the offset-point and tilt rows, over the unknowns."""
        start = 6 * (self.n - 1) + self.n_fit
        rho = res[start:]
        J, omega_p, A, ga = self._extra_jacobian(R)
        gn = (J[:, :, None] * J[:, None, :]).reshape(-1, 36)[:, self._x_upper6]
        ab = _accumulate(self._x_hbins, gn.ravel(), minlength=self._band_size)
        ab_gn = ab.reshape(_KD + 1, self._n_ext)[:, 6:-6]
        g = _accumulate(self._x_gbins, (J * rho[:, None]).ravel(), minlength=self._n_ext)[6:-6]
        if not second_order:
            return ab_gn, None, g
        S = self._extra_second_order(R, rho, omega_p, A, ga).reshape(-1, 9)[:, self._x_upper3]
        ab2 = _accumulate(self._x_sbins, S.ravel(), minlength=self._band_size)
        return ab_gn, ab2.reshape(_KD + 1, self._n_ext)[:, 6:-6], g

    # ------------------------------------------------------------------ configuration helpers

    def with_boundary(self, positions: ArrayLike, rotations: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Copies of (positions, rotations) with vertebrae 0 and N−1 set exactly to top and bottom."""
        r = np.array(positions, dtype=float)
        R = np.array(rotations, dtype=float)
        if r.shape != (self.n, 3) or R.shape != (self.n, 3, 3):
            raise ValueError(
                f"expected positions ({self.n}, 3) and rotations ({self.n}, 3, 3), got {r.shape}, {R.shape}"
            )
        r[0], R[0] = self.top
        r[-1], R[-1] = self.bottom
        return r, R

    def retract(self, positions: FloatArray, rotations: FloatArray, delta: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """New configuration r_j + δr_j, R_j exp(hat δθ_j) for the interior vertebrae (copies)."""
        d = np.asarray(delta, dtype=float).reshape(self._m, 6)
        r = positions.copy()
        R = rotations.copy()
        r[1:-1] += d[:, :3]
        R[1:-1] = rotations[1:-1] @ exp_so3(d[:, 3:])
        return r, R

    # ------------------------------------------------------------------ residual and derivatives

    def _evaluate(self, r: FloatArray, R: FloatArray, out: FloatArray) -> tuple[FloatArray, ...]:
        """Write ρ into ``out``; return the per-segment quantities the derivatives reuse."""
        ns = self.n - 1
        Rt = np.swapaxes(R[:-1], 1, 2)
        phi = log_so3(Rt @ R[1:])
        v = (Rt @ (r[1:] - r[:-1])[:, :, None])[:, :, 0] * self._inv_ds
        rod = out[: 6 * ns].reshape(ns, 6)
        np.multiply(self._au, phi, out=rod[:, :3])
        rod[:, :3] -= self._bu
        np.multiply(self._cv, v, out=rod[:, 3:])
        rod[:, 3:] -= self._bv
        fit = out[6 * ns : 6 * ns + self.n_fit].reshape(-1, 2, 1)
        np.matmul(self._fit_E, r[self._fit_idx, :, None], out=fit)
        fit[:, :, 0] -= self._fit_target
        if self.n_offsets or self.n_tilts:
            self._evaluate_extras(r, R, out)
        return Rt, phi, v, R

    def _local_jacobian(self, cache: tuple[FloatArray, ...]) -> tuple[FloatArray, ...]:
        """Fill the per-segment Jacobians (N−1, 6, 12) over [r_i, θ_i, r_{i+1}, θ_{i+1}]."""
        Rt, phi, v = cache[:3]
        theta2 = np.einsum("ij,ij->i", phi, phi)
        d, dp = _jr_inv_coefficients(theta2)
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
        return J, Jr_inv, Jl_inv, theta2, d, dp

    def _second_order(
        self, cache: tuple[FloatArray, ...], local: tuple[FloatArray, ...], rho: FloatArray
    ) -> FloatArray:
        """Σ_k ρ_k ∇²ρ_k per segment (N−1, 12, 12), upper blocks only (the rest is never read).

        With λ = ρ_u ⊙ √(Δs α/2)/Δs, K± = ±½ hat(λ) + d'/θ (Φ²λ) φᵀ + d (φλᵀ − 2λφᵀ + (φ·λ) I):
            θ_i θ_i: K₋ J_l⁻¹ + ½ hat(J_l⁻ᵀλ),  θ_{i+1} θ_{i+1}: K₊ J_r⁻¹ − ½ hat(J_r⁻ᵀλ),
            θ_{i+1} θ_i: −K₊ J_l⁻¹;
        with μ = ρ_v ⊙ √(Δs β/2): θ_i θ_i += ½(μvᵀ + vμᵀ) − (μ·v) I, θ_i r_{i±1} = ±hat(μ) R_iᵀ/Δs.
        """
        Rt, phi, v = cache[:3]
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

    def _normal_equations(
        self, res: FloatArray, cache: tuple[FloatArray, ...], second_order: bool
    ) -> tuple[FloatArray, FloatArray | None, FloatArray]:
        """Band JᵀJ, band Σ_k ρ_k ∇²ρ_k (when ``second_order``, else None) and Jᵀρ, over the unknowns."""
        ns = self.n - 1
        local = self._local_jacobian(cache)
        J = local[0]
        JT = np.swapaxes(J, 1, 2)
        rho = res[: 6 * ns].reshape(ns, 6)
        H = (JT @ J).reshape(ns, 144)[:, self._upper]
        gloc = (JT @ rho[:, :, None]).ravel()
        gfit = (self._fit_ET @ res[6 * ns : 6 * ns + self.n_fit].reshape(-1, 2, 1)).ravel()
        g = _accumulate(self._gbins, np.concatenate((gloc, gfit)), minlength=self._n_ext)[6:-6]
        extra = (
            self._extra_normal_equations(res, cache[3], second_order) if self.n_offsets or self.n_tilts else None
        )
        if extra is not None:
            g = g + extra[2]
        if not second_order:
            ab = _accumulate(self._hbins[: H.size], H.ravel(), minlength=self._band_size)
            ab_gn = ab.reshape(_KD + 1, self._n_ext)[:, 6:-6] + self._ab_fit
            return (ab_gn if extra is None else ab_gn + extra[0]), None, g
        S = self._second_order(cache, local, rho).reshape(ns, 144)[:, self._upper]
        both = _accumulate(self._hbins, np.concatenate((H.ravel(), S.ravel())), minlength=2 * self._band_size)
        both = both.reshape(2, _KD + 1, self._n_ext)[:, :, 6:-6]
        if extra is not None:
            assert extra[1] is not None
            return both[0] + self._ab_fit + extra[0], both[1] + extra[1], g
        return both[0] + self._ab_fit, both[1], g

    def residuals(self, positions: ArrayLike, rotations: ArrayLike) -> FloatArray:
        """Residual vector ρ (layout in the class docstring) of a configuration; E = ‖ρ‖² in N·mm."""
        r, R = self.with_boundary(positions, rotations)
        out = np.empty(self.n_residuals)
        self._evaluate(r, R, out)
        return out

    def jacobian(self, positions: ArrayLike, rotations: ArrayLike) -> FloatArray:
        """Analytic Jacobian ∂ρ/∂(δr_j, δθ_j), shape (n_residuals, 6(N−2)), dense."""
        r, R = self.with_boundary(positions, rotations)
        J_loc = self._local_jacobian(self._evaluate(r, R, np.empty(self.n_residuals)))[0]
        ns = self.n - 1
        J = np.zeros((self.n_residuals, self._n_ext))
        for i in range(ns):
            J[6 * i : 6 * i + 6, 6 * i : 6 * i + 12] = J_loc[i]
        for k, j in enumerate(self._fit_idx):
            J[6 * ns + 2 * k : 6 * ns + 2 * k + 2, 6 * j : 6 * j + 3] = self._fit_E[k]
        if self.n_offsets or self.n_tilts:
            Jx = self._extra_jacobian(R)[0]
            start = 6 * ns + self.n_fit
            for k, j in enumerate(self._x_idx):
                J[start + k, 6 * j : 6 * j + 6] = Jx[k]
        return J[:, 6:-6]

    def gradient_and_hessian(
        self, positions: ArrayLike, rotations: ArrayLike, second_order: bool = True
    ) -> tuple[FloatArray, FloatArray]:
        """(Jᵀρ, JᵀJ + Σ_k ρ_k ∇²ρ_k), dense; ½ the gradient and Hessian of E(retract(x, δ)) at δ = 0.

        Without ``second_order`` the matrix is the Gauss–Newton JᵀJ.
        """
        r, R = self.with_boundary(positions, rotations)
        res = np.empty(self.n_residuals)
        cache = self._evaluate(r, R, res)
        ab_gn, ab_2, g = self._normal_equations(res, cache, second_order)
        return g, _band_to_dense(ab_gn if ab_2 is None else ab_gn + ab_2)

    def energy(self, positions: ArrayLike, rotations: ArrayLike) -> float:
        """E = E_f + E_I = ‖ρ‖², N·mm."""
        res = self.residuals(positions, rotations)
        return float(res @ res)

    # ------------------------------------------------------------------ minimisation

    def solve(self, positions: ArrayLike, rotations: ArrayLike, max_iterations: int = 100) -> FitOutput:
        """Damped Newton (Levenberg–Marquardt) from (positions, rotations); ends reset to top and bottom.

        Each iteration solves (H + λD) h = −Jᵀρ in band storage (LAPACK dpbtrf/dpbtrs). The first
        iteration uses the Gauss–Newton H = JᵀJ (at the initial configuration the large residuals
        make the second-order terms misleading); later ones the Newton H = JᵀJ + Σ_k ρ_k ∇²ρ_k,
        the exact Hessian of E/2 in the chart δ ↦ (r + δr, R exp(hat δθ)), falling back to
        Gauss–Newton at the same λ when that matrix is not positive definite or its step does
        not lower E. D is the running maximum of diag(JᵀJ); λ starts at 1e-8 and follows
        Nielsen's rule (× max(0.1, 1 − (2ϱ − 1)³) on success, × 2, 4, 8, … on failure), with ϱ
        the ratio of actual to predicted decrease. A trial step is accepted when it lowers E.

        Convergence (with λ ≤ 1e-3, so that the step is not a damped one):
          * the step moves every position by ≤ XTOL_MM = 1e-6 mm and every rotation by
            ≤ XTOL_RAD = 1e-8 rad, or
          * its predicted decrease of E (the Newton decrement) is ≤ FTOL·E + ETOL with
            FTOL = 1e-10 and ETOL = 1e-12 N·mm, i.e. what is left is at the level of rounding;
        that last step is applied when it lowers E. Also converged: an accepted step that is
        within XTOL_MM / XTOL_RAD and lowered E by ≤ FTOL·E + ETOL. ``iterations`` counts
        accepted steps; reaching ``max_iterations`` of them, or λ > 1e12 without a decrease
        (non-finite data), ends the search unconverged.

        Not thread-safe on one instance (it reuses work buffers); ``fit`` makes a new one per call.
        """
        r, R = self.with_boundary(positions, rotations)
        res, res_t = self._buffers
        cache = self._evaluate(r, R, res)
        E = float(res @ res)
        lam = _LAMBDA0
        nu = 2.0
        D = np.zeros(self.n_params)
        iterations = 0
        converged = False
        m = self._m
        newton = False
        while iterations < max_iterations:
            ab_gn, ab_2, g = self._normal_equations(res, cache, second_order=newton)
            np.maximum(D, ab_gn[_KD], out=D)
            Dd = np.where(D > 0.0, D, 1.0)
            ab = ab_gn if ab_2 is None else ab_gn + ab_2
            accepted = False
            while lam <= _LAMBDA_MAX:
                A = ab.copy()
                A[_KD] += lam * Dd
                c, info = dpbtrf(A, overwrite_ab=1)
                if info == 0:
                    h = dpbtrs(c, -g[:, None])[0][:, 0]
                    hm = np.abs(h.reshape(m, 6))
                    small = hm[:, :3].max() <= XTOL_MM and hm[:, 3:].max() <= XTOL_RAD
                    predicted = float(lam * (h * Dd) @ h - h @ g)
                    final = lam <= _LAMBDA_GN and (small or predicted <= FTOL * E + ETOL)
                    r_t, R_t = self.retract(r, R, h)
                    cache_t = self._evaluate(r_t, R_t, res_t)
                    E_t = float(res_t @ res_t)
                    if E_t < E:
                        # From the initial configuration the second-order terms, weighted by
                        # its large residuals, mislead: the first step is Gauss–Newton.
                        newton = True
                        rho = (E - E_t) / predicted if predicted > 0.0 else 1.0
                        lam *= max(_LAMBDA_DOWN, 1.0 - (2.0 * rho - 1.0) ** 3)
                        nu = 2.0
                        accepted = True
                        iterations += 1
                        converged = final or (small and E - E_t <= FTOL * E + ETOL)
                        r, R, E, cache = r_t, R_t, E_t, cache_t
                        res, res_t = res_t, res
                        break
                    if final:
                        # Nothing left above rounding: the current point is the minimum.
                        converged = True
                        break
                if ab is not ab_gn:
                    # The Newton model failed (indefinite, or its step did not lower E): retry
                    # with Gauss–Newton at the same damping before damping more.
                    ab = ab_gn
                    continue
                lam *= nu
                nu *= 2.0
            if converged or not accepted:
                break
        return self._output(r, R, res, cache, iterations, converged)

    def _output(
        self,
        r: FloatArray,
        R: FloatArray,
        res: FloatArray,
        cache: tuple[FloatArray, ...],
        iterations: int,
        converged: bool,
    ) -> FitOutput:
        phi, v = cache[1], cache[2]
        rod = res[: 6 * (self.n - 1)]
        fit = res[6 * (self.n - 1) :]
        diff = (self._fit_E1 @ r[self._fit_idx, :, None])[:, :, 0] - self._fit_t1
        distance = np.sqrt(np.einsum("ij,ij->i", diff, diff))
        # unweighted residuals (a zero weight would hide them in ρ)
        Ro = (R[self._ped_idx] @ self._ped_o[:, :, None])[:, :, 0]
        ped = np.einsum("ij,ij->i", self._ped_e1, r[self._ped_idx] + Ro) - self._ped_t1
        a = self._tilt_projection(R)
        c = self._tilt_c
        tilt = np.degrees(np.arctan2(c[:, 0] * a[:, 1] - c[:, 1] * a[:, 0], np.einsum("ij,ij->i", c, a)))
        return FitOutput(
            positions=r,
            rotations=R,
            u=phi * self._inv_ds,
            v=v.copy(),
            energy_fit=float(fit @ fit),
            energy_internal=float(rod @ rod),
            iterations=iterations,
            converged=converged,
            residuals_mm={name: distance[sl] for name, sl in self._fit_slices.items()},
            offset_residuals_mm={name: ped[sl].copy() for name, sl in self._ped_slices.items()},
            tilt_residuals_deg={name: tilt[sl].copy() for name, sl in self._tilt_slices.items()},
        )


def _band_to_dense(ab: FloatArray) -> FloatArray:
    """Symmetric dense matrix from LAPACK upper band storage ab[KD + i − j, j] = H[i, j]."""
    kd = ab.shape[0] - 1
    n = ab.shape[1]
    H = np.zeros((n, n))
    for off in range(kd + 1):
        i = np.arange(n - off)
        H[i, i + off] = ab[kd - off, off:]
        H[i + off, i] = ab[kd - off, off:]
    return H


def residuals(
    params: RodParameters, views: list[ViewData], top: Pose, bottom: Pose, positions: ArrayLike, rotations: ArrayLike
) -> FloatArray:
    """Stacked residual vector ρ of a configuration (layout in ``RegistrationProblem``); E = ‖ρ‖²."""
    return RegistrationProblem(params, views, top, bottom).residuals(positions, rotations)


def jacobian(
    params: RodParameters, views: list[ViewData], top: Pose, bottom: Pose, positions: ArrayLike, rotations: ArrayLike
) -> FloatArray:
    """Analytic Jacobian of ``residuals`` w.r.t. (δr_j, δθ_j), j = 1..N−2; see ``RegistrationProblem``."""
    return RegistrationProblem(params, views, top, bottom).jacobian(positions, rotations)


def fit(
    params: RodParameters,
    views: list[ViewData],
    top: Pose,
    bottom: Pose,
    init_positions: ArrayLike,
    init_rotations: ArrayLike,
    max_iterations: int = 100,
) -> FitOutput:
    """Register the rod to the landmarks of ``views`` with T1 = ``top`` and L5 = ``bottom`` fixed.

    Minimises E = E_f + E_I (module docstring) by Levenberg–Marquardt from the initial
    configuration; convergence criteria in ``RegistrationProblem.solve``. The output's vertebrae
    0 and N−1 are bit-for-bit ``top`` and ``bottom``.
    """
    return RegistrationProblem(params, views, top, bottom).solve(init_positions, init_rotations, max_iterations)


def initial_configuration(
    rest_positions: ArrayLike,
    rest_rotations: ArrayLike,
    views: list[ViewData],
    top: Pose,
    bottom: Pose,
) -> tuple[FloatArray, FloatArray]:
    """A starting configuration for ``fit``: the rest shape bent between the fixed ends, moved onto the landmarks.

    1. Blend: rigid motions G_a, G_b take the rest T1 pose onto ``top`` and the rest L5 pose onto
       ``bottom``; vertebra i with arc-length fraction t_i goes to (1 − t_i) G_a r_i + t_i G_b r_i
       with rotation slerp(R_a, R_b, t_i) R_i. Both ends then match exactly.
    2. Landmarks: displacements d_i (d_0 = d_{N−1} = 0) minimise
       10⁶ Σ_landmarks w ‖E (r_i + d_i) − (p − T)/s‖² + Σ_i ‖d_{i+1} − d_i‖²/ℓ_i,
       E = [e_c; e_r], ℓ_i the segment lengths: landmarked vertebrae move in their image planes
       onto the landmarks (depth is unchanged by a PA view alone), the rest follow by linear
       interpolation in arc length.
    3. Directors: each interior rotation is turned by the smallest rotation taking the blended
       centreline's tangent (central difference) onto the displaced one's.
    Returns positions (N, 3) in mm and rotations (N, 3, 3).
    """
    p = np.asarray(rest_positions, dtype=float)
    Q = np.asarray(rest_rotations, dtype=float)
    n = len(p)
    if n < 3 or p.shape != (n, 3) or Q.shape != (n, 3, 3):
        raise ValueError(f"expected rest positions (N, 3) and rotations (N, 3, 3) with N ≥ 3, got {p.shape}, {Q.shape}")
    for view in views:
        _check_view(view, n)
    r_top, R_top = _pose(top, "top")
    r_bot, R_bot = _pose(bottom, "bottom")

    R_a = R_top @ Q[0].T
    R_b = R_bot @ Q[-1].T
    chords = p[1:] - p[:-1]
    t = np.zeros(n)
    np.cumsum(np.sqrt(np.einsum("ij,ij->i", chords, chords)), out=t[1:])
    t /= max(t[-1], 1e-300)
    r = (1.0 - t)[:, None] * ((p - p[0]) @ R_a.T + r_top) + t[:, None] * ((p - p[-1]) @ R_b.T + r_bot)
    R = slerp(R_a, R_b, t) @ Q
    r[0], R[0] = r_top, R_top
    r[-1], R[-1] = r_bot, R_bot

    # Band system (upper storage, half-bandwidth 5) over the extended index 3·vertebra + k; the
    # ends' rows and columns are sliced off before solving.
    kd = 5
    n_ext = 3 * n
    a, b = _UPPER3
    rows, cols, vals, rhs_bins, rhs_vals = [], [], [], [], []
    for view in views:
        idx = np.asarray(view.indices, dtype=int)
        E = np.stack((np.asarray(view.e_c, dtype=float), np.asarray(view.e_r, dtype=float)))
        wE = _DATA_WEIGHT * max(float(view.weight), 1e-12) * E
        target = (np.asarray(view.points, dtype=float) - np.asarray(view.translation, dtype=float)) / view.scale
        rows.append(np.tile(kd + a - b, len(idx)))
        cols.append((3 * idx[:, None] + b).ravel())
        vals.append(np.tile((E.T @ wE)[a, b], len(idx)))
        rhs_bins.append((3 * idx[:, None] + np.arange(3)).ravel())
        rhs_vals.append(((target - r[idx] @ E.T) @ wE).ravel())
    seg = r[1:] - r[:-1]
    k = 1.0 / np.maximum(np.sqrt(np.einsum("ij,ij->i", seg, seg)), 1e-9)
    ab = np.zeros((kd + 1, n_ext))
    k3 = np.repeat(k, 3)
    ab[kd, :-3] = k3
    ab[kd, 3:] += k3
    ab[kd - 3, 3:] = -k3
    rhs = np.zeros(n_ext)
    if rows:
        flat = np.concatenate(rows) * n_ext + np.concatenate(cols)
        ab += _accumulate(flat, np.concatenate(vals), minlength=ab.size).reshape(ab.shape)
        rhs = _accumulate(np.concatenate(rhs_bins), np.concatenate(rhs_vals), minlength=n_ext)
    c, info = dpbtrf(ab[:, 3:-3])
    if info != 0:
        raise ValueError("initial configuration: the displacement system is singular (non-finite input?)")
    d = dpbtrs(c, rhs[3:-3, None])[0].reshape(n - 2, 3)

    r_new = r.copy()
    r_new[1:-1] += d
    tangent_old = r[2:] - r[:-2]
    tangent_new = r_new[2:] - r_new[:-2]
    R_new = R.copy()
    R_new[1:-1] = rotation_between(tangent_old, tangent_new) @ R[1:-1]
    return r_new, R_new
