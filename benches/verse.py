"""Reconstruction of real spines from CT (VerSe): project, reconstruct, compare in 3D.

Each spine of a VerSe split (vertebral centroids T1..L5, LPS mm) is projected on a PA view
(and, for the PA+L case, a lateral view) by weak perspective; T1 and L5 are given from the truth
(position, and directors built from the centreline by ``frames_from_centreline``); the spine is
reconstructed and its 3D error measured per spine and per level. Tune on ``dev``, report ``test``.

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
from spine_engine.frames import axial_rotation_deg, frames_from_centreline
from spine_engine.levels import LEVELS, N_LEVELS
from spine_engine.measures import compute_measures, sagittal_inclination_deg
from spine_engine.reconstruction import fit_patient_rod, measure_fit, prepare_inputs, register
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


@dataclass(frozen=True)
class SpineOutcome:
    spine_id: str
    per_level_mm: np.ndarray
    kyphosis_error_deg: float
    lordosis_error_deg: float
    registration_error_mm: float
    converged: bool
    axial_rotation_error_deg: float = 0.0
    """Mean |ψ − ψ_truth| over T2..L4, degrees (``frames.axial_rotation_deg``)."""


def reconstruct_spine(
    spine_id: str, positions: np.ndarray, case: str, profile: Profile, noise_mm: float = 0.0, seed: int = 0
) -> SpineOutcome:
    """Reconstruct one real spine in one case and compare it with the truth.

    ``noise_mm``: SD of Gaussian noise added to every landmark coordinate (detector mm), as a
    clinician's or a detector's landmark error; the boundary poses stay exact.
    """
    rotations = frames_from_centreline(positions)
    extra: dict[str, list[int]] = {}
    if case in CLINICAL_CASES:
        pa_levels, lateral_levels, extra = ALL_LEVELS, None, CLINICAL_CASES[case]
    else:
        pa_levels, lateral_levels = CASES[case]
    rng = np.random.default_rng([seed, sum(map(ord, spine_id))])
    payload = payload_from_truth(
        positions, rotations, pa_levels, lateral_levels, noise_mm=noise_mm, rng=rng, **extra  # type: ignore[arg-type]
    )
    model = validate_payload(payload)
    inputs = prepare_inputs(model, profile)
    out = fit_patient_rod(inputs, profile)[0].output  # a Profile object: ``spine bench calibrate``'s draws
    truth_m = compute_measures(positions, rotations)
    recon_m = measure_fit(inputs, out)  # as ``register`` measures the fit
    return SpineOutcome(
        spine_id=spine_id,
        per_level_mm=np.linalg.norm(out.positions - positions, axis=1),
        kyphosis_error_deg=abs(recon_m.thoracic_kyphosis_t4_t12_deg - truth_m.thoracic_kyphosis_t4_t12_deg),
        lordosis_error_deg=abs(recon_m.lumbar_lordosis_l1_l5_deg - truth_m.lumbar_lordosis_l1_l5_deg),
        registration_error_mm=float(np.mean(out.residuals_mm["pa"])),
        converged=out.converged,
        axial_rotation_error_deg=float(
            np.mean(np.abs(axial_rotation_deg(out.rotations) - axial_rotation_deg(rotations))[1:-1])
        ),
    )


def evaluate(
    spines: list[tuple[str, np.ndarray]], case: str, profile: Profile, noise_mm: float = 0.0
) -> list[SpineOutcome]:
    return [reconstruct_spine(sid, pos, case, profile, noise_mm) for sid, pos in spines]


def mean_interior_error(outcomes: list[SpineOutcome]) -> float:
    """Mean over spines of the mean 3D error over T2..L4 (T1, L5 are given)."""
    return float(np.mean([o.per_level_mm[1:-1].mean() for o in outcomes]))


def summary(case: str, outcomes: list[SpineOutcome]) -> dict[str, Any]:
    per_level = np.array([o.per_level_mm for o in outcomes])
    return {
        "case": case,
        "spines": len(outcomes),
        "mean_3d_error_mm": mean_interior_error(outcomes),
        "max_3d_error_mm": float(per_level.max()),
        "mean_registration_error_mm": float(np.mean([o.registration_error_mm for o in outcomes])),
        "kyphosis_mae_deg": float(np.mean([o.kyphosis_error_deg for o in outcomes])),
        "lordosis_mae_deg": float(np.mean([o.lordosis_error_deg for o in outcomes])),
        "axial_rotation_mae_deg": float(np.mean([o.axial_rotation_error_deg for o in outcomes])),
        "not_converged": int(sum(not o.converged for o in outcomes)),
        "per_level_mean_mm": dict(zip(LEVELS, per_level.mean(axis=0).round(3).tolist(), strict=True)),
        "per_spine": [
            {"id": o.spine_id, "mean_mm": float(o.per_level_mm[1:-1].mean()), "max_mm": float(o.per_level_mm.max())}
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
    (``measures.sagittal_inclination_deg`` of the truth's frames), which the boundary gives."""
    profile = load_profile("default")  # register()'s default
    population = population_prior(profile)
    mean = float((profile.population_prior or {})["provenance"]["population"]["kyphosis_t4_t12_deg"]["mean"])
    rows: list[dict[str, Any]] = []
    for spine_id, positions in spines:
        rotations = frames_from_centreline(positions)
        rng = np.random.default_rng([seed, sum(map(ord, spine_id))])
        result = register(payload_from_truth(positions, rotations, ALL_LEVELS, noise_mm=noise_mm, rng=rng))
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
               "kyphosis_mae_deg", "lordosis_mae_deg", "not_converged"]
    if args.clinical:
        columns.insert(-1, "axial_rotation_mae_deg")
    print(format_table(columns, [[s[c] for c in columns] for s in summaries]))
    print()
    print(format_table(["level", *[s["case"] for s in summaries]],
                       [[lv, *[s["per_level_mean_mm"][lv] for s in summaries]] for lv in LEVELS]))
    stem = f"verse-{args.split}" + ("-clinical" if args.clinical else "") + (
        f"-noise{args.noise_mm:g}" if args.noise_mm else ""
    )
    write_json(args.out / f"{stem}.json",
               {"data": str(path), "profile": args.profile, "noise_mm": args.noise_mm, "cases": summaries})
    plot(summaries, args.out / f"{stem}.png")
    if args.plot:
        plot(summaries, args.plot)
    print(f"wrote {args.out}/{stem}.json and .png")
    return 0
