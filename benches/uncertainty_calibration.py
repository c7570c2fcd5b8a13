"""Calibration of the uncertainty model's two constants on VerSe dev.

``spine bench clinic --split dev --calibrate-uncertainty`` films every dev spine in every clinic
case (``clinic_films.simulate_series``, ``clinic_films.build_payload``), fits it once (``reconstruction``'s
``prepare_inputs`` and ``fit_patient_rod``: the same fit as ``register``, kept to reuse its
``Solution``) and then, with z = |error| / SD of every position coordinate relative to the
centroid (``fit.uncertainty``; the SD as ``register`` reports it before c, widened by its image
points' misfit max(1, B), ``fit.uncertainty.solution_misfit``):

1. λ (the rod's weight as a prior in the Laplace Hessian): the value at which the PA-only case
   (e), where the prior decides the depth, covers ``target`` (95 %) with c = 1; bisection on
   log10 λ in [−2, 6] (coverage falls as λ grows: the prior then holds the spine tighter);
2. c (``uncertainty_scale``): with that λ, the factor for which ±1.96·c·SD covers ``target`` of
   the coordinates of all cases pooled, each case weighing the same (``calibrated_scale``);
3. how the sagittal measures one PA film leaves to the prior are reported (``prior_only_readings``):
   on case (e), the film's reading plus the median of truth − reading where the reading predicts the
   truth (one-sided p < 0.05), else the population's mean.

Tune on dev only: the test split is reported, never used here.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
from scipy import stats

from benches.clinic_films import Case, FloatArray, Truth, centreline_measures, simulate_series
from benches.clinic_films import build_payload as clinic_payload
from spine_engine.anatomy import load_profile
from spine_engine.errors import SpineEngineError
from spine_engine.fit.types import Solution
from spine_engine.fit.uncertainty import (
    PRIOR_ONLY_ALPHA,
    PRIOR_ONLY_LENKE,
    PRIOR_ONLY_MEASURES,
    Calibration,
    PriorOnlyReading,
    solution_misfit,
    solution_uncertainty,
    write_calibration,
)
from spine_engine.models import Measures
from spine_engine.reconstruction import fit_patient_rod, measure_fit, prepare_inputs
from spine_engine.validation import validate_payload

LOG10_PRIOR_WEIGHT_RANGE = (-2.0, 6.0)
"""Bisection range of log10 λ."""
PRIOR_CASE = "e"
"""The case whose coverage sets λ: PA only, where depth comes from the prior alone."""
Z95 = 1.959963984540054
"""Two-sided 95 % quantile of the standard normal distribution."""


def coverage(z: Sequence[float] | FloatArray, scale: float = 1.0) -> float | None:
    """Fraction of items with |error| ≤ 1.96·scale·SD, from their z = |error|/SD."""
    a = np.asarray(z, dtype=float).ravel()
    return None if a.size == 0 else float(np.mean(a <= Z95 * scale))


def calibrated_scale(z_by_case: dict[str, FloatArray], target: float = 0.95) -> float:
    """The scale c for which ±1.96·c·SD covers ``target`` of the pooled coordinates, each case
    weighing the same: c = Q(z)/1.96 with Q the weighted ``target`` quantile of z."""
    parts = [np.asarray(z, dtype=float) for z in z_by_case.values() if len(z)]
    if not parts:
        raise ValueError("no coordinates with an SD to calibrate on")
    z = np.concatenate(parts)
    w = np.concatenate([np.full(len(p), 1.0 / len(p)) for p in parts])
    order = np.argsort(z)
    cum = np.cumsum(w[order]) / w.sum()
    return float(z[order][np.searchsorted(cum, target)] / Z95)


class Sample(NamedTuple):
    case: str
    truth: Truth
    solution: Solution
    measures: Measures
    """The fit's measures as ``register`` reads them before any offset (``reconstruction.measure_fit``)."""


def collect(truths: Sequence[Truth], cases: Sequence[Case], noise_mm: float, seed: int, profile: str) -> list[Sample]:
    """One fit per spine and case; cases the engine refuses or cannot fit are left out."""
    prof = load_profile(profile)
    out = []
    for truth in truths:
        series = simulate_series(truth, noise_mm, seed)
        for case in cases:
            try:
                model = validate_payload(clinic_payload(series, case).model_dump(mode="json", exclude_none=True))
                inputs = prepare_inputs(model, prof)
                solution, _ = fit_patient_rod(inputs, prof)
            except (SpineEngineError, ValueError, ArithmeticError, np.linalg.LinAlgError):
                continue  # refused (e.g. a subset this engine does not take) or broken down: not a sample
            if solution.output.converged:
                out.append(Sample(case.key, truth, solution, measure_fit(inputs, solution.output)))
    return out


def position_z(samples: Sequence[Sample], prior_weight: float) -> dict[str, np.ndarray]:
    """Per case, z = |error| / SD (c = 1, widened by max(1, B)) of every centroid-relative coordinate."""
    z: dict[str, list[np.ndarray]] = {}
    for s in samples:
        widen = max(1.0, solution_misfit(s.solution).ratio)
        u = solution_uncertainty(s.solution, scale=widen, prior_weight=prior_weight)
        r, t = s.solution.positions, s.truth.positions
        error = (r - r.mean(axis=0)) - (t - t.mean(axis=0))
        z.setdefault(s.case, []).append((np.abs(error) / u.position_sd_mm).ravel())
    return {k: np.concatenate(v) for k, v in z.items()}


def calibrate(
    samples: Sequence[Sample], target: float = 0.95, iterations: int = 30
) -> tuple[Calibration, dict[str, Any]]:
    """(constants, diagnostics): λ from the PA-only case, then c pooled (module docstring)."""
    cases = {s.case for s in samples}
    if PRIOR_CASE in cases:
        lo, hi = LOG10_PRIOR_WEIGHT_RANGE
        prior_only = [s for s in samples if s.case == PRIOR_CASE]
        for _ in range(iterations):
            mid = 0.5 * (lo + hi)
            cov = coverage(position_z(prior_only, 10.0**mid)[PRIOR_CASE])
            assert cov is not None
            lo, hi = (mid, hi) if cov > target else (lo, mid)
        prior_weight = float(10.0 ** (0.5 * (lo + hi)))
    else:
        prior_weight = 1.0
    z = position_z(samples, prior_weight)
    scale = calibrated_scale(z, target)
    diagnostics = {
        "coverage_at_calibration": {k: coverage(v, scale) for k, v in sorted(z.items())},
        "raw_coverage_at_prior_weight": {k: coverage(v) for k, v in sorted(z.items())},
        "coordinates": {k: len(v) for k, v in sorted(z.items())},
        "plain_laplace_coverage": {k: coverage(v) for k, v in sorted(position_z(samples, 1.0).items())},
    }
    readings = prior_only_readings([s for s in samples if s.case == PRIOR_CASE])
    return Calibration(scale, prior_weight, {}, readings), diagnostics


def prior_only_readings(samples: Sequence[Sample]) -> dict[str, PriorOnlyReading]:
    """``Calibration.prior_only`` from ``samples`` (the PA-only case): per sagittal measure the
    rank correlation of the fit's reading y with the truth (Spearman, one-sided p: one spine far out, as
    dev's T2–T5 kyphosis of 45°, does not decide it), the median of truth − y
    and the truth's mean, the truth's measured on its centreline frames as the clinic bench measures
    it; {} without samples (``fit.uncertainty.PriorOnlyReading``)."""
    if len(samples) < 3:
        return {}
    pairs = [(centreline_measures(s.truth.positions), s.measures) for s in samples]
    values: dict[str, tuple[list[float], list[float]]] = {
        name: ([getattr(t, key) for t, _ in pairs], [getattr(f, key) for _, f in pairs])
        for name, key in PRIOR_ONLY_MEASURES.items()
    }
    values.update({
        name: ([getattr(t.lenke, key) for t, _ in pairs], [getattr(f.lenke, key) for _, f in pairs])
        for name, key in PRIOR_ONLY_LENKE.items()
    })
    out = {}
    for name, (truth_values, film_values) in values.items():
        truth, film = np.array(truth_values, dtype=float), np.array(film_values, dtype=float)
        test = stats.spearmanr(film, truth, alternative="greater")
        out[name] = PriorOnlyReading(
            bool(test.pvalue < PRIOR_ONLY_ALPHA), float(np.median(truth - film)), float(truth.mean()),
            float(test.statistic), float(test.pvalue), float(truth.std(ddof=1)),
        )
    return out


def provenance(command: str, split: str, n_spines: int, cases: Sequence[Case], noise_mm: float, seed: int,
               diagnostics: dict[str, Any]) -> dict[str, Any]:
    """The calibration's provenance record (stored with the constants)."""
    return {
        "method": "Laplace approximation at the fit's optimum; prior_weight: the rod rows' weight in the Hessian at "
        "which the PA-only case (e) covers 95 % with scale 1 (bisection on log10); uncertainty_scale: then the "
        "factor on every SD for 95 % coverage of the centroid-relative position coordinates of all cases pooled, "
        "each case weighing the same; prior_only: on the PA-only case (e), per sagittal measure, the Spearman rank "
        "correlation of the fit's reading with the truth (one-sided p; film_predicts when p < 0.05), the median of "
        "truth − reading (offset_deg), the truth's mean (population_mean_deg) and SD (population_sd_deg; Lenke's "
        "regional kyphoses T2–T5 and T10–L2 too) (benches.uncertainty_calibration)",
        "command": command,
        "training_set": f"VerSe {split} split ({n_spines} spines), {split}.csv; simulated series of "
        "benches.clinic_films",
        "cases": {c.key: c.title for c in cases},
        "noise_mm": noise_mm,
        "seed": seed,
        "date": dt.date.today().isoformat(),
        **diagnostics,
    }


def calibrate_and_write(
    command: str, split: str, truths: list[Truth], cases: list[Case], noise_mm: float, seed: int, profile: str
) -> dict[str, Any]:
    """Calibrate the constants on ``truths``, write them with their provenance
    (``fit.uncertainty.write_calibration``) and return what the bench reports of them."""
    constants, diagnostics = calibrate(collect(truths, cases, noise_mm, seed, profile))
    record = constants._replace(provenance=provenance(command, split, len(truths), cases, noise_mm, seed, diagnostics))
    path = write_calibration(record)
    return {
        "uncertainty_scale": constants.uncertainty_scale,
        "prior_weight": constants.prior_weight,
        "prior_only": {k: r._asdict() for k, r in constants.prior_only.items()},
        "calibration_file": str(path),
        "calibration": diagnostics,
    }
