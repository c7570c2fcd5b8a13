"""Calibrated uncertainty of a registration: Laplace approximation at the fit's optimum.

The fit minimises E(x) = ‖ρ(x)‖² (N·mm) over the parameter vector x (vertebra position
increments δr_i in mm, rotation increments δθ_i in rad with R_i ← R_i exp(hat δθ_i), and any
projection parameters). Read as a negative log posterior, exp(−E/(2τ)) with τ the *temperature*
that turns the landmark rows into standard normal residuals: a landmark row √w (P r − p)/s
whose image noise has SD σ (detector mm) has SD √w σ/s, so τ = w σ²/s² (N·mm; ``temperature``);
rows already divided by their SD have τ = 1. The rod's elastic energy then acts as the prior at
the same temperature. Around the optimum x̂ (Laplace):

    Σ = c² τ H⁻¹,    H = J_dᵀJ_d + λ J_rodᵀJ_rod (Gauss–Newton Hessian of E/2 at λ = 1,
                                                J = ∂ρ/∂x at x̂, J_rod the rod's rows),

with two constants calibrated on VerSe dev (``calibration``, ``spine bench clinic --split dev
--calibrate-uncertainty``): λ, the weight of the rod's energy read as a prior (the fit's balance
of energy and landmarks was tuned for accuracy; as a prior at λ = 1 it lets a PA-only spine's
depth vary by ten times its actual error), set so that the PA-only intervals cover 95 %; then c,
the ``uncertainty_scale`` of the contract, one factor on every SD so that ±1.96 SD covers 95 % of
the truth's coordinates pooled over the clinic's cases. Only variances of scalar functionals f(x)
are needed, by the delta method:

    Var f = c² τ gᵀ H⁻¹ g,   g = ∂f/∂x at x̂,

computed for all functionals at once with one Cholesky factorisation of H and a triangular solve
(``functional_variances``): Var f_k = ‖L⁻¹ g_k‖² with H = L Lᵀ. The vertebra block of H is banded
(half-bandwidth 11) with a dense border of projection parameters, and ``functional_variances``
has that bordered band solve (``n_band``); at N = 17 (H 93 × 93 to 109 × 109) the dense
Cholesky is the cheaper: 0.83 against 1.50 million instructions per call for the ~71 functionals
(valgrind callgrind, deterministic, docs/performance.md: LAPACK's band triangular
solve ``dtbtrs`` takes the right-hand sides one at a time, and gathering the band costs more than
the band factorisation saves), so ``solution_uncertainty`` uses the dense one. H itself is summed
over the nonzero entries of each row of J only (``weighted_gram``).

Functionals (``functional_gradients``; gradients analytic, checked against finite differences in
tests/engine/test_uncertainty.py):

* each coordinate of a position relative to the centroid of the 17, r_i − r̄ (mm): g has 1 − 1/N
  on δr_i's column and −1/N on every other free vertebra's (the global translation, which the
  data do not fix without boundary, drops out);
* kyphosis T4–T12 = β_T4 − β_T12, T5–T12, lordosis L1–L5 = β_L5 − β_L1
  (``measures.kyphosis_lordosis_deg``) and Cobb = |θ_upper − θ_lower| (``measures.frontal_tilt_deg``)
  with β_i, θ_i the sagittal inclination and frontal tilt of the frame ``frames_from_centreline``
  puts on the tangent t_i = r_{i+1} − r_{i−1}: functions of the positions, whose covariance the
  landmarks determine (``functional_gradients`` says why not of the directors);
* the axial rotation ψ = atan2(d2_x, −d2_y) of each director frame (``frames.axial_rotation_deg``):
  for f = atan2(a·d_k, b·d_k) of director d_k = R e_k,
  ∂f/∂δθ = e_k × (Rᵀ g_d),  g_d = ((b·d) a − (a·d) b) / ((a·d)² + (b·d)²)
  (∂(R exp(hat δθ) e_k)/∂δθ = −R hat(e_k)); degrees.

The delta method is conditional on the curve's end vertebrae (chosen by the tilt sequence) and
linear: SDs of several degrees on an angle near a branch of atan2 are approximate.

A misfit the stated noise does not explain widens every SD (``landmark_misfit``). The image-point rows
(landmarks and offset points, variance τ each under the model) give

    χ² = Σ ρ_i² / τ,   ν = n − tr(S),   B = √(χ²/ν),

with n their count and tr(S) = Σ_i J_i H₁⁻¹ J_iᵀ their leverages in the fit's own Hessian H₁ = JᵀJ
(every row at weight 1, as the fit weighs them): the effective number of parameters the points
pay for, so that E[χ²] ≈ ν when the points scatter as stated about a spine the model can take. B is
the Birge ratio; ``reported_uncertainty`` multiplies the SDs by max(1, B), the scale factor with
which the Particle Data Group widens the errors of measurements that disagree by more than they
say (Review of Particle Physics, "Introduction", §5.2.2 "Unconstrained averaging"; B ≤ 1 changes
nothing). A view read in weak perspective whose film came from a point source (the clinic's case
(h)), or a stated SD below the clicks' scatter, reads B > 1; beyond 4 × the SD the landmarks are
refused instead (``reconstruction.LANDMARK_SD_CONTRADICTED``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import numpy.typing as npt
from numba import njit
from scipy.linalg import LinAlgError, cho_factor, solve_triangular
from scipy.linalg.lapack import dpbtrf, dpotrf, dtbtrs, dtrtrs

from ..levels import LEVEL_INDEX

if TYPE_CHECKING:
    from .types import Solution

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]

CALIBRATION_FILE = Path(__file__).resolve().parents[1] / "priors" / "uncertainty_calibration.json"
"""The calibrated constants of the reported uncertainty (c, λ), the readings of the sagittal measures
one PA film leaves to the prior (``PriorOnlyReading``) and their provenance (written by
``write_calibration``). Beside the tilt prior in ``priors/`` rather than in ``profiles/``, whose every
file is an elastic profile."""

_DEG = 180.0 / np.pi


class PoseColumns(NamedTuple):
    """Where each vertebra's pose increments sit in the parameter vector x: column of δr_i,k
    (mm) and of δθ_i,k (rad, right perturbation R exp(hat δθ)), shape (N, 3); −1 for a pose
    held fixed (the paper's exact boundary)."""

    position: IntArray
    rotation: IntArray


class Uncertainty(NamedTuple):
    """1 SD of the reported quantities (already multiplied by ``scale``)."""

    position_sd_mm: FloatArray
    """(N, 3) of each position coordinate relative to the centroid of the N vertebrae, mm."""
    axial_rotation_sd_deg: FloatArray
    """(N,) of each vertebra's axial rotation, degrees."""
    kyphosis_t4_t12_sd_deg: float
    kyphosis_t5_t12_sd_deg: float
    lordosis_l1_l5_sd_deg: float
    kyphosis_t2_t5_sd_deg: float
    """Of Lenke's regional kyphoses (``measures.lenke_inputs``), degrees, as the other sagittal ones."""
    kyphosis_t10_l2_sd_deg: float
    cobb_sd_deg: list[float]
    """Of each Cobb curve given to ``laplace_uncertainty``, in order, degrees."""
    scale: float
    """The factor that multiplied the Laplace SDs: the calibrated c, times max(1, B) in
    ``reported_uncertainty`` (``landmark_misfit``)."""
    landmark_misfit_ratio: float | None = None
    """B of ``landmark_misfit`` (``reported_uncertainty``); None where not computed."""


# ---------------------------------------------------------------- calibration file


class Calibration(NamedTuple):
    """The calibrated constants of the uncertainty model and their provenance."""

    uncertainty_scale: float
    """c: multiplies every Laplace SD (``FitReport.uncertainty_scale``)."""
    prior_weight: float
    """λ: weight of the rod's rows (its elastic energy, the prior) in the Laplace Hessian,
    H = J_dataᵀJ_data + λ J_rodᵀJ_rod. The fit's balance of energy and landmarks was tuned for
    accuracy, not as a population prior: at λ = 1 the PA-only depth SDs are ten times the errors
    (docs/accuracy.md, "The clinic's setting")."""
    provenance: dict[str, Any]
    prior_only: dict[str, PriorOnlyReading]
    """How a sagittal measure that no film determined (one PA film) is reported, by
    ``PRIOR_ONLY_MEASURES`` name; a name absent: the fit's reading as it is."""


class PriorOnlyReading(NamedTuple):
    """The report of a sagittal measure that one PA film leaves to the prior, calibrated on dev.

    The film's reading y (the fitted centreline's) is reported as y + ``offset_deg`` when, on dev, y
    predicts the truth (``film_predicts``: Spearman rank correlation > 0 at one-sided p < ``PRIOR_ONLY_ALPHA``);
    else the population's mean ``population_mean_deg`` is reported (what the film tells of it is noise).
    ``offset_deg``: the median on dev of truth − y, so that the reported value's median error is 0 (the
    MAE's best shift): the fitted centreline reads less lordosis than the population's because the rod's
    rest shape, whose chords take the mean inclinations, reads less than the mean of the measures."""

    film_predicts: bool
    offset_deg: float
    population_mean_deg: float
    correlation: float
    p_value: float
    population_sd_deg: float | None = None
    """The truth's SD on dev (ddof 1), degrees: the floor of the reported SD where the profile's
    population prior has none for the measure (Lenke's regional kyphoses); None in files written
    before it was recorded."""

    def reported(self, film_deg: float) -> float:
        """The value reported for the film's reading ``film_deg``, degrees."""
        return film_deg + self.offset_deg if self.film_predicts else self.population_mean_deg


PRIOR_ONLY_ALPHA = 0.05
"""One-sided significance at which dev must show that a PA film's reading of a sagittal measure
predicts the truth before the film's value is reported (``PriorOnlyReading``)."""


UNCALIBRATED = Calibration(1.0, 1.0, {}, {})

PRIOR_ONLY_MEASURES = {
    "kyphosis_t4_t12": "thoracic_kyphosis_t4_t12_deg",
    "kyphosis_t5_t12": "thoracic_kyphosis_t5_t12_deg",
    "lordosis_l1_l5": "lumbar_lordosis_l1_l5_deg",
}
"""The sagittal measures that one PA film leaves to the prior: ``Calibration.prior_only``'s
keys, and the ``models.Measures`` field each offsets."""

PRIOR_ONLY_LENKE = {
    "kyphosis_t2_t5": "t2_t5_kyphosis_deg",
    "kyphosis_t10_l2": "t10_l2_kyphosis_deg",
}
"""Lenke's regional kyphoses that one PA film leaves to the prior: further ``Calibration.prior_only``
keys, and the ``models.LenkeInputs`` field each offsets (T5–T12 there is ``kyphosis_t5_t12``'s)."""


@lru_cache(maxsize=4)
def _calibration(path: str) -> Calibration:
    try:
        with open(path) as fh:
            data: dict[str, Any] = json.load(fh)
    except FileNotFoundError:
        return UNCALIBRATED
    return Calibration(float(data["uncertainty_scale"]), float(data.get("prior_weight", 1.0)),
                       dict(data.get("provenance", {})),
                       {k: PriorOnlyReading(**v) for k, v in data.get("prior_only", {}).items()})


def calibration(path: Path | None = None) -> Calibration:
    """The calibrated constants from ``priors/uncertainty_calibration.json`` (``CALIBRATION_FILE``);
    ``UNCALIBRATED`` (c = λ = 1, the plain Laplace approximation) when the file is absent. Read once
    per process (``write_calibration`` forgets what was read)."""
    return _calibration(str(path or CALIBRATION_FILE))


def write_calibration(constants: Calibration, path: Path | None = None) -> Path:
    """Write the constants and their provenance as JSON; returns the path."""
    for name in ("uncertainty_scale", "prior_weight"):
        value = getattr(constants, name)
        if not (np.isfinite(value) and value > 0.0):
            raise ValueError(f"{name} must be positive and finite, got {value}")
    unknown = set(constants.prior_only) - set(PRIOR_ONLY_MEASURES) - set(PRIOR_ONLY_LENKE)
    values = [(r.offset_deg, r.population_mean_deg) for r in constants.prior_only.values()]
    if unknown or not np.all(np.isfinite(values)):
        raise ValueError(f"prior_only takes finite readings of {[*PRIOR_ONLY_MEASURES, *PRIOR_ONLY_LENKE]}")
    record = constants._asdict()
    record["prior_only"] = {k: r._asdict() for k, r in constants.prior_only.items()}
    file = path or CALIBRATION_FILE
    file.write_text(json.dumps(record, indent=2) + "\n")
    _calibration.cache_clear()
    return file


# ---------------------------------------------------------------- temperature


def temperature(weight: float, landmark_sd_mm: float, scale: float) -> float:
    """τ = w σ² / s² (N·mm): the variance of a landmark row √w (P r − p)/s whose image point has
    SD σ (detector mm) per coordinate on a view of magnification s (module docstring)."""
    if not (weight > 0.0 and landmark_sd_mm > 0.0 and scale > 0.0):
        raise ValueError(f"temperature needs positive weight, SD and scale, got {weight}, {landmark_sd_mm}, {scale}")
    return float(weight * landmark_sd_mm**2 / scale**2)


# ---------------------------------------------------------------- functionals


@njit(cache=True)
def _axial_rotation_rows(G: FloatArray, rotations: FloatArray, rot: IntArray, row0: int) -> None:
    """Row row0 + i of G: ∂ψ_i/∂δθ_i (deg/rad) of the axial rotation ψ_i = atan2(d2_x, −d2_y)
    (``frames.axial_rotation_deg``), at the columns ``rot[i]`` of the free δθ_i (module docstring:
    f = atan2(a·d_k, b·d_k) with k = 2nd director, a = e_x, b = −e_y, so a·d = d_x, b·d = −d_y and
    g_d = ((b·d) a − (a·d) b)/((a·d)² + (b·d)²) = (−d_y, d_x, 0)/(d_x² + d_y²);
    ∂f/∂δθ = e_2 × (Rᵀ g_d) = ((Rᵀg_d)_z, 0, −(Rᵀg_d)_x))."""
    for i in range(rotations.shape[0]):
        ya = rotations[i, 0, 1]
        xb = -rotations[i, 1, 1]
        norm2 = ya * ya + xb * xb
        g0 = xb / norm2
        g1 = ya / norm2
        local_x = rotations[i, 0, 0] * g0 + rotations[i, 1, 0] * g1
        local_z = rotations[i, 0, 2] * g0 + rotations[i, 1, 2] * g1
        grad = (_DEG * local_z, 0.0, -_DEG * local_x)
        for k in range(3):
            if rot[i, k] >= 0:
                G[row0 + i, rot[i, k]] = grad[k]


@njit(cache=True)
def _tangent(positions: FloatArray, v: int) -> tuple[float, float, float]:
    """t_v = r_{v+1} − r_{v−1}, one-sided at the ends (``frames.frames_from_centreline``)."""
    up = min(v + 1, positions.shape[0] - 1)
    down = max(v - 1, 0)
    return (positions[up, 0] - positions[down, 0], positions[up, 1] - positions[down, 1],
            positions[up, 2] - positions[down, 2])


@njit(cache=True)
def _frontal_tilt_deg(positions: FloatArray, v: int) -> float:
    """θ_v = atan2(−t_x t_z, t_y² + t_z²) (degrees), the frontal tilt of the frame
    ``frames.frames_from_centreline`` builds on the tangent t_v (``measures.frontal_tilt_deg``)."""
    x, y, z = _tangent(positions, v)
    return _DEG * math.atan2(-x * z, y * y + z * z)


@njit(cache=True)
def _centreline_angle_rows(
    G: FloatArray, positions: FloatArray, pos: IntArray, rows: IntArray, vertebrae: IntArray,
    signs: FloatArray, ends: IntArray,
) -> None:
    """Add each angle term's gradient to its row of G, in degrees per mm of δr_{v+1} (+) and
    δr_{v−1} (−) at the free columns ``pos``, v = vertebrae[j] and t_v its tangent (``_tangent``).
    Term j is signs[j] × β_v when ends[j, 0] < 0, else the Cobb term
    signs[j] × sgn(θ_u − θ_l) × θ_v with (u, l) = ends[j] (|θ_u − θ_l| = Cobb angle, sgn(0) = +1).
    β and θ are the sagittal inclination and frontal tilt of the frame
    ``frames.frames_from_centreline`` builds on t:

        β = atan2(t_y, −t_z):                ∂β/∂t = (0, −t_z, t_y) / (t_y² + t_z²);
        θ = atan2(d1_z, d1_x), d1 ∝ |t|² e_x − t_x t = (t_y² + t_z², ·, −t_x t_z), so
        θ = atan2(N, D), N = −t_x t_z, D = t_y² + t_z²:
        ∂θ/∂t = (D ∇N − N ∇D) / (N² + D²),  ∇N = (−t_z, 0, −t_x),  ∇D = (0, 2 t_y, 2 t_z).
    """
    n = positions.shape[0]
    for j in range(len(rows)):
        v = vertebrae[j]
        x, y, z = _tangent(positions, v)
        D = y * y + z * z
        sign = signs[j]
        if ends[j, 0] >= 0:
            if _frontal_tilt_deg(positions, ends[j, 0]) < _frontal_tilt_deg(positions, ends[j, 1]):
                sign = -sign
            N = -x * z
            q = N * N + D * D
            grad = (_DEG * (D * -z) / q, _DEG * (-N * (2.0 * y)) / q, _DEG * (D * -x - N * (2.0 * z)) / q)
        else:
            grad = (0.0, _DEG * (-z / D), _DEG * (y / D))
        for end, s in ((min(v + 1, n - 1), sign), (max(v - 1, 0), -sign)):
            for k in range(3):
                if pos[end, k] >= 0:
                    G[rows[j], pos[end, k]] += s * grad[k]


class Functionals(NamedTuple):
    """Gradient rows G (m, n_params) of the reported quantities, in this order: 3N centroid-
    relative coordinates (vertebra-major), N axial rotations, the sagittal measures of
    ``_SAGITTAL`` (kyphosis T4–T12, T5–T12, lordosis L1–L5, kyphosis T2–T5, T10–L2), then one row
    per Cobb curve."""

    G: FloatArray
    n_vertebrae: int
    n_curves: int


@lru_cache(maxsize=16)
def _position_rows(n: int, n_params: int, n_curves: int, pos_bytes: bytes) -> FloatArray:
    """G's rows that depend on the layout only, the others zero: the 3N position rows
    (r_i,k − (1/N) Σ_j r_j,k: 1 − 1/N on δr_i,k's column, −1/N on every other free one)."""
    pos = np.frombuffer(pos_bytes, dtype=np.intp).reshape(n, 3)
    G = np.zeros((4 * n + len(_SAGITTAL) + n_curves, n_params))
    for k in range(3):
        free = pos[:, k] >= 0
        rows = 3 * np.arange(n) + k
        G[np.ix_(rows, pos[free, k])] = -1.0 / n
        G[rows[free], pos[free, k]] += 1.0
    G.flags.writeable = False
    return G


_SAGITTAL = (("T4", "T12", 1.0), ("T5", "T12", 1.0), ("L1", "L5", -1.0), ("T2", "T5", 1.0), ("T10", "L2", 1.0))
"""(first, second, sign): kyphosis = β_T4 − β_T12, β_T5 − β_T12; lordosis = β_L5 − β_L1; Lenke's
regional kyphoses β_T2 − β_T5 and β_T10 − β_L2 (``measures.lenke_inputs``)."""


@lru_cache(maxsize=32)
def _angle_terms(n: int, curves: tuple[tuple[str, str], ...]) -> tuple[IntArray, IntArray, FloatArray, IntArray]:
    """Row of G, vertebra, sign and Cobb ends of each term of ``_centreline_angle_rows``, in order:
    the sagittal measures (``_SAGITTAL``, rows 4N … 4N + S − 1, ends −1), then each Cobb curve
    (row 4N + S + c, ends its (upper, lower) vertebrae); two terms each, first +sign, second −sign."""
    terms = [(4 * n + k, LEVEL_INDEX[level], s, -1, -1)
             for k, (first, second, sign) in enumerate(_SAGITTAL)
             for level, s in ((first, sign), (second, -sign))]
    for c, (upper, lower) in enumerate(curves):
        ends = (LEVEL_INDEX[upper], LEVEL_INDEX[lower])
        row = 4 * n + len(_SAGITTAL) + c
        terms += [(row, ends[0], 1.0, *ends), (row, ends[1], -1.0, *ends)]
    rows, vert, sign, up, low = zip(*terms, strict=True)
    out = (np.array(rows, dtype=np.intp), np.array(vert, dtype=np.intp), np.array(sign, dtype=float),
           np.stack((np.array(up, dtype=np.intp), np.array(low, dtype=np.intp)), axis=1))
    for a in out:
        a.flags.writeable = False
    return out


def functional_gradients(
    positions: npt.ArrayLike,
    rotations: npt.ArrayLike,
    columns: PoseColumns,
    n_params: int,
    curves: Sequence[tuple[str, str]] = (),
) -> Functionals:
    """Gradient rows of the reported quantities w.r.t. x (module docstring); ``curves``: the
    (upper, lower) end levels of each Cobb curve.

    Kyphosis, lordosis and Cobb angles are propagated through the centreline: β_i and θ_i of
    the tangent t_i (``_centreline_angle_rows``), so that their SDs follow the positions'
    covariance, which the landmarks determine. Their directors' own Laplace SDs are those of the
    rod's prior: with the calibrated soft shear (G ≈ 0.9 MPa) a director may leave the tangent by
    tens of degrees at the landmarks' temperature, far more than the reconstructions do (measured
    in docs/accuracy.md, "The clinic's setting"). Axial rotation, which no point landmark sees,
    keeps the directors' Laplace SD (``_axial_rotation_rows``): large, as it should be, without
    pedicles. The rows of the angles and axial rotations are compiled loops (numba), each a few
    scalar formulas per vertebra (about a hundred numpy calls before, docs/performance.md).
    """
    r = np.ascontiguousarray(positions, dtype=float)
    R = np.ascontiguousarray(rotations, dtype=float)
    n = len(R)
    pos = np.ascontiguousarray(columns.position, dtype=np.intp)
    rot = np.ascontiguousarray(columns.rotation, dtype=np.intp)
    G = _position_rows(n, n_params, len(curves), pos.tobytes()).copy()
    _axial_rotation_rows(G, R, rot, 3 * n)
    rows, vertebrae, signs, ends = _angle_terms(n, tuple((upper, lower) for upper, lower in curves))
    _centreline_angle_rows(G, r, pos, rows, vertebrae, signs, ends)
    return Functionals(G, n, len(curves))


# ---------------------------------------------------------------- variances


KD = 11
"""Half-bandwidth of the vertebra block of H: a segment couples two vertebrae of 6 unknowns."""


@njit(cache=True)
def weighted_gram(J: FloatArray, w: FloatArray) -> FloatArray:
    """H = Σ_k w_k J_kᵀ J_k = Jᵀ diag(w) J (n_params × n_params, symmetric) of a Jacobian J
    (n_rows × n_params) whose rows are sparse, summed over the nonzero entries of each row only:
    H_ab = Σ_k (w_k J_ka) J_kb, rows k in order, the same products as ``(J * w[:, None]).T @ J``.

    A row of the fit touches at most two vertebrae and the cameras (about 700 of 12,000 entries
    nonzero at N = 17), so this is about 10,000 multiplications against the dense product's 1.1
    million: 0.28 against 0.81 million instructions per call (callgrind, docs/performance.md)."""
    m, n = J.shape
    H = np.zeros((n, n))
    nonzero = np.empty(n, dtype=np.intp)
    for k in range(m):
        count = 0
        for c in range(n):
            if J[k, c] != 0.0:
                nonzero[count] = c
                count += 1
        for i in range(count):
            a = nonzero[i]
            wa = w[k] * J[k, a]
            for j in range(i, count):
                b = nonzero[j]
                H[a, b] += wa * J[k, b]
    for a in range(n):
        for b in range(a + 1, n):
            H[b, a] = H[a, b]
    return H


@lru_cache(maxsize=8)
def _band_index(n: int, kd: int) -> tuple[IntArray, IntArray, IntArray]:
    """Rows, columns of a dense (n, n) matrix and flat positions in band storage (kd + 1, n) of
    its upper band entries: ab[kd + i − j, j] = A[i, j] for 0 ≤ j − i ≤ kd."""
    rows, cols, flat = [], [], []
    for off in range(kd + 1):
        j = np.arange(off, n)
        rows.append(j - off)
        cols.append(j)
        flat.append((kd - off) * n + j)
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(flat)


def _bordered_variances(H: FloatArray, G: FloatArray, n_band: int, kd: int = KD) -> FloatArray:
    """gᵀH⁻¹g for H = [[A, B], [Bᵀ, C]] with A (n_band × n_band) banded (half-bandwidth kd):
    A = UᵀU (band Cholesky, ``dpbtrf``), W = U⁻ᵀB, S = C − WᵀW = VᵀV, and for each g = (g_A, g_p)
    y_A = U⁻ᵀg_A, y_p = V⁻ᵀ(g_p − Wᵀy_A), gᵀH⁻¹g = ‖y_A‖² + ‖y_p‖² (H = LLᵀ, L = [[Uᵀ, 0], [Wᵀ, Vᵀ]])."""
    rows, cols, flat = _band_index(n_band, kd)
    ab = np.zeros((kd + 1) * n_band)
    ab[flat] = H[rows, cols]
    u, info = dpbtrf(ab.reshape(kd + 1, n_band), lower=0, overwrite_ab=1)
    if info != 0:
        raise LinAlgError(f"the curvature of the vertebra block is not positive definite (dpbtrf info {info})")
    rhs = np.concatenate((G[:, :n_band].T, H[:n_band, n_band:]), axis=1)
    y, info = dtbtrs(u, rhs, uplo="U", trans="T", diag="N", overwrite_b=1)
    if info != 0:
        raise LinAlgError(f"band triangular solve failed (info {info})")
    m = len(G)
    y_a, w = y[:, :m], y[:, m:]
    var = np.einsum("ij,ij->j", y_a, y_a)
    if H.shape[0] > n_band:
        S = H[n_band:, n_band:] - w.T @ w
        v, _ = cho_factor(S, lower=True, check_finite=False)
        y_p = solve_triangular(v, G[:, n_band:].T - w.T @ y_a, lower=True, check_finite=False)
        var += np.einsum("ij,ij->j", y_p, y_p)
    return np.asarray(var)


def functional_variances(H: FloatArray, G: FloatArray, band: bool = False, n_band: int | None = None) -> FloatArray:
    """gᵀ H⁻¹ g for every row g of G, by one Cholesky factorisation H = L Lᵀ: ‖L⁻¹ g‖².

    ``band``: H given in LAPACK upper band storage (kd + 1, n) (``dpbtrf``). ``n_band``: H dense
    with its first ``n_band`` unknowns (the vertebrae) banded with half-bandwidth ``KD`` and a
    dense border (the projection parameters): the band Cholesky and Schur complement of
    ``_bordered_variances``. Else dense Cholesky; a dense H that is only semi-definite (a direction
    neither data nor prior fix) gets a ridge of 1e-9 × its largest diagonal entry, which changes the
    variance of a functional blind to that direction only by rounding.
    """
    if band:
        u, info = dpbtrf(H, lower=0)
        if info != 0:
            raise LinAlgError(f"the curvature at the optimum is not positive definite (dpbtrf info {info})")
        # H = Uᵀ U: g H⁻¹ g = ‖U⁻ᵀ g‖²
        x, info = dtbtrs(u, np.ascontiguousarray(G.T), uplo="U", trans="T", diag="N")
        if info != 0:
            raise LinAlgError(f"band triangular solve failed (info {info})")
        return np.asarray(np.einsum("ij,ij->j", x, x))
    if n_band is not None and n_band > KD:
        try:
            return _bordered_variances(H, G, n_band)
        except LinAlgError:
            pass  # semi-definite: the dense path with a ridge
    try:
        c = _cholesky_lower(H)
    except LinAlgError:
        ridge = 1e-9 * float(np.max(np.diag(H)))
        c = _cholesky_lower(H + ridge * np.eye(len(H)))
    x, info = dtrtrs(c, G.T, lower=1)
    if info != 0:
        raise LinAlgError(f"triangular solve failed (dtrtrs info {info})")
    return np.asarray(np.einsum("ij,ij->j", x, x))


def _cholesky_lower(H: FloatArray) -> FloatArray:
    """L of H = L Lᵀ (LAPACK ``dpotrf``, what ``scipy.linalg.cho_factor(lower=True)`` calls, without
    its checks: H is the solver's float array); LinAlgError when H is not positive definite."""
    c, info = dpotrf(H, lower=1, clean=0)
    if info != 0:
        raise LinAlgError(f"the curvature at the optimum is not positive definite (dpotrf info {info})")
    return np.asarray(c)


def laplace_uncertainty(
    jacobian: FloatArray | None,
    positions: npt.ArrayLike,
    rotations: npt.ArrayLike,
    columns: PoseColumns,
    temperature_nmm: float,
    curves: Sequence[tuple[str, str]] = (),
    scale: float | None = None,
    hessian: FloatArray | None = None,
    band: bool = False,
    n_band: int | None = None,
    row_weights: FloatArray | None = None,
) -> Uncertainty:
    """SDs of the reported quantities: c √(τ gᵀ H⁻¹ g) (module docstring).

    Give either the Jacobian J (n_residuals, n_params) at the optimum (H = JᵀJ, or
    H = Σ_k w_k J_kᵀ J_k with ``row_weights`` w, e.g. λ on the rod's rows) or ``hessian`` (dense,
    or band storage with ``band``). ``temperature_nmm``: τ. ``scale``: c; default the calibrated
    value (``calibration``). ``n_band``: the number of vertebra unknowns, first in x, whose block
    of H is banded (``functional_variances``).
    """
    if hessian is None:
        if jacobian is None:
            raise ValueError("give the Jacobian or the Hessian at the optimum")
        weights = np.ones(len(jacobian)) if row_weights is None else np.asarray(row_weights, dtype=float)
        H = weighted_gram(np.ascontiguousarray(jacobian, dtype=float), weights)
        n_params = jacobian.shape[1]
        band = False
    else:
        H = hessian
        n_params = H.shape[1]
    c = calibration().uncertainty_scale if scale is None else float(scale)
    f = functional_gradients(positions, rotations, columns, n_params, curves)
    var = functional_variances(H, f.G, band=band, n_band=n_band) * float(temperature_nmm)
    sd = c * np.sqrt(np.maximum(var, 0.0))
    n = f.n_vertebrae
    return Uncertainty(
        position_sd_mm=sd[: 3 * n].reshape(n, 3),
        axial_rotation_sd_deg=sd[3 * n : 4 * n],
        kyphosis_t4_t12_sd_deg=float(sd[4 * n]),
        kyphosis_t5_t12_sd_deg=float(sd[4 * n + 1]),
        lordosis_l1_l5_sd_deg=float(sd[4 * n + 2]),
        kyphosis_t2_t5_sd_deg=float(sd[4 * n + 3]),
        kyphosis_t10_l2_sd_deg=float(sd[4 * n + 4]),
        cobb_sd_deg=[float(v) for v in sd[4 * n + len(_SAGITTAL) :]],
        scale=c,
    )


AXIAL_ROTATION_SD_CAP_DEG = 180.0 / np.sqrt(3.0)
"""Largest reported axial rotation SD, degrees: the SD of an angle spread uniformly over the
circle (360°/√12 ≈ 103.9°). A Laplace SD beyond it (no pedicles: the rod's twist prior alone)
only says "not determined"; the linearisation behind it does not hold that far."""


@lru_cache(maxsize=32)
def _rod_rows(kinds: tuple[str, ...]) -> npt.NDArray[np.bool_]:
    """Mask of the rod's rows ("rod" in ``Solution.row_kinds``)."""
    mask = np.array([kind == "rod" for kind in kinds], dtype=bool)
    mask.flags.writeable = False
    return mask


def solution_uncertainty(
    solution: Solution,
    curves: Sequence[tuple[str, str]] = (),
    scale: float | None = None,
    prior_weight: float | None = None,
) -> Uncertainty:
    """``laplace_uncertainty`` of a solver's ``Solution``: whitened rows, so τ = κ/2 with κ its
    ``energy_unit`` (cov ≈ (κ/2)(JᵀJ)⁻¹, ``fit.types.Solution``), the rod's rows ("rod" in
    ``row_kinds``) weighted by λ. ``scale`` c and ``prior_weight`` λ default to ``calibration``."""
    constants = calibration()
    lam = constants.prior_weight if prior_weight is None else float(prior_weight)
    weights = None
    if lam != 1.0:
        weights = np.where(_rod_rows(solution.row_kinds), lam, 1.0)
    layout = solution.layout
    return laplace_uncertainty(
        solution.jacobian,
        solution.positions,
        solution.rotations,
        PoseColumns(np.asarray(layout.position), np.asarray(layout.rotation)),
        0.5 * float(solution.energy_unit),
        curves,
        constants.uncertainty_scale if scale is None else scale,
        row_weights=weights,
    )


class LandmarkMisfit(NamedTuple):
    """How far a fit's image points lie from it against their stated SD (module docstring)."""

    chi2: float
    """χ² = Σ ρ_i²/τ over the image-point rows (dimensionless)."""
    dof: float
    """ν = n − tr(S): the rows' count less their leverages in the fit's Hessian."""

    @property
    def ratio(self) -> float:
        """B = √(χ²/ν), the Birge ratio; 1 (nothing to judge) when ν < 1."""
        return math.sqrt(self.chi2 / self.dof) if self.dof >= 1.0 else 1.0


@lru_cache(maxsize=32)
def _image_rows(kinds: tuple[str, ...]) -> npt.NDArray[np.bool_]:
    """Mask of the rows of image points: landmarks and offset points (``fit.problem``'s kinds)."""
    mask = np.array([kind.startswith(("landmark:", "offset:")) for kind in kinds], dtype=bool)
    mask.flags.writeable = False
    return mask


def landmark_misfit(
    jacobian: FloatArray, residuals: FloatArray, rows: npt.NDArray[np.bool_], temperature_nmm: float
) -> LandmarkMisfit:
    """χ² and ν of the rows ``rows`` of whitened residuals ρ (variance τ = ``temperature_nmm`` each):
    χ² = Σ ρ_i²/τ, ν = n − Σ_i J_i H₁⁻¹ J_iᵀ with H₁ = JᵀJ, the leverages by ``functional_variances``
    (each row J_i a functional's gradient). For a linear model y = J x + e whose prior rows and noise
    are as stated, E[χ²] = ν exactly (Woodbury: I − S = (I + J_L P⁻¹ J_Lᵀ)⁻¹), and without a prior
    tr(S) is the number of parameters (tests/engine/test_uncertainty.py)."""
    J = np.ascontiguousarray(jacobian, dtype=float)
    H = weighted_gram(J, np.ones(len(J)))
    leverage = functional_variances(H, J[rows])
    chi2 = float(np.sum(np.square(residuals[rows]))) / float(temperature_nmm)
    return LandmarkMisfit(chi2, float(np.count_nonzero(rows)) - float(np.sum(leverage)))


def solution_misfit(solution: Solution) -> LandmarkMisfit:
    """``landmark_misfit`` of a solver's ``Solution``: its image-point rows, τ = κ/2."""
    return landmark_misfit(
        solution.jacobian, solution.residuals, _image_rows(solution.row_kinds), 0.5 * float(solution.energy_unit)
    )


def reported_uncertainty(
    solution: Solution,
    curves: Sequence[tuple[str, str]] = (),
    scale: float | None = None,
    prior_weight: float | None = None,
) -> Uncertainty:
    """The SDs a result reports: ``solution_uncertainty`` with c (default the calibrated value,
    ``calibration``) times max(1, B), B the image points' Birge ratio (``landmark_misfit``), and the
    axial rotation SDs capped at ``AXIAL_ROTATION_SD_CAP_DEG``; λ defaults to the calibrated value;
    ``curves``: the (upper, lower) end levels of the result's Cobb curves, in order."""
    misfit = solution_misfit(solution)
    c = calibration().uncertainty_scale if scale is None else float(scale)
    u = solution_uncertainty(solution, curves, c * max(1.0, misfit.ratio), prior_weight)
    return u._replace(
        axial_rotation_sd_deg=np.minimum(u.axial_rotation_sd_deg, AXIAL_ROTATION_SD_CAP_DEG),
        landmark_misfit_ratio=misfit.ratio,
    )
