"""``spine bench clinic``: the engine in the clinic's setting .

Known spines are filmed by a simulated scoliosis series and reconstructed through the public
entry point (``spine_engine.register`` on a ``JobPayload``), as a hospital would use it:

* truth: the VerSe CT spines (``dev`` to tune, ``test`` to report; centroids, directors from
  ``frames.frames_from_centreline``) and synthetic spines built geometrically by
  ``spine_engine.synthetic`` (curve angles, kyphosis, lordosis and axial rotation drawn, never
  made by the fit), other spines for each split (``SYNTHETIC_SEED_OF_SPLIT``);
* films and cases (``clinic_films``): a simulated PA and lateral radiograph of each spine
  (``simulate_series``: landmark noise, magnifications, film turn and offsets drawn) and what the
  clinic sends of them in each case (``CASES``, ``build_payload``): (a) uncalibrated PA + full
  lateral, (b) the lateral from T4 down, (c) perspective films with the geometry given, (d)
  without it, (e) PA only, (f) the paper's case.

Metrics per spine, then averaged (``summarise``):

* 3D error: mean over the 17 vertebrae of |(r_i − r̄) − (t_i − t̄)| (mm), r the result, t the
  truth, bars the centroids: the global translation, which is not observable without boundary,
  is removed and nothing else (a scale error counts); ``scale_error_pct`` is
  100·(RMS|r − r̄| / RMS|t − t̄| − 1);
* shape error (diagnostic): the same mean after also removing the best rotation (Kabsch,
  ``scipy.spatial.transform.Rotation.align_vectors``), and that rotation's component about the
  patient's left–right axis (``sagittal_lean_deg``, the whole spine leaning forward or back). Without
  boundary and calibration the lean is a near gauge: the lateral film's in-plane rotation ψ turns its
  image exactly as a lean of the spine does, so only the PA film (through the heights' small
  dependence on depth) and ψ's prior fix it;
* shape error with the scale removed too (``similarity_difference``): what two uncalibrated films
  leave beside the spine's size, which neither film states;
* kyphosis T4–T12, T5–T12, lordosis L1–L5 and the major Cobb angle computed the same way on truth
  and result: ``measures.compute_measures`` on the positions with the frames
  ``frames.frames_from_centreline`` puts on them (the truth has no other frames: VerSe gives
  centroids); the Cobb angle between the result's major curve's end vertebrae. Absolute errors.
  The JSON also has the errors of the result's reported measures (its directors, which the rod's
  shear lets leave the centreline's tangent) against the same truth (``reported_mae_deg``) and their
  mean signed error, result − truth (``reported_bias_deg``);
* coverage of the 95 % intervals (±1.96 SD): per coordinate of every position relative to the
  centroid (``position_sd_mm``), of each measure with an SD (kyphosis, lordosis, every Cobb curve;
  the value computed the same way as above, whose SD ``fit.uncertainty`` propagates; the JSON's
  ``coverage_reported`` uses the reported values) and of every vertebra's reported axial rotation
  against the truth's; the fraction of truths inside. A result without SDs has no coverage
  (reported as null / "-");
* axial rotation (synthetic spines only: VerSe's frames are the centreline's, whose axial rotation is
  a convention): the mean over the vertebrae of |reported − truth| (``axial_rotation_mae_deg``),
  beside its floor, answering 0 (``floor_mae_deg["axial_rotation"]``), and the same of the result's
  directors (``directors_axial_rotation_mae_deg``; reported only where pedicles observed them).

``--seeds N`` runs the convergence sweep instead (``convergence_sweep``): every case, and the
sweep's extra valid forms (``SWEEP_EXTRA_CASES``), on every spine over N noise seeds; each failure
(``FitFailed``, a refusal or any exception) is listed by data set, spine, case and seed in
``clinic-sweep-<split>.json`` (``sweep_stem``: ``-noise<N>``, ``-seeds<first>-<last>`` and
``-drop-levels`` added when used) and a table, and the command exits 1 if there is one. With
``--drop-levels`` each payload keeps a random subset of each view's landmarks (``drop_landmarks``).

``--calibrate-uncertainty`` (dev only) writes the scale factor of the Laplace SDs that makes the
pooled 95 % intervals of positions cover 95 % on dev (``fit.uncertainty``).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import re
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from benches.clinic_films import (
    CASES,
    SID_MM,
    Case,
    FloatArray,
    Series,
    Truth,
    build_payload,
    centreline_measures,
    seed_of,
    simulate_series,
)
from benches.report import format_table, save_figure, shared_data_dir, subplots, write_json
from benches.truth import read_verse
from benches.uncertainty_calibration import calibrate_and_write, coverage
from spine_engine.anatomy import load_profile, rest_shape_unit
from spine_engine.errors import InvalidInput, SpineEngineError
from spine_engine.fit.uncertainty import PRIOR_ONLY_LENKE, calibration
from spine_engine.frames import axial_rotation_deg, frames_from_centreline
from spine_engine.levels import LEVELS, N_LEVELS
from spine_engine.measures import frontal_tilt_deg
from spine_engine.models import LANDMARK_SD_MM_DEFAULT
from spine_engine.reconstruction import register, residual_per_coordinate_mm
from spine_engine.synthetic import generate_spines

# ---------------------------------------------------------------- one reconstruction


@dataclass
class Outcome:
    """The comparison of one reconstruction with its truth (``None`` fields: not reported)."""

    spine_id: str
    case: str
    ok: bool
    error: str = ""
    per_level_mm: FloatArray = field(default_factory=lambda: np.full(N_LEVELS, np.nan))
    error_vectors: FloatArray = field(default_factory=lambda: np.full((N_LEVELS, 3), np.nan))
    """(17, 3) (r_i − r̄) − (t_i − t̄), mm: the errors behind ``per_level_mm``."""
    scale_error_pct: float = float("nan")
    shape_error_mm: float = float("nan")
    """Mean 3D error after removing the best rigid motion (translation and rotation), mm."""
    similarity_error_mm: float = float("nan")
    """Mean 3D error after removing the best similarity (rigid motion and a uniform scale), mm."""
    rotation_error_deg: FloatArray = field(default_factory=lambda: np.full(3, np.nan))
    """That rotation's vector (about x, y, z, LPS), degrees."""
    sagittal_lean_deg: float = float("nan")
    """Its component about the left–right axis (x), degrees."""
    errors_deg: dict[str, float] = field(default_factory=dict)
    """Signed error of each measure computed the same way on result and truth (the centreline
    frames of the positions): kyphosis_t4_t12, kyphosis_t5_t12, lordosis_l1_l5, major_cobb."""
    reported_errors_deg: dict[str, float] = field(default_factory=dict)
    """Signed error of the result's reported measure (its directors) against the same truth."""
    truth_deg: dict[str, float] = field(default_factory=dict)
    """The truth's measures computed the same way (the trivial estimator's errors are measured on them)."""
    floor_rotation_deg: FloatArray = field(default_factory=lambda: np.full(3, np.nan))
    """The best rotation (as ``rotation_error_deg``) of the trivial answer of one PA film
    (``population_sagittal_answer``) onto the truth."""
    axial_rotation_mae_deg: float = float("nan")
    """Mean over the vertebrae of |reported axial rotation − truth's|, where the truth's is known."""
    directors_axial_rotation_mae_deg: float = float("nan")
    """The same of the result's directors' axial rotation (a diagnostic: reported only where pedicles
    observed it)."""
    truth_axial_rotation_mean_abs_deg: float = float("nan")
    """Mean |truth's axial rotation|: the error of answering 0 (the trivial answer)."""
    runtime_ms: float = float("nan")
    uncertainty_scale: float | None = None
    landmark_misfit_ratio: float | None = None
    """``fit.landmark_misfit_ratio``: the Birge ratio B of the image points about the fit."""
    position_z: FloatArray | None = None
    """(17, 3) |error| / SD of each centroid-relative coordinate, or None without SDs."""
    position_sd: FloatArray | None = None
    """(17, 3) the reported SDs, mm."""
    measure_z: dict[str, list[float]] = field(default_factory=dict)
    """Per measure name, |error| / SD of each item with an SD (errors as ``errors_deg``; axial
    rotation: the directors' ψ against the truth's)."""
    reported_z: dict[str, list[float]] = field(default_factory=dict)
    """The same with the reported measures' errors (``reported_errors_deg``)."""


def _z(error: float, sd: float | None) -> float | None:
    if sd is None or not np.isfinite(sd):
        return None
    if sd <= 0.0:
        return 0.0 if error == 0.0 else float("inf")
    return abs(error) / sd


def _turn_deg(a: FloatArray, b: FloatArray) -> FloatArray:
    """a − b wrapped into [−180, 180), degrees."""
    return np.asarray((a - b + 180.0) % 360.0 - 180.0)


def compare(result: dict[str, Any], truth: Truth, case: str, runtime_ms: float) -> Outcome:
    """Metrics of one ``register`` result against its truth (module docstring)."""
    vertebrae = result["vertebrae"]
    r = np.array([v["position"] for v in vertebrae], dtype=float)
    t = truth.positions
    dr, dt_ = r - r.mean(axis=0), t - t.mean(axis=0)
    diff = dr - dt_
    out = Outcome(spine_id=truth.spine_id, case=case, ok=True, runtime_ms=runtime_ms)
    out.error_vectors = diff
    out.per_level_mm = np.linalg.norm(diff, axis=1)
    rms_ratio = np.sqrt(np.mean(np.sum(dr**2, axis=1)) / np.mean(np.sum(dt_**2, axis=1)))
    out.scale_error_pct = 100.0 * (float(rms_ratio) - 1.0)
    out.shape_error_mm, out.rotation_error_deg = rigid_difference(r, t)
    out.similarity_error_mm = similarity_difference(r, t)
    out.sagittal_lean_deg = float(out.rotation_error_deg[0])
    # "computed the same way": the measures of the centreline frames of the positions, on both
    truth_m, same_m = centreline_measures(t), centreline_measures(r)
    m = result["measures"]
    pairs = {
        "kyphosis_t4_t12": ("thoracic_kyphosis_t4_t12_deg", "thoracic_kyphosis_t4_t12_sd_deg"),
        "kyphosis_t5_t12": ("thoracic_kyphosis_t5_t12_deg", "thoracic_kyphosis_t5_t12_sd_deg"),
        "lordosis_l1_l5": ("lumbar_lordosis_l1_l5_deg", "lumbar_lordosis_l1_l5_sd_deg"),
    }
    lenke, truth_lenke = m.get("lenke"), truth_m.lenke
    # Lenke's regional kyphoses T2–T5 and T10–L2, reported only (reported_mae_deg, coverage_reported, floor_mae_deg)
    for name, lenke_key in PRIOR_ONLY_LENKE.items():
        if lenke is None or truth_lenke is None:
            break
        out.truth_deg[name] = float(getattr(truth_lenke, lenke_key))
        out.reported_errors_deg[name] = float(lenke[lenke_key]) - out.truth_deg[name]
        z = _z(out.reported_errors_deg[name], lenke.get(lenke_key.replace("_deg", "_sd_deg")))
        if z is not None:
            out.reported_z.setdefault(name, []).append(z)
    for name, (key, sd_key) in pairs.items():
        error = float(getattr(same_m, key)) - float(getattr(truth_m, key))
        out.errors_deg[name] = error
        out.truth_deg[name] = float(getattr(truth_m, key))
        out.reported_errors_deg[name] = float(m[key]) - float(getattr(truth_m, key))
        for z_store, e in ((out.measure_z, error), (out.reported_z, out.reported_errors_deg[name])):
            z = _z(e, m.get(sd_key))
            if z is not None:
                z_store.setdefault(name, []).append(z)
    tilt_truth = frontal_tilt_deg(frames_from_centreline(t))
    tilt_same = frontal_tilt_deg(frames_from_centreline(r))
    index = {lv: i for i, lv in enumerate(LEVELS)}
    for curve in m["cobb"]:
        iu, il = index[curve["upper"]], index[curve["lower"]]
        truth_angle = abs(float(tilt_truth[iu] - tilt_truth[il]))
        error = abs(float(tilt_same[iu] - tilt_same[il])) - truth_angle
        reported = float(curve["angle_deg"]) - truth_angle
        if curve["major"]:
            out.errors_deg["major_cobb"] = error
            out.reported_errors_deg["major_cobb"] = reported
        for z_store, e in ((out.measure_z, error), (out.reported_z, reported)):
            z = _z(e, curve.get("angle_sd_deg"))
            if z is not None:
                z_store.setdefault("cobb", []).append(z)
    if truth.axial_rotation_known:
        psi_truth = axial_rotation_deg(truth.rotations)
        psi = np.array([v["axial_rotation_deg"] for v in vertebrae], dtype=float)
        d = _turn_deg(psi, psi_truth)
        out.axial_rotation_mae_deg = float(np.mean(np.abs(d)))
        R = np.array([np.asarray(v["directors"], dtype=float).T for v in vertebrae])
        out.directors_axial_rotation_mae_deg = float(np.mean(np.abs(_turn_deg(axial_rotation_deg(R), psi_truth))))
        out.truth_axial_rotation_mean_abs_deg = float(np.mean(np.abs(psi_truth)))
        for i, v in enumerate(vertebrae):
            z = _z(float(d[i]), v.get("axial_rotation_sd_deg"))
            if z is not None:
                out.measure_z.setdefault("axial_rotation", []).append(z)
    sds = [v.get("position_sd_mm") for v in vertebrae]
    if all(s is not None for s in sds):
        sd = np.asarray(sds, dtype=float)
        out.position_sd = sd
        safe = np.where(sd > 0, sd, 1.0)
        out.position_z = np.where(sd > 0, np.abs(diff) / safe, np.where(diff == 0, 0.0, np.inf))
    out.uncertainty_scale = result.get("fit", {}).get("uncertainty_scale")
    out.landmark_misfit_ratio = result.get("fit", {}).get("landmark_misfit_ratio")
    return out


def _aligned(r: FloatArray, t: FloatArray) -> tuple[FloatArray, FloatArray, Rotation]:
    """(Q(r_i − r̄), t_i − t̄, Q) with Q the rotation that best aligns the centred result r on the
    centred truth t (least squares, Kabsch)."""
    dr, dt_ = r - r.mean(axis=0), t - t.mean(axis=0)
    turn, _ = Rotation.align_vectors(dt_, dr)
    return turn.apply(dr), dt_, turn


def rigid_difference(r: FloatArray, t: FloatArray) -> tuple[float, FloatArray]:
    """(mean |Q(r_i − r̄) − (t_i − t̄)| in mm, Q's rotation vector in degrees) with Q the rotation
    that best aligns the centred result r on the centred truth t (least squares, Kabsch). The
    vector's x component is how far the result leans forward or back, its z component how far it is
    turned about the vertical."""
    turned, dt_, turn = _aligned(r, t)
    return float(np.mean(np.linalg.norm(turned - dt_, axis=1))), turn.as_rotvec(degrees=True)


def similarity_difference(r: FloatArray, t: FloatArray) -> float:
    """mean |c Q(r_i − r̄) − (t_i − t̄)| in mm, with Q as in ``rigid_difference`` and c the least-squares
    scale c = Σ (Q d_i)·e_i / Σ |d_i|² (d the centred result, e the centred truth): the shape error that
    remains when the result's size is also corrected."""
    turned, dt_, _ = _aligned(r, t)
    c = float(np.sum(turned * dt_) / np.sum(turned * turned))
    return float(np.mean(np.linalg.norm(c * turned - dt_, axis=1)))


Registrar = Callable[[dict[str, Any]], dict[str, Any]]


def run_one(series: Series, case: Case, profile: str = "default", registrar: Registrar = register) -> Outcome:
    """Film, reconstruct (``registrar``, default ``spine_engine.register``) and compare one spine."""
    try:
        model = build_payload(series, case)
    except ValueError as exc:  # pydantic's ValidationError: a field this engine does not know
        first = str(exc).splitlines()
        return Outcome(series.truth.spine_id, case.key, ok=False, error="payload: " + " ".join(first[:3])[:300])
    payload = model.model_dump(mode="json", exclude_none=True)
    payload.setdefault("options", {})["profile"] = profile
    start = time.perf_counter()
    try:
        result = registrar(payload)
    except SpineEngineError as exc:
        return Outcome(series.truth.spine_id, case.key, ok=False, error=f"{type(exc).__name__}: {exc}"[:300])
    out = compare(result, series.truth, case.key, (time.perf_counter() - start) * 1e3)
    trivial = population_sagittal_answer(series.truth.positions, profile)
    out.floor_rotation_deg = rigid_difference(trivial, series.truth.positions)[1]
    return out


def population_sagittal_answer(truth: FloatArray, profile: str = "default") -> FloatArray:
    """The trivial answer of one PA film (17, 3) mm: the truth's frontal curve (x, z) exactly, and as
    depth y the profile's rest shape (the population's mean sagittal shape) at the same height,
    scaled to the truth's T1–L5 height: what a PA film shows, completed by the population.

    Its best rotation onto the truth (``rigid_difference``) is the floor of the rotation RMS: a
    sagittal shape unlike the population's reads as a turn about the vertical even when nothing turned."""
    rest = rest_shape_unit(load_profile(profile))[1]
    height = truth[0, 2] - truth[-1, 2]
    scale = height / (rest[0, 2] - rest[-1, 2])
    depth = np.interp(truth[0, 2] - truth[:, 2], (rest[0, 2] - rest[:, 2]) * scale, rest[:, 1] * scale)
    answer = np.array(truth, dtype=float)
    answer[:, 1] = truth[0, 1] + depth - depth[0]
    return answer


# ---------------------------------------------------------------- data sets and summaries


def verse_truths(split: str, data: Path | None = None) -> list[Truth]:
    """The VerSe spines of ``split`` with directors from the centreline."""
    path = (data or shared_data_dir("verse")) / f"{split}.csv"
    if not path.is_file():
        raise FileNotFoundError(f"VerSe split not found at {path} (pass --data or set SPINE_SHARED_DATA)")
    return truths_of_csv(path)


def truths_of_csv(path: Path) -> list[Truth]:
    """The spines of a VerSe CSV (``benches.truth.read_verse``) with directors from the centreline;
    their axial rotation is the centreline's convention, not a measurement."""
    return [Truth(sid, pos, frames_from_centreline(pos), axial_rotation_known=False) for sid, pos in read_verse(path)]


SYNTHETIC_SEED_OF_SPLIT = {"test": 0, "dev": 10_000}
"""Added to ``--seed`` to draw the synthetic spines of each split: the spines tuned on (``--split dev``)
are not the spines reported (``--split test``), as for VerSe."""


def synthetic_truths(n: int, seed: int, split: str = "test") -> list[Truth]:
    """``n`` synthetic spines of ``spine_engine.synthetic`` (geometric, with axial rotation), drawn
    for ``split`` (``SYNTHETIC_SEED_OF_SPLIT``)."""
    return generated_truths(n, seed + SYNTHETIC_SEED_OF_SPLIT[split])


def generated_truths(n: int, seed: int) -> list[Truth]:
    """``generate_spines(n, seed)`` as truths."""
    return [
        Truth(f"synthetic-{s.seed}", np.asarray(s.positions), np.asarray(s.rotations))
        for s in generate_spines(n, seed=seed)
    ]


MEASURES = ("kyphosis_t4_t12", "kyphosis_t5_t12", "lordosis_l1_l5", "cobb", "axial_rotation")


def _mean(values: list[float]) -> float | None:
    a = np.asarray(values, dtype=float)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else None


def rms_rotation_error(outcomes: Sequence[Outcome]) -> list[float] | None:
    """RMS over the spines of the best rotation's components about x, y, z (degrees), None if none."""
    if not outcomes:
        return None
    vectors = np.array([o.rotation_error_deg for o in outcomes])
    return np.sqrt(np.mean(vectors**2, axis=0)).round(3).tolist()


def population_means(profile: str = "default") -> dict[str, float]:
    """The trivial estimator's answer: VerSe dev's mean kyphosis T4–T12 and lordosis L1–L5 (computed as
    this bench computes a truth's), from the profile's population prior provenance, and of Lenke's
    regional kyphoses T2–T5 and T10–L2, from the uncertainty calibration's ``prior_only`` readings."""
    data = load_profile(profile).population_prior or {}
    population = data.get("provenance", {}).get("population", {})
    means = {name: float(population[key]["mean"]) for name, key in (
        ("kyphosis_t4_t12", "kyphosis_t4_t12_deg"), ("lordosis_l1_l5", "lordosis_l1_l5_deg")) if key in population}
    readings = calibration().prior_only  # Lenke's regional kyphoses: VerSe dev's means, as the calibration read them
    means.update({name: readings[name].population_mean_deg for name in PRIOR_ONLY_LENKE if name in readings})
    return means


def summarise(
    dataset: str, case: Case, outcomes: list[Outcome], floor: dict[str, float] | None = None
) -> dict[str, Any]:
    """One row of the table: means over the spines reconstructed, and coverages (with their
    item counts). ``floor``: the population-mean estimator's answers (``population_means``), whose
    MAE on the same spines is the row's ``floor_mae_deg``."""
    ok = [o for o in outcomes if o.ok]
    per_level = np.array([o.per_level_mm for o in ok]) if ok else np.empty((0, N_LEVELS))
    pos_z = [o.position_z for o in ok if o.position_z is not None]
    row: dict[str, Any] = {
        "dataset": dataset,
        "case": case.key,
        "title": case.title,
        "spines": len(outcomes),
        "reconstructed": len(ok),
        "errors": sorted({o.error for o in outcomes if not o.ok})[:3],
        "mean_3d_error_mm": float(per_level.mean()) if ok else None,
        "max_3d_error_mm": float(per_level.max()) if ok else None,
        "scale_error_abs_pct": _mean([abs(o.scale_error_pct) for o in ok]),
        "shape_error_mm": _mean([o.shape_error_mm for o in ok]),
        "similarity_error_mm": _mean([o.similarity_error_mm for o in ok]),
        "sagittal_lean_rms_deg": float(np.sqrt(np.mean([o.sagittal_lean_deg**2 for o in ok]))) if ok else None,
        "rotation_error_rms_deg_xyz": rms_rotation_error(ok),
        "kyphosis_t4_t12_mae_deg": _mean([abs(o.errors_deg.get("kyphosis_t4_t12", np.nan)) for o in ok]),
        "kyphosis_t5_t12_mae_deg": _mean([abs(o.errors_deg.get("kyphosis_t5_t12", np.nan)) for o in ok]),
        "lordosis_l1_l5_mae_deg": _mean([abs(o.errors_deg.get("lordosis_l1_l5", np.nan)) for o in ok]),
        "major_cobb_mae_deg": _mean([abs(o.errors_deg.get("major_cobb", np.nan)) for o in ok]),
        "axial_rotation_mae_deg": _mean([o.axial_rotation_mae_deg for o in ok]),
        "directors_axial_rotation_mae_deg": _mean([o.directors_axial_rotation_mae_deg for o in ok]),
        "reported_mae_deg": {
            name: _mean([abs(o.reported_errors_deg.get(name, np.nan)) for o in ok])
            for name in ("kyphosis_t4_t12", "kyphosis_t5_t12", "lordosis_l1_l5", "major_cobb", *PRIOR_ONLY_LENKE)
        },
        "reported_bias_deg": {
            name: _mean([o.reported_errors_deg.get(name, np.nan) for o in ok])
            for name in ("kyphosis_t4_t12", "lordosis_l1_l5", "major_cobb")
        },
        "median_runtime_ms": float(np.median([o.runtime_ms for o in ok])) if ok else None,
        "per_level_mean_mm": dict(zip(LEVELS, per_level.mean(axis=0).round(3).tolist(), strict=True)) if ok else None,
        "coverage_positions": coverage(np.concatenate([z.ravel() for z in pos_z])) if pos_z else None,
        "coverage_positions_n": int(sum(z.size for z in pos_z)),
    }
    if pos_z:
        stacked = np.stack(pos_z)
        row["coverage_positions_xyz"] = [coverage(stacked[:, :, k]) for k in range(3)]
        sds = np.stack([o.position_sd for o in ok if o.position_sd is not None])
        row["median_position_sd_mm_xyz"] = np.median(sds, axis=(0, 1)).round(3).tolist()
    for name in MEASURES:
        z = [v for o in ok for v in o.measure_z.get(name, [])]
        row[f"coverage_{name}"] = coverage(z)
        row[f"coverage_{name}_n"] = len(z)
    row["coverage_reported"] = {
        name: coverage([v for o in ok for v in o.reported_z.get(name, [])])
        for name in (*MEASURES[:4], *PRIOR_ONLY_LENKE)
    }
    scales = {o.uncertainty_scale for o in ok if o.uncertainty_scale is not None}
    row["uncertainty_scale"] = scales.pop() if len(scales) == 1 else None
    ratios = [o.landmark_misfit_ratio for o in ok if o.landmark_misfit_ratio is not None]
    row["landmark_misfit_ratio_median_p90"] = (
        [round(float(np.median(ratios)), 3), round(float(np.percentile(ratios, 90)), 3)] if ratios else None
    )
    row["floor_rotation_rms_deg_xyz"] = (
        np.sqrt(np.mean([o.floor_rotation_deg**2 for o in ok], axis=0)).round(3).tolist() if ok else None
    )
    row["floor_mae_deg"] = {
        name: _mean([abs(mean - o.truth_deg[name]) for o in ok if name in o.truth_deg])
        for name, mean in (floor or {}).items()
    }
    row["floor_mae_deg"]["axial_rotation"] = _mean([o.truth_axial_rotation_mean_abs_deg for o in ok])
    return row


def run(
    datasets: dict[str, list[Truth]],
    cases: Sequence[Case],
    noise_mm: float,
    seed: int,
    profile: str = "default",
    registrar: Registrar = register,
    sid_mm: float = SID_MM,
) -> tuple[list[dict[str, Any]], dict[tuple[str, str], list[Outcome]]]:
    """Every case on every spine of every data set, the films taken at ``sid_mm``: summary rows and
    the outcomes behind them."""
    rows, outcomes = [], {}
    floor = population_means(profile)
    for name, truths in datasets.items():
        series = [simulate_series(t, noise_mm, seed, sid_mm) for t in truths]
        for case in cases:
            found = [run_one(s, case, profile, registrar) for s in series]
            outcomes[(name, case.key)] = found
            rows.append(summarise(name, case, found, floor))
    return rows, outcomes


# ---------------------------------------------------------------- convergence sweep


@dataclass(frozen=True)
class SweepCase:
    """A valid payload form of the convergence sweep: a bench ``Case``, optionally with the
    acquisition's central ray left out (the usual DX header: SID and SOD, no central ray)."""

    case: Case
    central_ray: bool = True


SWEEP_EXTRA_CASES = (
    SweepCase(Case("c0", "perspective PA + lateral, SID and SOD without central ray", perspective=True,
                   acquisition=True), central_ray=False),
    SweepCase(Case("e0", "perspective PA only, SID and SOD without central ray", lateral_from=None,
                   perspective=True, acquisition=True), central_ray=False),
)
"""Sweep-only forms beside ``CASES``: the films of (c) as a DX header describes them (SID and SOD
without the central ray), with and without the lateral. With one film the central ray and the
spine's place in the film trade almost exactly (only the perspective's depth dependence tells them
apart), the slowest valley the solver meets."""


def sweep_payload(series: Series, sweep_case: SweepCase) -> dict[str, Any]:
    """The JSON payload of ``sweep_case`` for ``series`` (``build_payload``, central ray removed
    when the form has none)."""
    payload = build_payload(series, sweep_case.case).model_dump(mode="json", exclude_none=True)
    if not sweep_case.central_ray:
        for name in ("pa", "lateral"):
            if name in payload and "acquisition" in payload[name]:
                payload[name]["acquisition"].pop("central_ray", None)
    return payload


MIN_KEPT = 3
"""Fewest landmarks ``drop_landmarks`` keeps in a view."""


def drop_landmarks(payload: dict[str, Any], rng: np.random.Generator) -> dict[str, list[str]]:
    """Keep in each view of ``payload`` (in place) a random subset of its landmarks, at least half of
    them and at least 3 (``MIN_KEPT``), in their order; returns the levels kept per view. A spine's
    landmarks with levels left out are as valid as all of them: a film may not show every vertebra."""
    kept = {}
    for name in ("pa", "lateral"):
        view = payload.get(name)
        if not view:
            continue
        n = len(view["landmarks"])
        size = int(rng.integers(min(n, max(MIN_KEPT, -(-n // 2))), n + 1))
        keep = np.sort(rng.choice(n, size=size, replace=False))
        view["landmarks"] = [view["landmarks"][k] for k in keep]
        kept[name] = [lm["level"] for lm in view["landmarks"]]
    return kept


def residual_to_sd(payload: dict[str, Any], result: dict[str, Any]) -> float:
    """The largest over the views of the landmark residual, RMS per image coordinate (√(mean d²/2),
    d each landmark's distance to the fit, ``fit.residuals``, ``reconstruction.residual_per_coordinate_mm``),
    over the view's landmark SD (stated, else ``LANDMARK_SD_MM_DEFAULT``): what
    ``reconstruction.LANDMARK_SD_CONTRADICTED`` bounds."""
    ratios = []
    for view in ("pa", "lateral"):
        d = [r["residual_mm"] for r in result["fit"]["residuals"] if r["view"] == view]
        if view in payload and d:
            sd = payload[view].get("landmark_sd_mm") or LANDMARK_SD_MM_DEFAULT
            ratios.append(residual_per_coordinate_mm(d) / sd)
    return max(ratios, default=0.0)


def convergence_sweep(
    datasets: dict[str, list[Truth]],
    cases: Sequence[SweepCase],
    seeds: Sequence[int],
    noise_mm: float,
    profile: str = "default",
    registrar: Registrar = register,
    drop_levels: bool = False,
    stated_sd_mm: float | None = None,
    sid_mm: float = SID_MM,
) -> dict[str, Any]:
    """Every case on every spine over every noise seed (``simulate_series(truth, noise_mm, seed, sid_mm)``):
    the runs per case and every failure (``FitFailed``, ``InvalidInput`` or any other exception:
    each payload is valid, so each failure is a defect) with its data set, spine, case and seed; per
    case the most solver iterations and the largest and median landmark residual over its stated SD
    (``residual_to_sd``) of the runs that succeeded.
    ``drop_levels``: each payload keeps a random subset of each view's landmarks (``drop_landmarks``,
    drawn from the seed, the spine and the case), listed with a failure. ``stated_sd_mm``: each view
    states this landmark SD instead of the noise drawn (a wrong statement on purpose): a refusal for
    ``landmark_sd_contradicted`` is then the expected answer, counted per case
    (``refused_sd_contradicted``, not a failure) with the ratio its message gives
    (``contradicted_ratio``) among the residual-to-SD ratios."""
    failures: list[dict[str, Any]] = []
    per_case: dict[str, dict[str, Any]] = {
        sc.case.key: {"title": sc.case.title, "runs": 0, "failures": 0, "max_iterations": 0, "max_residual_to_sd": 0.0,
                      "refused_sd_contradicted": 0}
        for sc in cases
    }
    ratios: dict[str, list[float]] = {sc.case.key: [] for sc in cases}
    for seed in seeds:
        for name, truths in datasets.items():
            for truth in truths:
                series = simulate_series(truth, noise_mm, seed, sid_mm)
                for sc in cases:
                    payload = sweep_payload(series, sc)
                    payload.setdefault("options", {})["profile"] = profile
                    kept = None
                    if drop_levels:
                        draw = np.random.default_rng([seed, seed_of(truth.spine_id), *sc.case.key.encode()])
                        kept = drop_landmarks(payload, draw)
                    if stated_sd_mm is not None:
                        for name in ("pa", "lateral"):
                            if name in payload:
                                payload[name]["landmark_sd_mm"] = stated_sd_mm
                    row = per_case[sc.case.key]
                    row["runs"] += 1
                    try:
                        result = registrar(payload)
                    except Exception as exc:  # any exception on a valid payload is a failure to report
                        ratio = contradicted_ratio(exc)
                        if stated_sd_mm is not None and ratio is not None:
                            row["refused_sd_contradicted"] += 1
                            ratios[sc.case.key].append(ratio)
                            row["max_residual_to_sd"] = max(row["max_residual_to_sd"], ratio)
                            continue
                        row["failures"] += 1
                        failures.append({
                            "dataset": name, "spine": truth.spine_id, "case": sc.case.key, "seed": seed,
                            "error": f"{type(exc).__name__}: {exc}"[:300], **({"levels": kept} if kept else {}),
                        })  # fmt: skip
                        continue
                    row["max_iterations"] = max(row["max_iterations"], int(result["fit"]["iterations"]))
                    ratios[sc.case.key].append(residual_to_sd(payload, result))
                    row["max_residual_to_sd"] = max(row["max_residual_to_sd"], ratios[sc.case.key][-1])
    for key, row in per_case.items():
        row["median_residual_to_sd"] = float(np.median(ratios[key])) if ratios[key] else None
    runs = sum(r["runs"] for r in per_case.values())
    return {"seeds": list(seeds), "drop_levels": drop_levels, "stated_sd_mm": stated_sd_mm, "runs": runs,
            "failed": len(failures), "per_case": per_case, "failures": failures}


CONTRADICTED_RATIO = re.compile(r"([0-9.]+(?:e[+-]?[0-9]+)?) times the landmark SD")
"""The ratio in ``reconstruction``'s ``landmark_sd_contradicted`` message: the landmarks' RMS distance per
coordinate from the fitted spine over the view's SD."""


def contradicted_ratio(exc: Exception) -> float | None:
    """The largest residual-to-SD ratio that a ``landmark_sd_contradicted`` refusal states (its
    message, ``CONTRADICTED_RATIO``; 3 significant digits), None for any other exception."""
    if not isinstance(exc, InvalidInput):
        return None
    found = [float(m.group(1)) for e in exc.errors if e.type == "landmark_sd_contradicted"
             for m in [CONTRADICTED_RATIO.search(e.msg)] if m]  # fmt: skip
    return max(found) if found else None


def sweep_table(sweep: dict[str, Any]) -> str:
    """The sweep as text: runs, failures and the most solver iterations per case, then each failure."""
    body = format_table(
        ["case", "runs", "failed", "max iter", "max residual / SD", "median", "refused: SD", "title"],
        [[k, r["runs"], r["failures"], r["max_iterations"], f"{r['max_residual_to_sd']:.2f}",
          "-" if r["median_residual_to_sd"] is None else f"{r['median_residual_to_sd']:.2f}",
          r["refused_sd_contradicted"], r["title"]]
         for k, r in sweep["per_case"].items()],
    )
    if not sweep["failures"]:
        return body + f"\nno failure in {sweep['runs']} runs (seeds {sweep['seeds']})"
    failed = format_table(
        ["data", "spine", "case", "seed", "error"],
        [[f["dataset"], f["spine"], f["case"], f["seed"], f["error"]] for f in sweep["failures"]],
    )
    return f"{body}\nfailures ({sweep['failed']} of {sweep['runs']} runs):\n{failed}"


# ---------------------------------------------------------------- output


TABLE_COLUMNS = [
    ("dataset", "data"),
    ("case", "case"),
    ("reconstructed", "ok"),
    ("mean_3d_error_mm", "3D mm"),
    ("scale_error_abs_pct", "|scale| %"),
    ("shape_error_mm", "shape mm"),
    ("similarity_error_mm", "no-scale mm"),
    ("sagittal_lean_rms_deg", "lean°"),
    ("reported_kyphosis_t4_t12", "kyph°"),
    ("floor_kyphosis", "floor"),
    ("reported_lordosis_l1_l5", "lord°"),
    ("floor_lordosis", "floor"),
    ("reported_major_cobb", "Cobb°"),
    ("major_cobb_mae_deg", "Cobb° cl"),
    ("coverage_positions", "cov pos"),
    ("covreported_kyphosis_t4_t12", "cov kyph"),
    ("covreported_lordosis_l1_l5", "cov lord"),
    ("covreported_cobb", "cov Cobb"),
    ("coverage_axial_rotation", "cov rot"),
    ("axial_rotation_mae_deg", "rot°"),
    ("floor_axial_rotation", "floor"),
]
"""The measures are the result's (``reported_…``: what a user reads, and the coverage of its
intervals); "Cobb° cl" is the major Cobb angle of the result's centreline, as the truth's is measured."""


def _value(row: dict[str, Any], key: str) -> Any:
    """A row's entry; ``floor_<measure>``: the population-mean estimator's MAE on the same spines;
    ``reported_<measure>`` / ``covreported_<measure>``: the MAE / coverage of the result's measure."""
    if key.startswith("floor_"):
        measure = {"floor_kyphosis": "kyphosis_t4_t12", "floor_lordosis": "lordosis_l1_l5"}.get(key, key[6:])
        return row["floor_mae_deg"].get(measure)
    if key.startswith("reported_"):
        return row["reported_mae_deg"].get(key.removeprefix("reported_"))
    if key.startswith("covreported_"):
        return row["coverage_reported"].get(key.removeprefix("covreported_"))
    return row[key]


def _cell(value: Any) -> Any:
    if value is None:
        return "-"
    if isinstance(value, float):
        return round(value, 3)
    return value


def table(rows: list[dict[str, Any]]) -> str:
    """The summary as an aligned plain-text table (``-``: not available), then the cases' titles
    and the errors of refused cases."""
    body = format_table([h for _, h in TABLE_COLUMNS], [[_cell(_value(r, k)) for k, _ in TABLE_COLUMNS] for r in rows])
    notes = [f"  ({c.key}) {c.title}" for c in CASES.values() if any(r["case"] == c.key for r in rows)]
    refused = [f"  {r['dataset']} ({r['case']}): {e}" for r in rows for e in r["errors"]]
    return "\n".join([body, "cases:", *notes, *(["refused or failed:", *refused] if refused else [])])


MARKDOWN_COLUMNS = [
    ("shape_error_mm", "shape error (mm)"),
    ("similarity_error_mm", "scale removed too (mm)"),
    ("mean_3d_error_mm", "3D error (mm)"),
    ("rotation_error_rms_deg_xyz", "rotation RMS x/y/z (°)"),
    ("reported_kyphosis_t4_t12", "kyphosis MAE (°)"),
    ("floor_kyphosis", "floor"),
    ("reported_lordosis_l1_l5", "lordosis MAE (°)"),
    ("floor_lordosis", "floor"),
    ("reported_major_cobb", "major Cobb MAE (°)"),
    ("major_cobb_mae_deg", "centreline's"),
    ("coverage_positions", "cov. positions"),
    ("covreported_kyphosis_t4_t12", "cov. kyphosis"),
    ("covreported_lordosis_l1_l5", "cov. lordosis"),
    ("covreported_cobb", "cov. Cobb"),
    ("coverage_axial_rotation", "cov. axial rot."),
    ("axial_rotation_mae_deg", "axial rot. MAE (°)"),
    ("floor_axial_rotation", "floor"),
]
"""The columns of ``markdown_table`` after data, case and ok: docs/accuracy.md's clinic table."""


def markdown_table(rows: list[dict[str, Any]]) -> str:
    """The summary as docs/accuracy.md's clinic table (``MARKDOWN_COLUMNS``; the cases' titles are in
    the docs' text)."""
    head = ["data", "case", "ok", *(h for _, h in MARKDOWN_COLUMNS)]
    lines = ["| " + " | ".join(head) + " |", "| " + " | ".join(["---"] * 2 + ["---:"] * (len(head) - 2)) + " |"]
    for r in rows:
        cells = [r["dataset"], f"({r['case']})", f"{r['reconstructed']}/{r['spines']}"]
        for key, _ in MARKDOWN_COLUMNS:
            v = _value(r, key)
            if v is None:
                cells.append("–")
            elif key == "rotation_error_rms_deg_xyz":
                cells.append("/".join(f"{x:.2f}" for x in v))
            elif key.startswith(("coverage", "covreported")):
                cells.append(f"{round(100 * v)} %")
            else:
                cells.append(f"{v:.2f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    """Mean 3D error per case and data set (left) and coverage of the 95 % position intervals
    with the 90–98 % target band (right)."""
    fig, (ax1, ax2) = subplots(1, 2, figsize=(11, 4))
    datasets = list(dict.fromkeys(r["dataset"] for r in rows))
    keys = list(dict.fromkeys(r["case"] for r in rows))
    width = 0.8 / max(len(datasets), 1)
    for k, name in enumerate(datasets):
        by_case = {r["case"]: r for r in rows if r["dataset"] == name}
        x = np.arange(len(keys)) + (k - (len(datasets) - 1) / 2) * width
        err = [by_case[c]["mean_3d_error_mm"] if by_case.get(c) and by_case[c]["mean_3d_error_mm"] is not None
               else np.nan for c in keys]
        cov = [100 * by_case[c]["coverage_positions"] if by_case.get(c) and by_case[c]["coverage_positions"] is not None
               else np.nan for c in keys]
        ax1.bar(x, err, width, label=name)
        ax2.bar(x, cov, width, label=name)
    for ax in (ax1, ax2):
        ax.set_xticks(np.arange(len(keys)), [f"({c})" for c in keys])
        ax.set_xlabel("case")
    ax1.set_yscale("log")
    ax1.set(ylabel="mean 3D error after removing translation (mm)", title="3D error, 1 mm landmark noise")
    ax2.axhspan(90, 98, color="0.85", zorder=0, label="target 90–98 %")
    ax2.axhline(95, color="0.4", lw=0.8)
    ax2.set(ylabel="coverage of ±1.96 SD, positions (%)", ylim=(60, 100), title="calibrated 95 % intervals")
    ax1.legend(fontsize=8)
    ax2.legend(fontsize=8, loc="lower right")
    save_figure(fig, path)


# ---------------------------------------------------------------- command


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="spine bench clinic", description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="VerSe folder with dev.csv and test.csv")
    parser.add_argument("--split", choices=["dev", "test"], default="test", help="VerSe split (default test)")
    parser.add_argument("--synthetic", type=int, default=20, help="number of synthetic spines (0: none)")
    parser.add_argument("--limit", type=int, default=None, help="use only the first N VerSe spines")
    parser.add_argument("--cases", default="".join(CASES), help="case letters to run, e.g. ace (default all)")
    parser.add_argument("--noise-mm", type=float, default=1.0, help="landmark noise SD, detector mm (default 1)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--seeds", type=int, default=None, metavar="N",
        help="convergence sweep: run every case (and the sweep's extra forms, SWEEP_EXTRA_CASES) over N noise "
        "seeds from --seed on, report each failure; exit code 1 if any",
    )
    parser.add_argument("--drop-levels", action="store_true",
                        help="with --seeds: each payload keeps a random subset of each view's landmarks "
                             "(at least half, at least 3)")
    parser.add_argument("--stated-sd-mm", type=float, default=None, metavar="SD",
                        help="with --seeds: each view states this landmark SD instead of --noise-mm (refusals for "
                             "a contradicted SD are counted, not failures)")
    parser.add_argument("--sid-mm", type=float, default=SID_MM, metavar="SID",
                        help="take the films at this SID, the PA's spine 200 mm before its detector (default "
                             f"{SID_MM:g}, full-spine radiography's); the JSON is then clinic-<split>-sid<SID>, "
                             "the sweep's clinic-sweep-<split>-sid<SID>")
    parser.add_argument("--profile", default="default")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON instead of a table")
    parser.add_argument("--out", type=Path, default=Path("bench-out/clinic"), help="folder of the JSON and PNG")
    parser.add_argument("--plot", type=Path, default=None, help="also write the plot here (e.g. docs/img/...)")
    parser.add_argument("--markdown", action="store_true", help="also print the markdown table")
    parser.add_argument(
        "--calibrate-uncertainty", action="store_true",
        help="(dev) compute the uncertainty scale that makes 95 %% intervals cover 95 %% and write it",
    )
    args = parser.parse_args(argv)
    unknown = [c for c in args.cases if c not in CASES]
    if unknown:
        print(f"error: unknown case(s) {unknown}; known: {list(CASES)}", file=sys.stderr)
        return 2
    cases = [CASES[c] for c in args.cases]
    if args.sid_mm != SID_MM and args.calibrate_uncertainty:
        print("error: the calibration's films are taken at full-spine radiography's SID (no --sid-mm)", file=sys.stderr)
        return 2
    try:
        verse = verse_truths(args.split, args.data)
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.limit is not None:
        verse = verse[: args.limit]
    command = "spine bench clinic " + " ".join(argv if argv is not None else sys.argv[1:])
    calibrated: dict[str, Any] = {}
    start = time.perf_counter()
    if args.calibrate_uncertainty:
        if args.split != "dev":
            print("error: calibrate on the dev split only (--split dev); test is reported, never tuned on",
                  file=sys.stderr)
            return 2
        calibrated = calibrate_and_write(command, args.split, verse, cases, args.noise_mm, args.seed, args.profile)
    datasets = {f"verse-{args.split}": verse}
    if args.synthetic > 0 and not args.calibrate_uncertainty:
        datasets["synthetic"] = synthetic_truths(args.synthetic, args.seed, args.split)
    if args.seeds is not None:
        return _sweep_main(args, command, datasets, cases)
    rows, _ = run(datasets, cases, args.noise_mm, args.seed, args.profile, sid_mm=args.sid_mm)
    elapsed = time.perf_counter() - start
    report: dict[str, Any] = {
        "command": command,
        "date": dt.date.today().isoformat(),
        "noise_mm": args.noise_mm,
        "seed": args.seed,
        "sid_mm": args.sid_mm,
        "profile": args.profile,
        "seconds": round(elapsed, 1),
        **calibrated,
        "rows": rows,
    }
    stem = f"clinic-{args.split}" + ("" if args.sid_mm == SID_MM else f"-sid{args.sid_mm:g}")
    write_json(args.out / f"{stem}.json", report)
    plot(rows, args.out / f"{stem}.png")
    if args.plot:
        plot(rows, args.plot)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(table(rows))
        if args.markdown:
            print()
            print(markdown_table(rows))
        if calibrated:
            print(f"uncertainty_scale {calibrated['uncertainty_scale']:.4f}, prior_weight "
                  f"{calibrated['prior_weight']:.4g} (written to {calibrated['calibration_file']})")
        print(f"wrote {args.out}/{stem}.json and .png ({elapsed:.1f} s)")
    return 0


SWEEP_SEEDS = range(3)
"""The noise seeds of the sweeps docs/engine.md cites (``--seeds 3``, from ``--seed 0``)."""


def sweep_stem(
    split: str, noise_mm: float, drop_levels: bool, seeds: range = SWEEP_SEEDS, stated_sd_mm: float | None = None,
    sid_mm: float = SID_MM,
) -> str:
    """The sweep's file name without ``.json``: ``clinic-sweep-<split>``, then ``-noise<N>`` when the
    landmark noise is not the default 1 mm, ``-stated<SD>`` with ``--stated-sd-mm``, ``-sid<SID>`` with films
    taken at another SID than ``SID_MM``, ``-seeds<first>-<last>``
    when the seeds are not ``SWEEP_SEEDS`` and ``-drop-levels`` with ``--drop-levels``, so that each sweep
    keeps its own file."""
    noise = "" if noise_mm == 1.0 else f"-noise{noise_mm:g}"
    stated = "" if stated_sd_mm is None else f"-stated{stated_sd_mm:g}"
    drawn = "" if seeds == SWEEP_SEEDS else f"-seeds{seeds[0]}-{seeds[-1]}"
    sid = "" if sid_mm == SID_MM else f"-sid{sid_mm:g}"
    return f"clinic-sweep-{split}{noise}{stated}{sid}{drawn}" + ("-drop-levels" if drop_levels else "")


def _sweep_main(args: argparse.Namespace, command: str, datasets: dict[str, list[Truth]], cases: list[Case]) -> int:
    """``--seeds N``: the convergence sweep, its JSON (``sweep_stem``) and table."""
    start = time.perf_counter()
    extra = [sc for sc in SWEEP_EXTRA_CASES if sc.case.key[0] in args.cases]
    seeds = range(args.seed, args.seed + args.seeds)
    sweep = convergence_sweep(
        datasets, [SweepCase(c) for c in cases] + extra, seeds, args.noise_mm, args.profile,
        drop_levels=args.drop_levels, stated_sd_mm=args.stated_sd_mm, sid_mm=args.sid_mm,
    )
    report = {"command": command, "noise_mm": args.noise_mm, "sid_mm": args.sid_mm, "profile": args.profile,
              "seconds": round(time.perf_counter() - start, 1), **sweep}  # fmt: skip
    stem = sweep_stem(args.split, args.noise_mm, args.drop_levels, seeds, args.stated_sd_mm, args.sid_mm)
    write_json(args.out / f"{stem}.json", report)
    print(json.dumps(report, indent=2) if args.json else sweep_table(sweep))
    return 1 if sweep["failures"] else 0


if __name__ == "__main__":
    raise SystemExit(main())
