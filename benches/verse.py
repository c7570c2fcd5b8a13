"""Reconstruction of real spines from CT (VerSe): project, reconstruct, compare in 3D.

Each spine of a VerSe split (vertebral centroids T1..L5, LPS mm) is projected on a PA view
(and, for the PA+L case, a lateral view) by weak perspective; T1 and L5 are given from the truth
(position, and directors built from the centreline by ``frames_from_centreline``); the spine is
reconstructed as a user's job is, ``reconstruction.register_model`` on the validated payload (the
profile ``--profile`` names, by default the shipped one), and every figure is read from its result
(``models.RegistrationResult``): the 3D error of ``vertebrae[].position`` per spine and per level, the
kyphosis T4–T12 and lordosis L1–L5 of ``measures`` (as reported: with T1 and L5 given, as in every
case here, the centreline's reading, not the prior-only one), the registration error
``fit.mean_registration_error_mm`` and the axial rotation of ``vertebrae[].axial_rotation_deg``
(without pedicles, the population's that the result reports). A
spine whose fit ``register_model`` refuses (``FitFailed``: not converged or numerically broken;
``InvalidInput``: landmarks contradicting their SD or corners met only end-on) is counted
(``not_converged``, ``refused``) and left out of the means. Tune on ``dev``, report ``test``.

``--pa-kyphosis`` instead reconstructs each spine from one PA film with T1 and L5 given exactly
(``--noise-mm`` on its 17 landmarks) through the public ``register()`` and compares the reported
kyphosis T4–T12 and its SD with the truth's (``pa_kyphosis``).

``--clinical`` adds the clinical cases (``CLINICAL_CASES``) to the 17 PA points: the two
pedicle centres of every vertebra on the PA view, derived from the truth frames with the
engine's offsets (``observations.pedicle_offsets_mm``; the truth frames carry no axial rotation,
so these say "not rotated"), and/or four corners per vertebra (a box of the table's width and
height around each truth frame, ``truth.vertebra_corners_3d``); it also reports the axial
rotation error.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benches.report import format_table, save_figure, shared_data_dir, subplots, write_json
from benches.truth import payload_from_truth, read_verse
from spine_engine.anatomy import Profile, load_profile, population_prior
from spine_engine.errors import FitFailed, InvalidInput
from spine_engine.frames import axial_rotation_deg, frames_from_centreline
from spine_engine.levels import LEVELS, N_LEVELS
from spine_engine.measures import compute_measures, sagittal_inclination_deg
from spine_engine.models import RegistrationResult
from spine_engine.reconstruction import register, register_model
from spine_engine.validation import validate_payload

CASES: dict[str, tuple[list[int], list[int] | None]] = {
    "PA-17": (list(range(N_LEVELS)), None),
    "PA-17+L-17": (list(range(N_LEVELS)), list(range(N_LEVELS))),
}
ALL_LEVELS = list(range(N_LEVELS))
CLINICAL_CASES: dict[str, dict[str, list[int]]] = {
    "PA-17+pedicles": {"pedicle_levels": ALL_LEVELS},
    "PA-17+corners": {"corner_levels": ALL_LEVELS},
    "PA-17+corners+pedicles": {"corner_levels": ALL_LEVELS, "pedicle_levels": ALL_LEVELS},
}
"""PA-17 plus clinical landmarks (keyword arguments of ``truth.payload_from_truth``)."""
CLINICAL_REPORT = ["PA-17", "PA-17+pedicles", "PA-17+corners", "PA-17+corners+pedicles", "PA-17+L-17"]


def default_data_dir() -> Path:
    return shared_data_dir("verse")


FIELDS: dict[str, str] = {
    "mean_3d_error_mm": "mean over the reconstructed spines of the mean |r_j - r_j,truth| over T2..L4, mm, r_j the "
    "result's vertebrae[j].position",
    "max_3d_error_mm": "largest |r_j - r_j,truth| over the reconstructed spines' 17 levels, mm",
    "mean_registration_error_mm": "mean over the reconstructed spines of the result's fit.mean_registration_error_mm "
    "(mean PA landmark residual), mm",
    "kyphosis_mae_deg": "mean |measures.thoracic_kyphosis_t4_t12_deg - truth's|, degrees, the result's reported "
    "kyphosis (T1 and L5 given: the centreline's reading, not the prior-only one, docs/engine.md); the truth's "
    "on its centreline frames",
    "lordosis_mae_deg": "as kyphosis_mae_deg for measures.lumbar_lordosis_l1_l5_deg",
    "axial_rotation_mae_deg": "mean over spines of the mean |vertebrae[j].axial_rotation_deg - truth's| over T2..L4, "
    "degrees: the result's reported axial rotation (without pedicles the population's given the frontal curves, "
    "fit.assumed population_axial_rotation); the truth's centreline frames carry none",
    "not_converged": "spines for which register_model raised FitFailed (not converged, or numerically broken)",
    "refused": "spines for which register_model raised InvalidInput after the fit (landmarks contradicting their "
    "SD, corners met only end-on)",
    "reconstructed": "spines with a result; the means and per-level figures are over these",
}
"""What each figure of a case's summary is (written beside them in the JSON): every one is read from
the result ``register_model`` returns, as a user reads it."""


@dataclass(frozen=True)
class SpineOutcome:
    spine_id: str
    per_level_mm: np.ndarray
    """|r_j − r_j,truth| per level, mm, r_j the result's ``vertebrae[j].position``; NaN when ``failure``."""
    kyphosis_error_deg: float
    lordosis_error_deg: float
    registration_error_mm: float
    converged: bool
    axial_rotation_error_deg: float = 0.0
    """Mean |ψ − ψ_truth| over T2..L4, degrees: ψ the result's ``vertebrae[].axial_rotation_deg``,
    ψ_truth ``frames.axial_rotation_deg`` of the truth's frames."""
    failure: str | None = None
    """None, or why ``register_model`` gave no result: "not_converged" (``FitFailed``) or "refused"
    (``InvalidInput``); the figures are then NaN."""


def _failed(spine_id: str, failure: str) -> SpineOutcome:
    nan = float("nan")
    return SpineOutcome(spine_id, np.full(N_LEVELS, nan), nan, nan, nan, False, nan, failure)


def spine_payload(
    spine_id: str, positions: np.ndarray, case: str, noise_mm: float = 0.0, seed: int = 0
) -> dict[str, Any]:
    """The job payload of one real spine in one case (``truth.payload_from_truth``): the boundary poses
    the truth's (directors ``frames_from_centreline``), ``noise_mm`` the SD of Gaussian noise on every
    landmark coordinate (detector mm), drawn from a generator seeded by ``seed`` and the spine's id."""
    rotations = frames_from_centreline(positions)
    extra: dict[str, list[int]] = {}
    if case in CLINICAL_CASES:
        pa_levels, lateral_levels, extra = ALL_LEVELS, None, CLINICAL_CASES[case]
    else:
        pa_levels, lateral_levels = CASES[case]
    rng = np.random.default_rng([seed, sum(map(ord, spine_id))])
    return payload_from_truth(
        positions, rotations, pa_levels, lateral_levels, noise_mm=noise_mm, rng=rng, **extra  # type: ignore[arg-type]
    )


def compare(spine_id: str, positions: np.ndarray, result: RegistrationResult) -> SpineOutcome:
    """A result against the truth: per level |r_j − r_j,truth| (mm), |κ − κ_truth| of the reported
    kyphosis T4–T12 and lordosis L1–L5 (degrees; the truth's ``compute_measures`` on its centreline
    frames), the reported mean PA residual (mm) and mean |ψ_j − ψ_j,truth| over T2..L4 (degrees)."""
    rotations = frames_from_centreline(positions)
    truth_m = compute_measures(positions, rotations)
    recon = np.array([v.position for v in result.vertebrae])
    psi = np.array([v.axial_rotation_deg for v in result.vertebrae])
    m = result.measures
    return SpineOutcome(
        spine_id=spine_id,
        per_level_mm=np.linalg.norm(recon - positions, axis=1),
        kyphosis_error_deg=abs(m.thoracic_kyphosis_t4_t12_deg - truth_m.thoracic_kyphosis_t4_t12_deg),
        lordosis_error_deg=abs(m.lumbar_lordosis_l1_l5_deg - truth_m.lumbar_lordosis_l1_l5_deg),
        registration_error_mm=result.fit.mean_registration_error_mm,
        converged=result.fit.converged,
        axial_rotation_error_deg=float(np.mean(np.abs(psi - axial_rotation_deg(rotations))[1:-1])),
    )


def reconstruct_spine(
    spine_id: str, positions: np.ndarray, case: str, profile: Profile, noise_mm: float = 0.0, seed: int = 0
) -> SpineOutcome:
    """Reconstruct one real spine in one case as a user's job is and compare it with the truth.

    ``register_model(validate_payload(payload), profile=profile)``: ``profile`` is the one the fit
    uses (``spine bench calibrate``'s draws; the bench's ``--profile``). ``noise_mm``: SD of Gaussian
    noise added to every landmark coordinate (detector mm), as a clinician's or a detector's landmark
    error; the boundary poses stay exact. ``FitFailed`` and ``InvalidInput`` from the fit are an
    outcome with ``failure`` set, not an exception.
    """
    model = validate_payload(spine_payload(spine_id, positions, case, noise_mm, seed))
    try:
        result = register_model(model, profile=profile)
    except FitFailed:
        return _failed(spine_id, "not_converged")
    except InvalidInput:
        return _failed(spine_id, "refused")
    return compare(spine_id, positions, result)


def evaluate(
    spines: list[tuple[str, np.ndarray]], case: str, profile: Profile, noise_mm: float = 0.0
) -> list[SpineOutcome]:
    return [reconstruct_spine(sid, pos, case, profile, noise_mm) for sid, pos in spines]


def reconstructed(outcomes: list[SpineOutcome]) -> list[SpineOutcome]:
    """The outcomes with a result (``failure`` None)."""
    return [o for o in outcomes if o.failure is None]


def mean_interior_error(outcomes: list[SpineOutcome]) -> float:
    """Mean over the reconstructed spines of the mean 3D error over T2..L4 (T1, L5 are given), mm;
    NaN when none was."""
    done = reconstructed(outcomes)
    return float(np.mean([o.per_level_mm[1:-1].mean() for o in done])) if done else float("nan")


def summary(case: str, outcomes: list[SpineOutcome]) -> dict[str, Any]:
    """A case's figures (``FIELDS``) over the spines ``register_model`` reconstructed; each spine's
    row says its failure, if any."""
    done = reconstructed(outcomes)
    per_level = np.array([o.per_level_mm for o in done]).reshape(len(done), N_LEVELS)

    def mean(values: list[float]) -> float:
        return float(np.mean(values)) if values else float("nan")

    return {
        "case": case,
        "spines": len(outcomes),
        "reconstructed": len(done),
        "mean_3d_error_mm": mean_interior_error(outcomes),
        "max_3d_error_mm": float(per_level.max()) if done else float("nan"),
        "mean_registration_error_mm": mean([o.registration_error_mm for o in done]),
        "kyphosis_mae_deg": mean([o.kyphosis_error_deg for o in done]),
        "lordosis_mae_deg": mean([o.lordosis_error_deg for o in done]),
        "axial_rotation_mae_deg": mean([o.axial_rotation_error_deg for o in done]),
        "not_converged": sum(o.failure == "not_converged" for o in outcomes),
        "refused": sum(o.failure == "refused" for o in outcomes),
        "per_level_mean_mm": dict(zip(LEVELS, per_level.mean(axis=0).round(3).tolist(), strict=True))
        if done else dict.fromkeys(LEVELS, float("nan")),
        "per_spine": [
            {"id": o.spine_id, "mean_mm": float(o.per_level_mm[1:-1].mean()), "max_mm": float(o.per_level_mm.max())}
            if o.failure is None else {"id": o.spine_id, "failure": o.failure}
            for o in outcomes
        ],
    }


def pa_kyphosis(spines: list[tuple[str, np.ndarray]], noise_mm: float, seed: int = 0) -> dict[str, Any]:
    """One PA film of each spine with T1 and L5 given exactly (``payload_from_truth``: 17 PA landmarks
    with ``noise_mm`` of noise, the boundary poses the truth's centreline frames), reconstructed by
    ``register()`` with its defaults: the reported kyphosis T4–T12 against the truth's (computed on the
    truth's centreline frames), degrees. Reports the RMSE and that of answering VerSe dev's mean (the
    profile's population mean, the trivial estimator), the Pearson correlation with the truth, the
    coverage of the 95 % intervals (±1.96 SD), the reported SDs (min, median, max), how many results name
    "kyphosis" in ``fit.unreliable``, and the truth's correlation with T1's sagittal inclination
    (``measures.sagittal_inclination_deg`` of the truth's frames), which the boundary gives. A spine
    whose ``register()`` raises ``FitFailed`` or ``InvalidInput`` is counted in ``failed`` (with its
    reason in ``failures``) and left out of the figures."""
    profile = load_profile("default")  # register()'s default
    population = population_prior(profile)
    mean = float((profile.population_prior or {})["provenance"]["population"]["kyphosis_t4_t12_deg"]["mean"])
    rows: list[dict[str, Any]] = []
    failures: list[dict[str, str]] = []
    for spine_id, positions in spines:
        rotations = frames_from_centreline(positions)
        rng = np.random.default_rng([seed, sum(map(ord, spine_id))])
        try:
            result = register(payload_from_truth(positions, rotations, ALL_LEVELS, noise_mm=noise_mm, rng=rng))
        except (FitFailed, InvalidInput) as exc:
            failures.append({"id": spine_id, "failure": "not_converged" if isinstance(exc, FitFailed) else "refused"})
            continue
        m = result["measures"]
        rows.append({
            "id": spine_id,
            "truth_deg": compute_measures(positions, rotations).thoracic_kyphosis_t4_t12_deg,
            "reported_deg": float(m["thoracic_kyphosis_t4_t12_deg"]),
            "sd_deg": float(m["thoracic_kyphosis_t4_t12_sd_deg"]),
            "flagged": "kyphosis" in result["fit"]["unreliable"],
            "t1_sagittal_inclination_deg": float(sagittal_inclination_deg(rotations)[0]),
        })  # fmt: skip
    truth = np.array([r["truth_deg"] for r in rows])
    reported = np.array([r["reported_deg"] for r in rows])
    sd = np.array([r["sd_deg"] for r in rows])
    floor_sd = population.measure_sd_deg["kyphosis_t4_t12_deg"] if population else None
    return {
        "spines": len(rows),
        "noise_mm": noise_mm,
        "seed": seed,
        "kyphosis_rmse_deg": float(np.sqrt(np.mean((reported - truth) ** 2))),
        "population_mean_deg": mean,
        "population_mean_rmse_deg": float(np.sqrt(np.mean((mean - truth) ** 2))),
        "correlation_with_truth": float(np.corrcoef(reported, truth)[0, 1]),
        "coverage_95": float(np.mean(np.abs(reported - truth) <= 1.96 * sd)),
        "sd_deg": {"min": float(sd.min()), "median": float(np.median(sd)), "max": float(sd.max())},
        "population_sd_deg": floor_sd,
        "flagged": sum(1 for r in rows if r["flagged"]),
        "failed": len(failures),
        "failures": failures,
        "truth_correlation_with_t1_inclination": float(
            np.corrcoef(truth, [r["t1_sagittal_inclination_deg"] for r in rows])[0, 1]),
        "per_spine": rows,
    }


def plot(summaries: list[dict[str, Any]], path: Path) -> None:
    fig, ax = subplots(figsize=(8, 4))
    for s in summaries:
        label = f"{s['case']} (mean {s['mean_3d_error_mm']:.2f} mm)"
        ax.plot(LEVELS, list(s["per_level_mean_mm"].values()), "o-", label=label)
    ax.set(xlabel="level", ylabel="mean 3D error (mm)", title=f"VerSe, {summaries[0]['spines']} real spines")
    ax.legend()
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="spine bench verse", description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="VerSe folder with dev.csv and test.csv")
    parser.add_argument("--split", choices=["dev", "test"], default="test")
    parser.add_argument("--profile", default="default")
    parser.add_argument("--noise-mm", type=float, default=0.0, help="landmark noise SD, detector mm")
    parser.add_argument("--out", type=Path, default=Path("bench-out/verse"))
    parser.add_argument("--clinical", action="store_true", help="also the pedicle and corner cases")
    parser.add_argument("--plot", type=Path, default=None, help="also write the plot here (e.g. docs/img/...)")
    parser.add_argument("--pa-kyphosis", action="store_true",
                        help="only: one PA film with T1 and L5 given, register(); the kyphosis and its SD")
    parser.add_argument("--limit", type=int, default=None, help="use only the first N spines (quick runs)")
    args = parser.parse_args(argv)
    path = (args.data or default_data_dir()) / f"{args.split}.csv"
    if not path.is_file():
        print(f"error: VerSe split not found at {path} (pass --data or set SPINE_SHARED_DATA)")
        return 2
    spines = read_verse(path)[: args.limit]
    if args.pa_kyphosis:
        found = pa_kyphosis(spines, args.noise_mm)
        stem = f"verse-{args.split}-pa-kyphosis" + (f"-noise{args.noise_mm:g}" if args.noise_mm else "")
        write_json(args.out / f"{stem}.json", {"command": "spine bench verse " + " ".join(
            argv if argv is not None else sys.argv[2:]), "data": str(path), **found})
        print(format_table(["spines", "RMSE", "dev mean's RMSE", "r", "coverage", "SD min", "SD max", "flagged"],
                           [[found["spines"], found["kyphosis_rmse_deg"], found["population_mean_rmse_deg"],
                             found["correlation_with_truth"], found["coverage_95"], found["sd_deg"]["min"],
                             found["sd_deg"]["max"], found["flagged"]]]))  # fmt: skip
        print(f"wrote {args.out}/{stem}.json")
        return 0
    profile = load_profile(args.profile)
    cases = CLINICAL_REPORT if args.clinical else list(CASES)
    summaries = [summary(case, evaluate(spines, case, profile, args.noise_mm)) for case in cases]
    columns = ["case", "spines", "mean_3d_error_mm", "max_3d_error_mm", "mean_registration_error_mm",
               "kyphosis_mae_deg", "lordosis_mae_deg", "not_converged", "refused"]
    if args.clinical:
        columns.insert(-2, "axial_rotation_mae_deg")
    print(format_table(columns, [[s[c] for c in columns] for s in summaries]))
    print()
    print(format_table(["level", *[s["case"] for s in summaries]],
                       [[lv, *[s["per_level_mean_mm"][lv] for s in summaries]] for lv in LEVELS]))
    stem = f"verse-{args.split}" + ("-clinical" if args.clinical else "") + (
        f"-noise{args.noise_mm:g}" if args.noise_mm else ""
    )
    write_json(args.out / f"{stem}.json",
               {"command": "spine bench verse " + " ".join(argv if argv is not None else sys.argv[2:]),
                "data": str(path), "profile": args.profile, "noise_mm": args.noise_mm,
                "measured": "every figure read from register_model's result (the user's path), docs/accuracy.md",
                "fields": FIELDS, "cases": summaries})
    plot(summaries, args.out / f"{stem}.png")
    if args.plot:
        plot(summaries, args.plot)
    print(f"wrote {args.out}/{stem}.json and .png")
    return 0
