"""Cobb angles on real PA radiographs (AASCE 2019 / SpineWeb dataset 16): corners and midpoints.

Each radiograph of a split has 4 corners per vertebra T1..L5 annotated by clinicians (pixels,
``landmarks_px_from_mat.csv``) and three Cobb angles (``angles.csv``: the major curve first, then
the curves above and below it) measured on those corners by the data set's own script. Per
radiograph, with no boundary conditions (the data has no 3D):

* (a) **corners**: the 68 corners go into the payload; ``measures.cobb``'s major curve uses the
  corner lines' tilts (the definition the angles were measured with);
* (a-model) the same fit, the major angle from the reconstructed vertebrae's d1 instead;
* (b) **midpoints**: only the 17 superior endplate midpoints (the paper's form), through the
  reconstruction with the tilt prior (``spine_engine.tilt_prior``, calibrated on ``training``);
* (b-no-prior) the same without the prior, and (b-line) the straight-chord baseline: each
  vertebra perpendicular to the chords of its midpoints (mean of the chords above and below);
* (b-largest) the fit of (b), read in ``measures.largest_cobb``: the largest frontal angle
  whatever its size, where (b) reads 0 for a spine whose curves are all below the 10° reporting
  threshold (the data set's angles are measured on every spine, without threshold).

Reported: the mean absolute error of the major angle and the challenge's SMAPE over the three
angles (per radiograph Σ|a − b| / Σ(a + b) × 100, averaged), the latter with the dataset script's
rules for the two minor angles (``aasce_angles``) applied to each method's vertebra axes.
Pixels are taken as square (pixel spacing [1, 1]: the data has no mm scale; angles do not depend
on it). ``--calibrate`` fits the tilt prior on ``training`` (never on ``test``) and writes it;
``--calibrate-cobb-sd`` then sets the SD its Cobb angles gain (``TiltPrior.cobb_sd_deg``) so that
the major angle's 95 % interval covers 95 % of ``training``. The coverage of that interval on the
split is reported beside the errors (midpoint methods: corner lines have no model SD to judge).
``--cv`` compares variants of the prior (chord window, end-vertebra weighting, weight fraction) by
k-fold cross-validation on ``training`` of the major angle through the reconstruction; it changes
nothing. The data is read from its folder and never copied into the repository.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benches.clinic import residual_to_sd
from benches.report import format_table, save_figure, shared_data_dir, subplots, write_json
from spine_engine.anatomy import VERTEBRA_TABLE, rest_segment_lengths
from spine_engine.errors import FitFailed, InvalidInput
from spine_engine.levels import LEVELS, N_LEVELS
from spine_engine.measures import frontal_tilt_deg
from spine_engine.models import PA_ORIENTATION
from spine_engine.observations import chord_angles_deg, frontal_tilt_deg_of_image_vectors
from spine_engine.projection import image_axes
from spine_engine.reconstruction import MODEL_TILT_ENDS, register, register_model
from spine_engine.tilt_prior import (
    DEFAULT_PRIOR,
    PRIORS_DIR,
    WINDOW,
    TiltPrior,
    fit_coefficients,
    load_tilt_prior,
    predict_tilts_deg,
    save_tilt_prior,
    toward_chord_normal,
)
from spine_engine.validation import validate_payload

DATE = "2026-12-03"
PLAUSIBLE_CHORD_DEG = 60.0
"""A radiograph whose superior endplate midpoints make a chord steeper than this (or going up) has
a misplaced landmark (e.g. an L5 annotated at the top of the image): left out of calibration."""
MAJOR_LIMIT_DEG = 90.0
"""Training radiographs with a major angle at or above this are left out of calibration (``tunes_the_prior``)."""
WEIGHT_FRACTIONS = (0.3, 1.0, 3.0, 10.0, 30.0)
"""Candidate weights of the prior's tilts relative to corner tilts, tried on ``training`` (below 0.3 the
MAE only grows: 3.47° at 0.3 up to 12.6° at 0.001 with the window −2..+1, clipped)."""
FRACTION_TIE_DEG = 0.01
"""Weight fractions whose training MAE is within this of the lowest count as equal (the smallest wins)."""
CAL_WINDOW: tuple[int, ...] = tuple(range(-3, 3))
CAL_PLACEMENT = "shifted"
RIDGE = 1e-3
BLENDS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5)
"""Candidate blends β toward the chord-normal tilt (``tilt_prior.toward_chord_normal``)."""


def default_data_dir() -> Path:
    return shared_data_dir("aasce2019")


@dataclass(frozen=True)
class Radiograph:
    name: str
    height_px: float
    corners: np.ndarray  # (17, 4, 2) px: top-left, top-right, bottom-left, bottom-right
    angles: np.ndarray  # (3,) degrees: major, above, below


def read_split(folder: Path) -> list[Radiograph]:
    """Radiographs of a split folder: ``landmarks_px_from_mat.csv`` (header; filename, img_w_est,
    img_h_est, then x0, y0, …, x67, y67 in pixels, 4 corners per vertebra T1..L5) and
    ``angles.csv`` (3 columns, same row order; checked against ``filenames.csv``)."""
    with (folder / "landmarks_px_from_mat.csv").open(newline="") as fh:
        rows = list(csv.reader(fh))
    header, rows = rows[0], rows[1:]
    expected = ["filename", "img_w_est", "img_h_est"] + [f"{a}{k}" for k in range(4 * N_LEVELS) for a in "xy"]
    if header != expected:
        raise ValueError(
            f"{folder}/landmarks_px_from_mat.csv: unexpected header (want filename, img_w_est, "
            "img_h_est, x0, y0, ..., x67, y67)"
        )
    angles = np.loadtxt(folder / "angles.csv", delimiter=",", ndmin=2)
    names = [line.strip() for line in (folder / "filenames.csv").read_text().splitlines() if line.strip()]
    if len(rows) != len(angles) or [r[0] for r in rows] != names:
        raise ValueError(f"{folder}: landmarks, angles and filenames do not list the same radiographs in order")
    return [
        Radiograph(r[0], float(r[2]), np.asarray(r[3:], dtype=float).reshape(N_LEVELS, 4, 2), a)
        for r, a in zip(rows, angles, strict=True)
    ]


# ---------------------------------------------------------------- the data set's Cobb script


def _is_s(mid_p_v: np.ndarray) -> bool:
    """The script's S-shape test on the 34 endplate midpoints (float32 as in the script)."""
    num = mid_p_v.shape[0]
    ll = []
    with np.errstate(divide="ignore", invalid="ignore"):  # as the script: a vertical T1–L5 line gives nan
        for i in range(num - 2):
            term1 = (mid_p_v[i, 1] - mid_p_v[num - 1, 1]) / (mid_p_v[0, 1] - mid_p_v[num - 1, 1])
            term2 = (mid_p_v[i, 0] - mid_p_v[num - 1, 0]) / (mid_p_v[0, 0] - mid_p_v[num - 1, 0])
            ll.append(term1 - term2)
        lv = np.asarray(ll, np.float32)[:, None]
        pair = lv @ lv.T
        return bool(abs(float(np.sum(pair)) - float(np.sum(np.abs(pair)))) >= 1e-4)


def aasce_angles(vectors: np.ndarray, endplate_midpoints: np.ndarray, height_px: float) -> np.ndarray:
    """The three Cobb angles (degrees) of the AASCE 2019 challenge's script (its Python port of the
    MATLAB original), from each vertebra's axis vector (17, 2) (left-edge midpoint → right-edge
    midpoint) and the 34 endplate midpoints (superior, inferior per vertebra, image px):

    angles A_ij = arccos(clip(cos ∠(v_i, v_j), 0, 1)); the major angle is the largest, at row p
    (the row of the largest row maximum) and column q; if the midpoints are not S-shaped the
    others are A[0, p] and A[16, q]; if S-shaped and the two ends' midpoints lie in the upper half
    of the image (row_p + row_q < h), the others are max A[p, :p+1] and max A[q, q:]; else
    max A[p, :p+1] and max A[p', :p'+1] with p' its argmax."""
    v = np.asarray(vectors, dtype=np.float32)
    mid = np.asarray(endplate_midpoints, dtype=np.float32)
    norms = np.sqrt(np.sum(v**2, axis=1))[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):  # an axis of length 0 reads NaN, as in the script
        cosine = np.clip((v @ v.T) / (norms @ norms.T), 0.0, 1.0)
    angles = np.arccos(cosine)
    pos1 = np.argmax(angles, axis=1)
    maxt = np.amax(angles, axis=1)
    pos2 = int(np.argmax(maxt))
    first = float(np.amax(maxt))
    vnum = len(v) - 1
    if not _is_s(mid):
        second, third = angles[0, pos2], angles[vnum, pos1[pos2]]
    elif mid[pos2 * 2, 1] + mid[pos1[pos2] * 2, 1] < height_px:
        second = np.max(angles[pos2, : pos2 + 1])
        third = np.max(angles[pos1[pos2], pos1[pos2] : vnum + 1])
    else:
        row = angles[pos2, : pos2 + 1]
        second = np.max(row)
        above = int(np.argmax(row))
        third = np.max(angles[above, : above + 1])
    return np.degrees(np.array([first, second, third], dtype=float))


def corner_axes(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis vectors (17, 2) and endplate midpoints (34, 2) of annotated corners (17, 4, 2)."""
    vectors = 0.5 * (corners[:, 1] + corners[:, 3]) - 0.5 * (corners[:, 0] + corners[:, 2])
    mids = np.empty((2 * N_LEVELS, 2))
    mids[0::2] = 0.5 * (corners[:, 0] + corners[:, 1])
    mids[1::2] = 0.5 * (corners[:, 2] + corners[:, 3])
    return vectors, mids


def smape(predicted: np.ndarray, truth: np.ndarray) -> float:
    """The challenge's symmetric mean absolute percentage error, %: mean over radiographs of
    Σ_j |a_j − b_j| / Σ_j (a_j + b_j) × 100 over the three angles."""
    p, t = np.asarray(predicted, dtype=float), np.asarray(truth, dtype=float)
    return float(np.mean(np.sum(np.abs(p - t), axis=1) / np.sum(p + t, axis=1)) * 100.0)


def plausible(rad: Radiograph) -> bool:
    """No chord of the superior endplate midpoints steeper than ``PLAUSIBLE_CHORD_DEG`` (or going up)."""
    e_c, e_r = image_axes(PA_ORIENTATION)
    mids = 0.5 * (rad.corners[:, 0] + rad.corners[:, 1])
    return bool(np.all(np.abs(chord_angles_deg(mids, e_c, e_r)) <= PLAUSIBLE_CHORD_DEG))


def tunes_the_prior(rad: Radiograph) -> bool:
    """A training radiograph the tilt prior and its Cobb SD are fitted on: ``plausible`` and a major
    angle below ``MAJOR_LIMIT_DEG``."""
    return plausible(rad) and rad.angles[0] < MAJOR_LIMIT_DEG


# ---------------------------------------------------------------- reconstructions


CASSETTE_HEIGHT_MM = 914.4
"""Height of the long (14 × 36 in, 35 × 91 cm) cassette or detector of a full-spine radiograph."""


def spacing_mm(rad: Radiograph) -> float:
    """A nominal pixel spacing, mm per px: the image's height spread over a 36-inch full-spine film.
    The data set gives no scale; with 1 mm per px the landmarks' 1 mm noise model (landmark_sd_mm)
    would be a fraction of a pixel, and the fit would weigh them against the rod's prior as if the
    spine were several metres long."""
    return CASSETTE_HEIGHT_MM / rad.height_px


def payload(rad: Radiograph, form: str, tilt_prior: bool | None = None) -> dict[str, Any]:
    """A no-boundary payload in px (``spacing_mm``) with corners or superior endplate midpoints."""
    spacing = spacing_mm(rad)
    landmarks = []
    for level, quad in zip(LEVELS, rad.corners, strict=True):
        if form == "corners":
            landmarks.append({"level": level, "corners": quad.tolist()})
        else:
            landmarks.append({"level": level, "point": (0.5 * (quad[0] + quad[1])).tolist()})
    body: dict[str, Any] = {
        "pa": {"units": "px", "pixel_spacing": [spacing, spacing], "patient_orientation": list(PA_ORIENTATION),
               "landmarks": landmarks}
    }
    if tilt_prior is not None:
        body["options"] = {"tilt_prior": tilt_prior}
    return body


def model_axes(result: dict[str, Any], spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Axis vectors (17, 2) and endplate midpoints (34, 2) of a reconstruction, in image px: each
    vertebra's d1 projected, its node (superior endplate midpoint) projected, and the node + H·d3
    projected as the inferior midpoint (H the table's body height × the reconstruction's length
    over the table's)."""
    e_c, e_r = image_axes(PA_ORIENTATION)
    E = np.stack([e_c, e_r])
    s = result["fit"]["pa"]["scale"]
    T = np.asarray(result["fit"]["pa"]["translation"])
    r = np.array([v["position"] for v in result["vertebrae"]])
    R = np.array([np.asarray(v["directors"]).T for v in result["vertebrae"]])
    size = float(np.linalg.norm(np.diff(r, axis=0), axis=1).sum() / rest_segment_lengths().sum())
    heights = size * np.array([VERTEBRA_TABLE[lv][0] for lv in LEVELS])
    vectors = R[:, :, 0] @ E.T
    mids = np.empty((2 * N_LEVELS, 2))
    mids[0::2] = s * r @ E.T + T
    mids[1::2] = s * (r + heights[:, None] * R[:, :, 2]) @ E.T + T
    return vectors, mids / spacing


def line_axes(rad: Radiograph) -> tuple[np.ndarray, np.ndarray]:
    """The straight-chord baseline: each vertebra's axis perpendicular to the mean of the chords of
    the superior endplate midpoints above and below it (one-sided at T1 and L5)."""
    e_c, e_r = image_axes(PA_ORIENTATION)
    mids = 0.5 * (rad.corners[:, 0] + rad.corners[:, 1])
    phi = chord_angles_deg(mids, e_c, e_r)
    tilt = np.concatenate([[phi[0]], 0.5 * (phi[:-1] + phi[1:]), [phi[-1]]])
    t = np.radians(tilt)
    _, endplates = corner_axes(rad.corners)
    return np.stack([np.cos(t), -np.sin(t)], axis=1), endplates


def major_angle(result: dict[str, Any]) -> float:
    """The major Cobb angle a user reads in a result: ``measures.cobb``'s major curve's ``angle_deg``,
    0 when no curve reaches the 10° reporting threshold (the user then reads no curve)."""
    return next((float(c["angle_deg"]) for c in result["measures"]["cobb"] if c["major"]), 0.0)


def major_curve(result: dict[str, Any]) -> dict[str, Any] | None:
    """``measures.cobb``'s major curve as the result's JSON gives it (None below the threshold)."""
    return next((c for c in result["measures"]["cobb"] if c["major"]), None)


def in_order(rad: Radiograph) -> bool:
    """Every superior endplate midpoint lies below (larger row than) the one of the level above."""
    mids = 0.5 * (rad.corners[:, 0] + rad.corners[:, 1])
    return bool(np.all(np.diff(mids[:, 1]) > 0.0))


@dataclass
class Outcome:
    major: dict[str, float]
    three: dict[str, np.ndarray]
    failed: list[str]
    major_sd: dict[str, float] = dataclasses.field(default_factory=dict)
    """The reported SD of the major angle, per method that reports one (a major curve found)."""
    residual_to_sd: dict[str, float] = dataclasses.field(default_factory=dict)
    """Per fitted method, the landmark residual over its SD (``clinic.residual_to_sd``)."""
    smallest_projection: dict[str, float] = dataclasses.field(default_factory=dict)
    """Per fitted method, the shortest projection of a vertebra's d1 on the PA (|(d1_x, d1_z)|, at most 1;
    ``reconstruction.END_ON_PROJECTION`` refuses corners met below 0.5)."""
    refusals: dict[str, list[str]] = dataclasses.field(default_factory=dict)
    """Per method that ``register`` refused, the reasons: the error types of ``InvalidInput.errors``
    (sorted, each once), or ``fit_failed``."""


def evaluate(rad: Radiograph) -> Outcome:
    """Every method on one radiograph."""
    major: dict[str, float] = {}
    three: dict[str, np.ndarray] = {}
    failed: list[str] = []
    vectors, mids = corner_axes(rad.corners)
    three["script"] = aasce_angles(vectors, mids, rad.height_px)

    ratio: dict[str, float] = {}
    projection: dict[str, float] = {}
    refusals: dict[str, list[str]] = {}

    def run(name: str, body: dict[str, Any]) -> dict[str, Any] | None:
        try:
            result = register(body)
        except (FitFailed, InvalidInput) as exc:  # refused annotations count as not reconstructed
            failed.append(name)
            refusals[name] = sorted({e.type for e in exc.errors}) if isinstance(exc, InvalidInput) else ["fit_failed"]
            return None
        ratio[name] = residual_to_sd(body, result)
        d1 = np.array([np.asarray(v["directors"])[0] for v in result["vertebrae"]])
        projection[name] = float(np.min(np.hypot(d1[:, 0], d1[:, 2])))
        return result

    a = run("corners", payload(rad, "corners"))
    if a is not None:
        major["corners"] = major_angle(a)
        major["corners_aasce"] = a["measures"]["aasce2019"]["angle_deg"]
        three["corners"] = three["script"]  # the corner lines are the script's own vectors
        mv, mm = model_axes(a, spacing_mm(rad))
        tilt = frontal_tilt_deg(np.array([np.asarray(v["directors"]).T for v in a["vertebrae"]]))
        major["corners_model"] = float(tilt.max() - tilt.min())
        three["corners_model"] = aasce_angles(mv, mm, rad.height_px)
    major_sd: dict[str, float] = {}
    for method, flag in (("midpoints", None), ("midpoints_no_prior", False)):
        b = run(method, payload(rad, "midpoints", tilt_prior=flag))
        if b is not None:
            major[method] = major_angle(b)
            three[method] = aasce_angles(*model_axes(b, spacing_mm(rad)), rad.height_px)
            curve = major_curve(b)
            if curve is not None and curve["angle_sd_deg"] is not None:
                major_sd[method] = float(curve["angle_sd_deg"])
            largest = b["measures"].get("largest_cobb") if method == "midpoints" else None
            if largest is not None:
                major["midpoints_largest"] = float(largest["angle_deg"])
                three["midpoints_largest"] = three[method]
                if largest["angle_sd_deg"] is not None:
                    major_sd["midpoints_largest"] = float(largest["angle_sd_deg"])
        elif method == "midpoints":
            failed.append("midpoints_largest")
    lv, lm = line_axes(rad)
    three["line"] = aasce_angles(lv, lm, rad.height_px)
    major["line"] = float(three["line"][0])
    return Outcome(major, three, failed, major_sd, ratio, projection, refusals)


def interval_coverage(errors: np.ndarray, sds: np.ndarray) -> float:
    """Fraction of |error| ≤ 1.96 SD: the coverage of the 95 % intervals."""
    return float(np.mean(np.abs(errors) <= 1.96 * sds))


METHODS = {
    "corners": "(a) 4 corners: Cobb of measures.cobb (corner lines)",
    "corners_model": "(a-model) 4 corners: reconstructed d1",
    "midpoints": "(b) midpoints + tilt prior, reconstructed d1",
    "midpoints_no_prior": "(b-no-prior) midpoints, reconstructed d1",
    "midpoints_largest": "(b-largest) midpoints + tilt prior, measures.largest_cobb (also below 10°)",
    "line": "(b-line) midpoints, chord-perpendicular tilts",
}


def summarise(
    rads: list[Radiograph], outcomes: list[Outcome], subset: np.ndarray | None = None
) -> list[dict[str, Any]]:
    truth = np.array([r.angles for r in rads])
    keep = np.ones(len(rads), dtype=bool) if subset is None else subset
    rows = []
    for method, label in METHODS.items():
        ok = [i for i, o in enumerate(outcomes) if keep[i] and method in o.major and method in o.three]
        if not ok:
            continue
        major = np.array([outcomes[i].major[method] for i in ok])
        three = np.array([outcomes[i].three[method] for i in ok])
        err = major - truth[ok, 0]
        with_sd = [k for k, i in enumerate(ok) if method in outcomes[i].major_sd]
        sds = np.array([outcomes[ok[k]].major_sd[method] for k in with_sd])
        rows.append(
            {
                "method": method,
                "label": label,
                "radiographs": len(ok),
                "major_mae_deg": float(np.mean(np.abs(err))),
                "major_mae_se_deg": float(np.std(np.abs(err), ddof=1) / np.sqrt(len(err))) if len(err) > 1 else None,
                "major_bias_deg": float(np.mean(err)),
                "major_median_ae_deg": float(np.median(np.abs(err))),
                "smape_pct": smape(three, truth[ok]),
                "not_reconstructed": int(sum(method in outcomes[i].failed for i in range(len(outcomes)) if keep[i])),
                "major_coverage_95": interval_coverage(err[with_sd], sds) if with_sd else None,
                "major_coverage_n": len(with_sd),
                "max_residual_to_sd": max((outcomes[i].residual_to_sd[method] for i in ok
                                           if method in outcomes[i].residual_to_sd), default=None),
                "smallest_projection": min((outcomes[i].smallest_projection[method] for i in ok
                                            if method in outcomes[i].smallest_projection), default=None),
                "refused_by_reason": refused_by_reason(
                    [o for i, o in enumerate(outcomes) if keep[i]], method),
            }
        )
    return rows


def refused_by_reason(outcomes: list[Outcome], method: str) -> dict[str, int]:
    """How many of ``outcomes`` ``register`` refused for ``method``, per reason (an error type of
    ``Outcome.refusals``; a radiograph refused for two reasons counts under each)."""
    counts: dict[str, int] = {}
    for o in outcomes:
        for reason in o.refusals.get(method, []):
            counts[reason] = counts.get(reason, 0) + 1
    return dict(sorted(counts.items()))


def plot(rads: list[Radiograph], outcomes: list[Outcome], path: Path, title: str) -> None:
    """Engine against the annotation script's major angle, for (a) corners and (b) midpoints;
    predictions beyond the axes are drawn on its top edge as triangles and counted."""
    truth = np.array([r.angles[0] for r in rads])
    top = 95.0
    fig, axes = subplots(1, 2, figsize=(8, 3.6))
    for ax, method, label in (
        (axes[0], "corners", "(a) corners"),
        (axes[1], "midpoints", "(b) midpoints + prior"),
    ):
        series = [(method, label, ".")]
        if method == "midpoints":
            series.append(("midpoints_no_prior", "(b) without prior", "x"))
        for name, text, marker in series:
            ok = [i for i, o in enumerate(outcomes) if name in o.major]
            pred = np.array([outcomes[i].major[name] for i in ok])
            inside = pred <= top
            ax.plot(
                truth[ok][inside],
                pred[inside],
                marker,
                ms=4 if marker == "." else 3,
                alpha=1.0 if marker == "." else 0.5,
                label=text,
            )
            if (~inside).any():
                ax.plot(
                    truth[ok][~inside],
                    np.full(int((~inside).sum()), top),
                    "^",
                    color="C3",
                    ms=5,
                    label=f"{int((~inside).sum())} above {top:.0f}° (misplaced landmarks)",
                )
        ok = [i for i, o in enumerate(outcomes) if method in o.major]
        err = np.mean(np.abs(np.array([outcomes[i].major[method] for i in ok]) - truth[ok]))
        ax.plot([0, top], [0, top], "k-", lw=0.8)
        ax.set(
            xlabel="major Cobb, annotation script (deg)",
            ylabel="engine (deg)",
            title=f"{label}: MAE {err:.2f}° (all {len(ok)})",
            xlim=(0, top),
            ylim=(0, top + 3),
        )
        ax.title.set_fontsize(9)
        ax.legend(fontsize=7, loc="upper left")
    fig.suptitle(title, fontsize=9)
    save_figure(fig, path, dpi=80)


# ---------------------------------------------------------------- calibration (training only)


def choose_blend(
    tilts: np.ndarray, chords: np.ndarray, major: np.ndarray, window: tuple[int, ...], placement: str, seed: int = 0
) -> tuple[float, dict[float, float]]:
    """The blend β toward the chord-normal tilt (``tilt_prior.toward_chord_normal``) with the lowest
    major-angle MAE of the prior alone (max − min of its predicted tilts) in 5-fold CV on the given
    spines; also every candidate's MAE."""
    folds = np.random.default_rng(seed).integers(0, 5, len(tilts))
    predicted = {b: np.empty_like(tilts) for b in BLENDS}
    for f in range(5):
        fitted = fit_coefficients(tilts[folds != f], chords[folds != f], window, RIDGE, placement)
        for b in BLENDS:
            prior = TiltPrior("cv", window, toward_chord_normal(fitted, window, placement, b), 1.0, {}, placement)
            predicted[b][folds == f] = predict_tilts_deg(prior, chords[folds == f])
    scores = {b: float(np.mean(np.abs(p.max(axis=1) - p.min(axis=1) - major))) for b, p in predicted.items()}
    return min(scores, key=lambda b: scores[b]), scores


def calibrate(data: Path, out_dir: Path, fractions: tuple[float, ...], limit: int | None) -> TiltPrior:
    """Fit the tilt prior on ``training`` (``fit_tilt_prior``) and write it as the shipped prior."""
    prior = fit_tilt_prior(data, fractions, limit)
    path = PRIORS_DIR / f"{DEFAULT_PRIOR}.json"
    save_tilt_prior(prior, path)
    load_tilt_prior.cache_clear()
    write_json(out_dir / "calibration.json", {"weight_fraction": prior.weight_fraction, "provenance": prior.provenance})
    print(f"chosen weight fraction {prior.weight_fraction}; wrote {path}")
    return prior


def tilt_training_arrays(rads: list[Radiograph]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the tilt prior learns from: each radiograph's corner-line frontal tilts (n, 17), the
    frontal angles of the chords of its superior endplate midpoints (n, 16) and its major Cobb
    angle (n,), degrees."""
    e_c, e_r = image_axes(PA_ORIENTATION)
    tilts = np.array([frontal_tilt_deg_of_corners(r.corners) for r in rads])
    chords = np.array([chord_angles_deg(0.5 * (r.corners[:, 0] + r.corners[:, 1]), e_c, e_r) for r in rads])
    return tilts, chords, np.array([r.angles[0] for r in rads])


def prior_major_angles(tilts: np.ndarray, chords: np.ndarray, major: np.ndarray, new_chords: np.ndarray) -> np.ndarray:
    """The tilt prior fitted on (tilts, chords, major) as ``fit_tilt_prior`` fits it (blend chosen by
    ``choose_blend`` on them), applied to ``new_chords`` (m, 16) alone: the largest difference of its
    predicted tilts (m,), degrees, as the prior's own cross-validation reads the major angle."""
    blend, _ = choose_blend(tilts, chords, major, CAL_WINDOW, CAL_PLACEMENT)
    coefficients = toward_chord_normal(
        fit_coefficients(tilts, chords, CAL_WINDOW, RIDGE, CAL_PLACEMENT), CAL_WINDOW, CAL_PLACEMENT, blend
    )
    predicted = predict_tilts_deg(TiltPrior("cv", CAL_WINDOW, coefficients, 1.0, {}, CAL_PLACEMENT), new_chords)
    return np.asarray(predicted.max(axis=1) - predicted.min(axis=1))


def fit_tilt_prior(data: Path, fractions: tuple[float, ...], limit: int | None) -> TiltPrior:
    """The tilt prior of ``training`` (plausible radiographs, major < 90°): least-squares
    coefficients on the chords of ``CAL_WINDOW`` ("shifted"), blended toward the chord-normal tilt by
    the β that 5-fold CV of the prior's own major angle chooses; checked by 5-fold CV; its weight
    fraction chosen through the reconstruction (among the fractions with the fewest failed fits,
    the smallest within ``FRACTION_TIE_DEG`` of the lowest training MAE). Writes nothing."""
    rads = read_split(data / "training")
    keep = [r for r in rads if tunes_the_prior(r)]
    tilts, chords, major = tilt_training_arrays(keep)
    blend, blend_scores = choose_blend(tilts, chords, major, CAL_WINDOW, CAL_PLACEMENT)
    print("blend toward the chord normal, prior-only 5-fold CV major MAE: "
          + ", ".join(f"{b:g}: {v:.3f}°" for b, v in blend_scores.items()) + f"; chosen {blend:g}")
    folds = np.random.default_rng(1).integers(0, 5, len(keep))
    cv_err = np.empty(len(keep))
    for f in range(5):  # the whole procedure, β included, checked on folds it did not see
        train = folds != f
        angles = prior_major_angles(tilts[train], chords[train], major[train], chords[folds == f])
        cv_err[folds == f] = angles - major[folds == f]
    coefficients = toward_chord_normal(
        fit_coefficients(tilts, chords, CAL_WINDOW, RIDGE, CAL_PLACEMENT), CAL_WINDOW, CAL_PLACEMENT, blend
    )
    subset = keep if limit is None else keep[:limit]
    truth = np.array([r.angles[0] for r in subset])
    scores: dict[float, float] = {}
    failures: dict[float, int] = {}
    for fraction in fractions:
        prior = TiltPrior(DEFAULT_PRIOR, CAL_WINDOW, coefficients, fraction, {}, CAL_PLACEMENT)
        outcomes = np.array([evaluate_midpoints(r, prior) for r in subset])
        scores[fraction] = float(np.nanmean(np.abs(outcomes - truth)))
        failures[fraction] = int(np.isnan(outcomes).sum())
        print(
            f"weight fraction {fraction:6.3g}: training major MAE {scores[fraction]:.3f}° ({len(subset)} radiographs, "
            f"{failures[fraction]} failed)"
        )
    fewest = min(failures.values())
    candidates = [f for f in fractions if failures[f] == fewest]
    lowest = min(scores[f] for f in candidates)
    # the smallest fraction within FRACTION_TIE_DEG of the lowest MAE: past a point the curve is flat
    # and larger weights only make the fit stiffer (non-converged fits appeared at 10-100 in --cv)
    best = min(f for f in candidates if scores[f] <= lowest + FRACTION_TIE_DEG)
    provenance = {
        "method": "constrained least squares (sum of coefficients 1, ridge 1e-3) of each vertebra's corner-line "
        f"tilt on the frontal angles of the chords of the superior endplate midpoints, window {CAL_WINDOW} "
        f"({CAL_PLACEMENT} inside the 16 chords at the ends), blended toward the chord-normal tilt with the "
        "weight chosen by 5-fold CV of the prior's own major Cobb MAE; weight fraction chosen by the major Cobb "
        f"MAE through the reconstruction (the smallest within {FRACTION_TIE_DEG}° of the lowest) "
        "(benches.aasce --calibrate)",
        "command": "spine bench aasce --calibrate" + (f" --limit {limit}" if limit else ""),
        "training_set": f"AASCE 2019 training split: {len(keep)} of {len(rads)} radiographs (left out: a chord "
        f"steeper than {PLAUSIBLE_CHORD_DEG}° or a major angle >= 90°); never the test split",
        "blend_toward_chord_normal": blend,
        "blend_cv_5fold_prior_only_major_mae_deg": {str(k): round(v, 3) for k, v in blend_scores.items()},
        "cv_5fold_prior_only_major_mae_deg": round(float(np.mean(np.abs(cv_err))), 3),
        "cv_5fold_prior_only_major_bias_deg": round(float(np.mean(cv_err)), 3),
        "weight_fraction_training_major_mae_deg": {str(k): round(v, 3) for k, v in scores.items()},
        "weight_fraction_failed_fits": {str(k): v for k, v in failures.items()},
        "data": "AASCE 2019 / SpineWeb dataset 16 (Wu et al., MICCAI 2017; Med Image Anal 2018); evaluation use only",
        "date": DATE,
    }
    print(
        f"5-fold CV of the prior alone on training (blend chosen inside each fold): major MAE "
        f"{np.mean(np.abs(cv_err)):.2f}°, bias {np.mean(cv_err):+.2f}°"
    )
    return TiltPrior(DEFAULT_PRIOR, CAL_WINDOW, coefficients, best, provenance, CAL_PLACEMENT)


def frontal_tilt_deg_of_corners(corners: np.ndarray) -> np.ndarray:
    """Frontal tilt (17,) of annotated corner lines on a PA ["L", "F"] image, degrees."""
    e_c, e_r = image_axes(PA_ORIENTATION)
    vectors, _ = corner_axes(corners)
    return frontal_tilt_deg_of_image_vectors(vectors, e_c, e_r)


def evaluate_midpoints(rad: Radiograph, prior: TiltPrior | None = None) -> float:
    """Major angle of the midpoints method with ``prior`` (None: the shipped one; NaN when the fit
    fails)."""
    try:
        return major_angle(register_model(validate_payload(payload(rad, "midpoints")), prior).model_dump(mode="json"))
    except (FitFailed, InvalidInput):
        return float("nan")


def cobb_sd_on_training(data: Path, limit: int | None) -> tuple[dict[str, float], dict[str, dict[str, float]], int]:
    """(σ per key, checks per key, radiographs): for the midpoints with ("tilt_prior") and without
    ("no_tilt_prior") the shipped tilt prior, the smallest σ (bisection, 0.01°) at which the major
    angle's interval, SD = √(SD_Laplace² + (m/2) σ²) with m its model-tilt ends
    (``reconstruction.MODEL_TILT_ENDS``), covers 95 % of the plausible training radiographs (major <
    90°) whose fit finds a major curve. SD_Laplace is the reported SD with the current term taken
    out, so the result does not depend on it. Writes nothing."""
    rads = [r for r in read_split(data / "training") if tunes_the_prior(r)][:limit]
    prior = load_tilt_prior()
    sigmas: dict[str, float] = {}
    checks: dict[str, dict[str, float]] = {}
    for key, flag in (("tilt_prior", True), ("no_tilt_prior", False)):
        current = prior.model_tilt_cobb_sd_deg(flag)
        errors, laplace, shares = [], [], []
        for rad in rads:
            try:
                curve = major_curve(register(payload(rad, "midpoints", tilt_prior=flag)))
            except (FitFailed, InvalidInput):
                continue
            if curve is None or curve["angle_sd_deg"] is None:
                continue
            share = MODEL_TILT_ENDS[curve["tilt_source"] or "model"] / 2.0
            errors.append(float(curve["angle_deg"]) - float(rad.angles[0]))
            laplace.append(math.sqrt(max(float(curve["angle_sd_deg"]) ** 2 - share * current**2, 0.0)))
            shares.append(share)
        e, lap, m = np.array(errors), np.array(laplace), np.array(shares)

        def covered(sigma: float, e: np.ndarray = e, lap: np.ndarray = lap, m: np.ndarray = m) -> float:
            return interval_coverage(e, np.sqrt(lap**2 + m * sigma**2))

        lo, hi = 0.0, 30.0
        if covered(lo) >= 0.95:
            hi = lo
        while hi - lo > 0.01:
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if covered(mid) >= 0.95 else (mid, hi)
        sigmas[key] = round(hi, 2)
        checks[key] = {"radiographs": len(e), "coverage_laplace_only": round(covered(0.0), 3),
                       "coverage_calibrated": round(covered(sigmas[key]), 3),
                       "major_mae_deg": round(float(np.mean(np.abs(e))), 3)}  # fmt: skip
        print(f"{key}: σ = {sigmas[key]:.2f}° over {len(e)} radiographs; 95 % coverage "
              f"{checks[key]['coverage_laplace_only']:.3f} with the Laplace SD alone, "
              f"{checks[key]['coverage_calibrated']:.3f} with σ")  # fmt: skip
    return sigmas, checks, len(rads)


def calibrate_cobb_sd(data: Path, limit: int | None) -> TiltPrior:
    """Set the shipped prior's ``cobb_sd_deg`` on ``training`` (``cobb_sd_on_training``) and write it."""
    prior = load_tilt_prior()
    sigmas, checks, radiographs = cobb_sd_on_training(data, limit)
    provenance = {
        **prior.provenance,
        "cobb_sd": {
            "method": "smallest σ at which the major Cobb angle's 95 % interval, SD = √(SD_Laplace² + (m/2) σ²) "
            "with m its end vertebrae of model tilt, covers 95 % of the training radiographs whose fit finds a "
            "major curve, midpoints through register() with the tilt prior on and off "
            "(benches.aasce.calibrate_cobb_sd)",
            "command": "spine bench aasce --calibrate-cobb-sd" + (f" --limit {limit}" if limit else ""),
            "training_set": f"AASCE 2019 training split, the {radiographs} plausible radiographs of major < 90°; "
            "never the test split",
            "checks": checks,
            "date": DATE,
        },
    }
    calibrated = dataclasses.replace(prior, cobb_sd_deg=sigmas, provenance=provenance)
    save_tilt_prior(calibrated, PRIORS_DIR / f"{DEFAULT_PRIOR}.json")
    load_tilt_prior.cache_clear()
    return calibrated


# ---------------------------------------------------------------- cross-validation of variants (training only)


@dataclass(frozen=True)
class PriorVariant:
    """A candidate tilt prior: its chord window (offsets from chord i, clipped to 0..15 as the shipped
    prior's; ``range(-16, 16)`` gives every vertebra all 16 chords), the extra least-squares weight
    of the two end vertebrae of each training spine's major curve (its most and least tilted
    vertebrae: the Cobb angle depends only on them), the ridge, and the weight fractions to try."""

    name: str
    window: tuple[int, ...]
    end_weight: float
    fractions: tuple[float, ...]
    ridge: float = 1e-3
    placement: str = "clipped"
    blend: float | None = 0.0
    """Blend toward the chord-normal tilt; None: chosen inside each training fold (``choose_blend``)."""


CV_VARIANTS = (
    PriorVariant("2026-12-01 prior: -2..+1", WINDOW, 0.0, (1.0, 3.0, 10.0, 30.0, 100.0)),
    PriorVariant("window -3..+2", tuple(range(-3, 3)), 0.0, (3.0, 10.0)),
    PriorVariant("window -3..+2, ends x4", tuple(range(-3, 3)), 3.0, (3.0, 10.0)),
    PriorVariant("window -4..+3, ends x4", tuple(range(-4, 4)), 3.0, (3.0, 10.0)),
    PriorVariant("all 16 chords", tuple(range(-16, 16)), 0.0, (3.0, 10.0)),
    PriorVariant("all 16 chords, ends x4", tuple(range(-16, 16)), 3.0, (3.0, 10.0)),
    PriorVariant("-3..+2 shifted", CAL_WINDOW, 0.0, (3.0, 10.0), placement="shifted"),
    PriorVariant("-3..+2 shifted, blend by CV", CAL_WINDOW, 0.0, (3.0, 10.0), placement="shifted", blend=None),
)
"""Variants compared by ``--cv``. "ends x4": the end vertebrae weigh 1 + 3 in the fit (3 chosen among
0, 1, 3, 10, 30 by the prior's own major-angle MAE in 5-fold CV on ``training``)."""


def end_weights(tilts_deg: np.ndarray, end_weight: float) -> np.ndarray:
    """1 for every vertebra, 1 + ``end_weight`` for each spine's most and least tilted vertebra."""
    w = np.ones_like(tilts_deg)
    rows = np.arange(len(tilts_deg))
    w[rows, np.argmax(tilts_deg, axis=1)] += end_weight
    w[rows, np.argmin(tilts_deg, axis=1)] += end_weight
    return w


def cross_validate(
    data: Path, variants: tuple[PriorVariant, ...], seeds: tuple[int, ...], folds: int, out_dir: Path
) -> list[dict[str, Any]]:
    """k-fold CV on ``training`` only: per seed, radiographs drawn into ``folds`` folds; each fold's
    prior is fitted on the other folds' plausible radiographs (as ``calibrate``) and every in-order
    radiograph of the fold is reconstructed from its midpoints with it. Major-angle MAE and bias over
    the in-order radiographs (refused ones excluded, failed fits counted) and over the plausible ones."""
    rads = read_split(data / "training")
    tilts, chords, truth = tilt_training_arrays(rads)
    fit_on = np.array([tunes_the_prior(r) for r in rads])
    scored = np.flatnonzero([in_order(r) for r in rads])
    rows: list[dict[str, Any]] = []
    for variant in variants:
        for seed in seeds:
            fold = np.random.default_rng(seed).integers(0, folds, len(rads))
            coefficients = []
            for f in range(folds):
                train = (fold != f) & fit_on
                fitted = fit_coefficients(tilts[train], chords[train], variant.window, variant.ridge, variant.placement,
                                          weights=end_weights(tilts[train], variant.end_weight))  # fmt: skip
                blend = variant.blend
                if blend is None:
                    blend, _ = choose_blend(
                        tilts[train], chords[train], truth[train], variant.window, variant.placement
                    )
                coefficients.append(toward_chord_normal(fitted, variant.window, variant.placement, blend))
            for fraction in variant.fractions:
                major = np.full(len(rads), np.nan)
                for i in scored:
                    prior = TiltPrior("cv", variant.window, coefficients[fold[i]], fraction, {}, variant.placement)
                    major[i] = evaluate_midpoints(rads[i], prior)
                err = major - truth
                row: dict[str, Any] = {
                    "variant": variant.name,
                    "weight_fraction": fraction,
                    "seed": seed,
                    "folds": folds,
                    "radiographs": int(np.isfinite(err[scored]).sum()),
                    "failed": int(np.isnan(err[scored]).sum()),
                    "major_mae_deg": float(np.nanmean(np.abs(err[scored]))),
                    "major_bias_deg": float(np.nanmean(err[scored])),
                    "plausible_major_mae_deg": float(np.nanmean(np.abs(err[fit_on]))),
                }
                rows.append(row)
                print(
                    f"{variant.name:26s} fraction {fraction:5g} seed {seed} ({folds}-fold): major MAE "
                    f"{row['major_mae_deg']:.3f}° bias {row['major_bias_deg']:+.3f}° failed {row['failed']} "
                    f"(plausible: {row['plausible_major_mae_deg']:.3f}°)",
                    flush=True,
                )
    summary: dict[tuple[str, float], list[dict[str, Any]]] = {}
    for row in rows:
        summary.setdefault((row["variant"], row["weight_fraction"]), []).append(row)
    columns = ["variant", "fraction", "MAE mean over seeds", "bias", "plausible MAE", "failed"]
    table = [
        [
            name,
            f"{fraction:g}",
            float(np.mean([r["major_mae_deg"] for r in group])),
            float(np.mean([r["major_bias_deg"] for r in group])),
            float(np.mean([r["plausible_major_mae_deg"] for r in group])),
            sum(r["failed"] for r in group),
        ]
        for (name, fraction), group in summary.items()
    ]
    print(f"\nAASCE 2019 training, {folds}-fold CV, seeds {list(seeds)}, major angle through register():")
    print(format_table(columns, table))
    write_json(out_dir / "aasce-cv.json", {"data": str(data / "training"), "date": DATE, "rows": rows})
    return rows


# ---------------------------------------------------------------- command


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="spine bench aasce", description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="AASCE 2019 folder with training/ and test/")
    parser.add_argument("--split", choices=["training", "test"], default="test")
    parser.add_argument("--calibrate", action="store_true", help="fit the tilt prior on training and write it")
    parser.add_argument(
        "--calibrate-cobb-sd", action="store_true",
        help="set the SD Cobb angles of model tilts gain (95 %% coverage on training) and write it",
    )
    parser.add_argument(
        "--cv", action="store_true", help="compare variants of the prior by k-fold CV on training (writes nothing)"
    )
    parser.add_argument("--folds", type=int, default=5, help="folds of --cv")
    parser.add_argument("--variants", default="", help="only the --cv variants whose name contains this")
    parser.add_argument("--seeds", default="0,1,2", help="fold draws of --cv, comma-separated")
    parser.add_argument("--limit", type=int, default=None, help="only the first N radiographs (quick runs)")
    parser.add_argument("--out", type=Path, default=Path("bench-out/aasce"))
    parser.add_argument("--plot", type=Path, default=None, help="also write the plot here (e.g. docs/img/...)")
    args = parser.parse_args(argv)
    data = args.data or default_data_dir()
    if not (data / ("training" if args.cv else args.split) / "landmarks_px_from_mat.csv").is_file():
        print(f"error: AASCE 2019 data not found at {data} (pass --data or set SPINE_SHARED_DATA)")
        return 2
    start = time.perf_counter()
    if args.cv:
        seeds = tuple(int(v) for v in args.seeds.split(","))
        variants = tuple(v for v in CV_VARIANTS if args.variants in v.name)
        cross_validate(data, variants, seeds, args.folds, args.out)
        print(f"wrote {args.out}/aasce-cv.json in {time.perf_counter() - start:.0f} s")
        return 0
    if args.calibrate:
        calibrate(data, args.out, WEIGHT_FRACTIONS, args.limit)
    if args.calibrate or args.calibrate_cobb_sd:  # the SD belongs to the coefficients just written
        calibrate_cobb_sd(data, args.limit)
    rads = read_split(data / args.split)[: args.limit]
    outcomes = [evaluate(r) for r in rads]
    ordered = np.array([in_order(r) for r in rads])
    ok = np.array([plausible(r) for r in rads])
    columns = [
        "method",
        "radiographs",
        "major_mae_deg",
        "major_mae_se_deg",
        "major_bias_deg",
        "major_median_ae_deg",
        "smape_pct",
        "not_reconstructed",
        "major_coverage_95",
        "max_residual_to_sd",
        "smallest_projection",
    ]
    tables = {
        "all": summarise(rads, outcomes),
        "in_order": summarise(rads, outcomes, ordered),
        "plausible": summarise(rads, outcomes, ok),
    }
    print(f"AASCE 2019 {args.split}: all {len(rads)} radiographs")
    print(format_table(columns, [[r[c] for c in columns] for r in tables["all"]]))
    print(f"\n{int(ordered.sum())} radiographs whose superior endplate midpoints go down the image level by level:")
    print(format_table(columns, [[r[c] for c in columns] for r in tables["in_order"]]))
    print(f"\n{int(ok.sum())} radiographs with no midpoint chord steeper than {PLAUSIBLE_CHORD_DEG}°:")
    print(format_table(columns, [[r[c] for c in columns] for r in tables["plausible"]]))
    exact = [
        abs(o.major["corners"] - o.major["corners_aasce"])
        for o in outcomes
        if "corners" in o.major and o.major["corners"] < 90.0
    ]
    script = np.array([o.three["script"] for o in outcomes])
    truth = np.array([r.angles for r in rads])
    print(f"\nmajor of measures.cobb vs measures.aasce2019 (same corners, < 90°): max |difference| {max(exact):.2e}°")
    print(
        f"script port vs angles.csv: MAE {np.mean(np.abs(script - truth), axis=0).round(4).tolist()} "
        f"(major, above, below)"
    )
    write_json(
        args.out / f"aasce-{args.split}.json",
        {
            "data": str(data / args.split),
            "date": DATE,
            **tables,
            "out_of_order": [r.name for r, k in zip(rads, ordered, strict=True) if not k],
            "implausible": [r.name for r, k in zip(rads, ok, strict=True) if not k],
            "per_radiograph": [
                {"name": r.name, "truth": r.angles.tolist(), "major": o.major, "failed": o.failed,
                 "refusals": o.refusals}
                for r, o in zip(rads, outcomes, strict=True)
            ],
        },
    )
    title = f"AASCE 2019 {args.split} split, {len(rads)} radiographs"
    plot(rads, outcomes, args.out / f"aasce-{args.split}.png", title)
    if args.plot:
        plot(rads, outcomes, args.plot, title)
    print(f"wrote {args.out}/aasce-{args.split}.json and .png in {time.perf_counter() - start:.0f} s")
    return 0
