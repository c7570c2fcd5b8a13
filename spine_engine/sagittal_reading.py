"""What one PA film's foreshortening tells of the kyphosis.

A chord between adjacent vertebrae, of length L_i, leaning by β_i out of the frontal plane, projects
on a PA film with length ℓ_i = m L_i cos β_i (m the magnification): its frontal tilt keeps its length,
its sagittal inclination shortens it. With L_i = S λ_i (λ_i the population's mean share of the T1–L5
chord sum, S the spine's size, one unknown with m) and β = μ + δ + Σ_k a_k u_k (μ the population's
mean chord inclinations, δ a lean of the whole spine, u_k the first principal modes of the
population's inclinations about each spine's mean, a_k their weights), the reading is the maximum a
posteriori (log mS, δ, a) of

    log ℓ_i = log(mS) + log λ_i + log cos β_i + ε_i,   ε_i ~ N(0, σ_λ² + 2σ²/ℓ_i²),
    δ ~ N(0, σ_δ²),   a_k ~ N(0, σ_k²),

over the chords between adjacent landmarked levels (σ_λ: the spread of log(L_i / (S λ_i)) in the
population, σ: the film's landmark SD, mm; ℓ_i in detector mm). The kyphosis read is that of the read
inclinations' tangents t_l = (β_{l−1} + β_l) / 2 (the mean of the two chords at vertebra l):
t_T4 − t_T12, and t_T5 − t_T12.

The fitted rod reads the same foreshortening through its bending prior, whose segments are
independent, and it may also explain a short chord by turning the frontal curve out of the film's
plane; a reading held to the population's few sagittal shapes does not (docs/accuracy.md, "One PA
film"). The model's numbers are VerSe dev's, written with their provenance by ``spine bench pa-reading
--write`` into ``priors/sagittal_reading.json`` (``benches.pa_reading``), with ``weight``,
the share of this reading in the film's value of a PA-only kyphosis (the rest the rod's,
``reconstruction.measure_fit``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from .levels import LEVEL_INDEX, N_LEVELS

FloatArray = npt.NDArray[np.float64]

READING_FILE = Path(__file__).resolve().parent / "priors" / "sagittal_reading.json"
MIN_CHORDS = 8
"""Fewest chords between adjacent landmarked levels from which the film's foreshortening is read;
below it the rod's reading stands alone."""
LARGEST_INCLINATION_DEG = 80.0
"""Bound of every read chord inclination |β_i| during the search (cos β stays above 0.17)."""


@dataclass(frozen=True)
class ReadingModel:
    """The population's numbers of the reading (module docstring), angles in degrees."""

    chord_share: FloatArray
    """(16,) λ: each chord's mean share of the T1–L5 chord sum."""
    mean_inclination_deg: FloatArray
    """(16,) μ: each chord's mean inclination out of the frontal plane (``chord_inclinations_deg``)."""
    modes: FloatArray
    """(k, 16) u_k: unit principal modes of the inclinations about each spine's mean."""
    mode_sd_deg: FloatArray
    """(k,) σ_k: the SD of each mode's weight."""
    lean_sd_deg: float
    """σ_δ: the SD of a spine's mean inclination about the population's."""
    length_sd: float
    """σ_λ: the SD of log(L_i / (S λ_i)), the chords' lengths about their mean shares."""
    weight: float
    """The share of this reading in a PA-only kyphosis's film value, in [0, 1]."""
    provenance: dict[str, Any]


def chord_inclinations_deg(positions: npt.ArrayLike) -> FloatArray:
    """(N − 1,) each chord's inclination out of the frontal plane, degrees: atan2(Δy, √(Δx² + Δz²)) of
    the chord from the upper vertebra down (LPS: +y posterior): a kyphotic thoracic spine's chords
    run posteriorly (β > 0) from T4 down to its apex and anteriorly (β < 0) below it."""
    d = np.diff(np.asarray(positions, dtype=float), axis=0)
    return np.asarray(np.degrees(np.arctan2(d[:, 1], np.hypot(d[:, 0], d[:, 2]))))


def kyphoses_deg(inclinations_deg: npt.ArrayLike) -> tuple[float, float]:
    """(kyphosis T4–T12, kyphosis T5–T12), degrees, of chord inclinations (N − 1,): t_l − t_T12 with
    t_l = (β_{l−1} + β_l) / 2 the tangent's inclination at vertebra l."""
    beta = np.asarray(inclinations_deg, dtype=float)

    def tangent(level: str) -> float:
        i = LEVEL_INDEX[level]
        return float(0.5 * (beta[i - 1] + beta[i]))

    return tangent("T4") - tangent("T12"), tangent("T5") - tangent("T12")


def read_inclinations_deg(
    model: ReadingModel, indices: npt.ArrayLike, points_mm: npt.ArrayLike, landmark_sd_mm: float
) -> FloatArray | None:
    """(16,) the chord inclinations one PA film reads (module docstring), degrees; None with fewer
    than ``MIN_CHORDS`` chords between adjacent landmarked levels, or when the search breaks down.
    ``indices`` (n,) the landmarks' levels, increasing; ``points_mm`` (n, 2) their image points,
    detector mm."""
    levels = np.asarray(indices, dtype=int)
    points = np.asarray(points_mm, dtype=float)
    adjacent = np.flatnonzero(np.diff(levels) == 1)
    if len(adjacent) < MIN_CHORDS:
        return None
    chords = levels[adjacent]
    ell = np.linalg.norm(points[adjacent + 1] - points[adjacent], axis=1)
    if not np.all(ell > 0.0):
        return None
    noise_sd = np.sqrt(model.length_sd**2 + 2.0 * landmark_sd_mm**2 / ell**2)
    mu = np.radians(model.mean_inclination_deg)
    modes = np.asarray(model.modes, dtype=float)
    prior_sd = np.concatenate(([np.radians(model.lean_sd_deg)], np.radians(model.mode_sd_deg)))
    y = np.log(ell) - np.log(model.chord_share[chords])
    start = np.concatenate(([np.log(ell.sum() / model.chord_share[chords].sum())], np.zeros(len(prior_sd))))
    try:
        with np.errstate(all="ignore"):
            p = _map_estimate(start, y, noise_sd, mu[chords], modes[:, chords], prior_sd)
    except np.linalg.LinAlgError:
        return None  # a search that breaks down reads nothing, as too few chords do
    beta = np.degrees(mu + p[1] + p[2:] @ modes)
    return np.asarray(beta) if np.all(np.isfinite(beta)) else None


SEARCH_STEPS = 30
"""Most steps of the reading's search (Newton's converges in 3–5)."""
STEP_TOLERANCE = 1e-6
"""The search ends when no parameter moved by more than this (rad, or log units: 6e-5°, 1e-4 % of
the size), far below what the reading can tell."""


def _map_estimate(
    p: FloatArray, y: FloatArray, noise_sd: FloatArray, mu: FloatArray, modes: FloatArray, prior_sd: FloatArray
) -> FloatArray:
    """The MAP p = (log mS, δ, a) of the module docstring's model by Newton's method, falling back to
    Levenberg–Marquardt's step where Newton's does not lower the cost, from ``p``: residuals
    r_i = (y_i − p₀ − log cos β_i)/σ_i with y_i = log ℓ_i − log λ_i, β = μ + p₁ + aᵀU, and the prior
    rows p_{1+k}/σ_prior,k; ∂r_i/∂p₀ = −1/σ_i, ∂r_i/∂β_i = tan β_i/σ_i, ∂²r_i/∂β_i² = sec²β_i/σ_i.
    ``modes`` (k, m) and ``mu`` (m,) at the m chords read. Hand-written: scipy's ``least_squares`` cost
    1 ms a reading, a third of a ``register()`` call; this 0.15 ms."""
    limit = np.radians(LARGEST_INCLINATION_DEG)
    d_beta = np.vstack((np.ones(len(mu)), modes)).T  # (m, 1 + k): ∂β/∂(δ, a)

    def residuals(q: FloatArray) -> tuple[FloatArray, FloatArray]:
        beta = np.clip(mu + d_beta @ q[1:], -limit, limit)
        r = np.concatenate(((y - q[0] - np.log(np.cos(beta))) / noise_sd, q[1:] / prior_sd))
        return r, beta

    r, beta = residuals(p)
    cost = float(r @ r)
    jacobian = np.zeros((len(r), len(p)))
    jacobian[: len(mu), 0] = -1.0 / noise_sd
    jacobian[len(mu) :, 1:] = np.diag(1.0 / prior_sd)
    for _ in range(SEARCH_STEPS):
        jacobian[: len(mu), 1:] = (np.tan(beta) / noise_sd)[:, None] * d_beta
        normal, gradient = jacobian.T @ jacobian, jacobian.T @ r
        curvature = (r[: len(mu)] / (noise_sd * np.cos(beta) ** 2))[:, None] * d_beta  # Σ r_i ∂²r_i/∂β² ...
        newton = normal.copy()
        newton[1:, 1:] += d_beta.T @ curvature  # ... the residuals' second-order term, ∂²r_i/∂β_i² = sec²β_i/σ_i
        damping = 0.0  # Newton's step first, then Levenberg–Marquardt's if it does not lower the cost
        while True:
            matrix = newton if damping == 0.0 else normal + damping * np.diag(np.diag(normal))
            step = np.linalg.solve(matrix, -gradient)
            r_new, beta_new = residuals(p + step)
            cost_new = float(r_new @ r_new)
            if cost_new <= cost or damping > 1e8:
                break
            damping = max(10.0 * damping, 1e-3)
        if cost_new > cost:
            break
        p, r, beta, cost = p + step, r_new, beta_new, cost_new
        if np.max(np.abs(step)) < STEP_TOLERANCE:
            break
    return p


@cache
def load_reading_model(path: str = str(READING_FILE)) -> ReadingModel | None:
    """The shipped reading model (``READING_FILE``), None when absent. Read once per process."""
    file = Path(path)
    if not file.is_file():
        return None
    data = json.loads(file.read_text(encoding="utf-8"))
    model = ReadingModel(
        chord_share=np.asarray(data["chord_share"], dtype=float),
        mean_inclination_deg=np.asarray(data["mean_inclination_deg"], dtype=float),
        modes=np.asarray(data["modes"], dtype=float).reshape(-1, N_LEVELS - 1),
        mode_sd_deg=np.asarray(data["mode_sd_deg"], dtype=float),
        lean_sd_deg=float(data["lean_sd_deg"]),
        length_sd=float(data["length_sd"]),
        weight=float(data["weight"]),
        provenance=dict(data.get("provenance", {})),
    )
    return model


def write_reading_model(model: ReadingModel, path: Path = READING_FILE) -> Path:
    """Write ``model`` as JSON with its provenance (``load_reading_model`` forgets what it read)."""
    if not 0.0 <= model.weight <= 1.0:
        raise ValueError(f"weight must lie in [0, 1], got {model.weight}")
    data = {
        "chord_share": np.round(model.chord_share, 6).tolist(),
        "mean_inclination_deg": np.round(model.mean_inclination_deg, 4).tolist(),
        "modes": np.round(model.modes, 6).tolist(),
        "mode_sd_deg": np.round(model.mode_sd_deg, 4).tolist(),
        "lean_sd_deg": round(model.lean_sd_deg, 4),
        "length_sd": round(model.length_sd, 6),
        "weight": model.weight,
        "provenance": model.provenance,
    }
    path.write_text(json.dumps(data, indent=2, ensure_ascii=False) + "\n", encoding="utf-8")
    load_reading_model.cache_clear()
    return path
