"""``spine bench noise-weight``: the prior's strength for noisy landmarks, by Monte Carlo on VerSe dev.

The landmarks weigh w·(σ_ref/σ)² (σ a view's ``landmark_sd_mm``, σ_ref = 1 mm,
``models.LANDMARK_SD_MM_DEFAULT``) against the rod's potential energy, so the profile's
``fit_weight_pa`` / ``fit_weight_lateral`` w set how strongly the elastic prior smooths landmark
noise. This command scores a grid of multipliers of the current weights on the VerSe ``dev`` spines
(never ``test``), filmed as in ``spine bench clinic`` with ``--noise-mm`` (default 1 mm) landmark
noise, no boundary and uncalibrated films: cases (a) PA + full lateral, (b) lateral T4–L5,
(c) perspective films with their geometry and (e) PA only. The score is the mean over the cases of
the mean 3D error after removing the translation; the grid's scores go to ``noise-weight.json`` in
``--out``, and the best multiplier is written into the profile (``--write``) with the grid's scores
as provenance (``provenance.noise_calibration``).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from benches import clinic
from benches.clinic_films import CASES, Truth, simulate_series
from benches.report import write_json
from spine_engine.anatomy import PROFILES_DIR, Profile, load_profile, save_profile
from spine_engine.reconstruction import register_model
from spine_engine.validation import validate_payload

DEFAULT_GRID = (3.0, 1.0, 0.3, 0.1, 0.03)
DEFAULT_CASES = "abce"


def score(profile: Profile, truths: list[Truth], cases: str, noise_mm: float, seed: int) -> dict[str, float]:
    """Mean 3D error (mm, translation removed) per case with ``profile``'s weights."""
    def registrar(payload: dict[str, Any]) -> dict[str, Any]:
        return register_model(validate_payload(payload), profile=profile).model_dump(mode="json")

    out = {}
    for key in cases:
        runs = [clinic.run_one(simulate_series(t, noise_mm, seed), CASES[key], registrar=registrar) for t in truths]
        ok = [r for r in runs if r.ok]
        out[key] = float(np.mean([r.per_level_mm.mean() for r in ok])) if ok else float("inf")
    return out


def grid_scores(
    base: Profile, truths: list[Truth], grid: list[float], cases: str, noise_mm: float, seed: int
) -> list[dict[str, Any]]:
    """One row per multiplier m of ``base``'s landmark weights: the weights m·w, each case's mean 3D
    error (``score``) and their mean, the score the command minimises; printed as they come."""
    rows: list[dict[str, Any]] = []
    for mult in grid:
        prof = dataclasses.replace(
            base, fit_weight_pa=base.fit_weight_pa * mult, fit_weight_lateral=base.fit_weight_lateral * mult
        )
        errors = score(prof, truths, cases, noise_mm, seed)
        rows.append({"multiplier": mult, "fit_weight_pa": prof.fit_weight_pa, "mean_3d_error_mm": errors,
                     "score_mm": float(np.mean(list(errors.values())))})  # fmt: skip
        print(f"x{mult:<6g} w = {prof.fit_weight_pa:9.4g} N/mm  "
              + "  ".join(f"({k}) {v:.3f}" for k, v in errors.items()) + f"  score {rows[-1]['score_mm']:.3f}",
              flush=True)  # fmt: skip
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="spine bench noise-weight", description=__doc__)
    parser.add_argument("--data", type=Path, default=None, help="VerSe folder (only dev.csv is read)")
    parser.add_argument("--profile", default="default")
    parser.add_argument("--grid", default=",".join(f"{m:g}" for m in DEFAULT_GRID), help="weight multipliers")
    parser.add_argument("--cases", default=DEFAULT_CASES)
    parser.add_argument("--noise-mm", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--write", default=None, help="write the best multiplier's weights into this profile")
    parser.add_argument("--out", type=Path, default=Path("bench-out/noise-weight"),
                        help="folder of noise-weight.json (the grid's scores)")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    truths = clinic.verse_truths("dev", args.data)
    base = load_profile(args.profile)
    grid = [float(x) for x in args.grid.split(",")]
    rows = grid_scores(base, truths, grid, args.cases, args.noise_mm, args.seed)
    best = min(rows, key=lambda r: r["score_mm"])
    print(f"best: x{best['multiplier']:g} (w = {best['fit_weight_pa']:.4g} N/mm), {time.perf_counter() - start:.0f} s")
    write_json(args.out / "noise-weight.json", {
        "command": "spine bench noise-weight " + " ".join(argv if argv is not None else sys.argv[2:]),
        "date": dt.date.today().isoformat(), "profile": args.profile,
        "fit_weight_pa": base.fit_weight_pa, "fit_weight_lateral": base.fit_weight_lateral,
        "spines": len(truths), "noise_mm": args.noise_mm, "seed": args.seed, "cases": args.cases,
        "grid": rows, "best_multiplier": best["multiplier"],
    })  # fmt: skip
    print(f"wrote {args.out / 'noise-weight.json'}")
    if args.write:
        provenance = dict(base.provenance)
        provenance["noise_calibration"] = {
            "method": __doc__.split("\n\n")[1].replace("\n", " ") if __doc__ else "",
            "command": "spine bench noise-weight " + " ".join(argv if argv is not None else []),
            "training_set": f"VerSe dev split ({len(truths)} spines), dev.csv",
            "noise_mm": args.noise_mm,
            "seed": args.seed,
            "cases": args.cases,
            "started_from": {"fit_weight_pa": base.fit_weight_pa, "fit_weight_lateral": base.fit_weight_lateral},
            "grid": rows,
            "chosen_multiplier": best["multiplier"],
            "date": dt.date.today().isoformat(),
        }
        chosen = dataclasses.replace(
            base,
            name=args.write,
            fit_weight_pa=best["fit_weight_pa"],
            fit_weight_lateral=base.fit_weight_lateral * best["multiplier"],
            provenance=provenance,
        )
        save_profile(chosen, PROFILES_DIR / f"{args.write}.json")
        print(f"wrote {PROFILES_DIR / (args.write + '.json')}")
    return 0
