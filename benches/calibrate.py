"""Elastic properties by Monte Carlo, as in Li et al. (2009): sample, score on a training set, keep the best.

Two steps, both on the training split (VerSe ``dev``) only — never on ``test``:
1. Rest shape: the mean sagittal shape of the training spines (the inclination of each
   vertebra's tangent relative to T1's, and each segment's share of the T1–L5 length) replaces
   the literature's normal profile as the rod's rest shape.
2. Monte Carlo: Young's modulus Y, shear modulus G (MPa) and the stretch factor are drawn
   log-uniformly around the starting profile; each draw reconstructs every training spine from
   17 PA landmarks and from 17 PA + 17 lateral landmarks and is scored by the sum of the two mean
   3D errors. The landmark weights stay fixed: only the ratio of stiffness to weight matters.
   A profile with a population prior (``spine bench prior``) takes its bending, twist and shear
   stiffnesses from that prior, and Y acts only in the stretch stiffness stretch_factor·Y·A
   (``anatomy.rest_model``): from such a profile only the stretch factor is drawn.
``--check`` writes nothing: it scores the start profile's stretch factor times a grid of multipliers
on this score and on the clinic's (``spine bench noise-weight``'s: VerSe dev filmed as ``spine
bench clinic`` films it, no boundary), to show where the shipped value sits on each.
The best draw is written as a named profile with its provenance (``--write``), never over or from a
profile with a population prior (``refusal``).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from benches import clinic, noise_weight
from benches.report import format_table, write_json
from benches.truth import read_verse
from benches.verse import default_data_dir, evaluate, mean_interior_error
from spine_engine.anatomy import PROFILES_DIR, Profile, load_profile, save_profile
from spine_engine.errors import UnknownProfile
from spine_engine.frames import frames_from_centreline


def score(spines: list[tuple[str, np.ndarray]], profile: Profile) -> tuple[float, float]:
    """Mean 3D error (mm, T2..L4) with PA-17 and with PA-17 + lateral-17, each spine fitted as a
    user's job is (``verse.reconstruct_spine``: ``register_model`` with ``profile``); +inf for a case
    where ``register_model`` fails on any spine (not converged, or refused): a draw users could not
    fit scores worst, not better by dropping its hardest spines."""

    def case_score(case: str) -> float:
        outcomes = evaluate(spines, case, profile)
        return math.inf if any(o.failure is not None for o in outcomes) else mean_interior_error(outcomes)

    return case_score("PA-17"), case_score("PA-17+L-17")


MECHANICAL = ("youngs_modulus_mpa", "shear_modulus_mpa", "stretch_factor")


def searched(base: Profile) -> tuple[str, ...]:
    """The profile fields the search draws: Y, G and the stretch factor, or the stretch factor
    alone when ``base`` has a population prior (its bending, twist and shear stiffnesses are the
    prior's then, and Y appears only in the product stretch_factor·Y·A)."""
    return ("stretch_factor",) if base.population_prior is not None else MECHANICAL


def sample(base: Profile, rng: np.random.Generator, decades: float) -> Profile:
    """A profile with Y, G and the stretch factor each multiplied by 10^U(−decades, decades), the
    ones ``searched(base)`` leaves out kept (one draw of three factors either way, so a seed gives
    the same stretch factors with or without a prior)."""
    factors = dict(zip(MECHANICAL, 10.0 ** rng.uniform(-decades, decades, size=3), strict=True))
    drawn: dict[str, Any] = {k: float(getattr(base, k) * factors[k]) for k in searched(base)}
    return dataclasses.replace(base, **drawn)


def refusal(start: Profile, target: Profile | None) -> str | None:
    """Why a draw from ``start`` may not be written over ``target`` (None: no such profile yet), or
    None. A profile with a population prior keeps the stretch factor it was calibrated with: the
    prior's sagittal SDs, the landmark weight and the uncertainty constants were fitted with it in
    place, and this search's score (the paper's setting) would stiffen it at the cost of one PA
    film's depth (``--check``). A start without a prior would drop the target's prior."""
    if start.population_prior is not None:
        return (f"profile {start.name!r} has a population prior, fitted with its stretch factor in place; "
                "see --check for where that factor sits")
    if target is not None and target.population_prior is not None:
        return f"profile {target.name!r} has a population prior that a draw from {start.name!r} would drop"
    return None


CHECK_GRID = (0.3, 0.56, 1.0, 1.78, 3.0)
"""Stretch-factor multipliers of ``--check``: a quarter decade apart, ±½ decade."""


def stretch_check(profile: Profile, path: Path, grid: tuple[float, ...] = CHECK_GRID) -> list[dict[str, Any]]:
    """One row per multiplier m of ``profile``'s stretch factor: this search's two scores (mm, VerSe
    dev at ``path``) and the clinic's mean 3D error per case and their mean (mm, with the cases,
    noise and seed of the profile's landmark-weight calibration, ``noise_weight.score``)."""
    spines, truths = read_verse(path), clinic.truths_of_csv(path)
    shipped = profile.provenance["noise_calibration"]
    rows = []
    for mult in grid:
        prof = dataclasses.replace(profile, stretch_factor=profile.stretch_factor * mult)
        paper = score(spines, prof)
        cases = noise_weight.score(prof, truths, shipped["cases"], shipped["noise_mm"], shipped["seed"])
        rows.append({"multiplier": mult, "stretch_factor": prof.stretch_factor,
                     "paper_mm": {"PA-17": paper[0], "PA-17+L-17": paper[1]}, "paper_score_mm": sum(paper),
                     "clinic_mm": cases, "clinic_score_mm": float(np.mean(list(cases.values())))})  # fmt: skip
    return rows


def mean_sagittal_shape(spines: list[tuple[str, np.ndarray]]) -> dict[str, Any]:
    """Mean rest shape of real spines: per-vertebra sagittal inclination relative to T1 (degrees,
    the tangent's angle toward +y going caudally, as ``measures.sagittal_inclination_deg``) and
    each segment's fraction of the summed segment lengths."""
    inclinations, fractions = [], []
    for _, positions in spines:
        tangent = frames_from_centreline(positions)[:, :, 2]
        beta = np.degrees(np.arctan2(tangent[:, 1], -tangent[:, 2]))
        inclinations.append(beta - beta[0])
        lengths = np.linalg.norm(np.diff(positions, axis=0), axis=1)
        fractions.append(lengths / lengths.sum())
    return {
        "sagittal_inclination_deg": np.round(np.mean(inclinations, axis=0), 4).tolist(),
        "length_fractions": np.round(np.mean(fractions, axis=0), 6).tolist(),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="spine bench calibrate", description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="VerSe folder (only dev.csv is read)")
    parser.add_argument("--samples", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--decades", type=float, default=1.5, help="half-width of the log10 sampling range")
    parser.add_argument("--start", default="literature", help="profile to start from")
    parser.add_argument("--write", default=None, help="write the best draw as this profile name")
    parser.add_argument("--check", action="store_true",
                        help="score the start profile's stretch factor on a grid of multipliers, write nothing")
    parser.add_argument("--out", type=Path, default=None, help="with --check: folder of calibrate-check.json")
    args = parser.parse_args(argv)
    if args.out is not None and not args.check:
        parser.error("--out goes with --check (the search writes a profile, not a JSON)")
    path = (args.data or default_data_dir()) / "dev.csv"
    if not path.is_file():
        print(f"error: VerSe dev split not found at {path} (pass --data or set SPINE_SHARED_DATA)")
        return 2
    try:
        start_profile = load_profile(args.start)
    except UnknownProfile as exc:
        print(f"error: --start: {exc.errors[0].msg}")
        return 2
    try:
        target = load_profile(args.write) if args.write else None
    except UnknownProfile:
        target = None
    if args.write and (why := refusal(start_profile, target)):
        print(f"error: --write {args.write}: {why}")
        return 2
    if args.check:
        return check(start_profile, path, args.out)
    spines = read_verse(path)
    shape = mean_sagittal_shape(spines)
    shape["source"] = f"mean of the VerSe dev split ({len(spines)} spines from CT), {path.name}"
    base = dataclasses.replace(start_profile, rest_shape=shape)
    rng = np.random.default_rng(args.seed)
    print(f"drawing {', '.join(searched(base))} within ±{args.decades} decades")
    start = time.perf_counter()
    best, best_scores = base, score(spines, base)
    print(f"start  Y={base.youngs_modulus_mpa:10.4g} G={base.shear_modulus_mpa:10.4g} "
          f"stretch={base.stretch_factor:8.3g}  "
          f"PA {best_scores[0]:.3f} mm  PA+L {best_scores[1]:.3f} mm")
    for i in range(args.samples):
        candidate = sample(base, rng, args.decades)
        scores = score(spines, candidate)
        if sum(scores) < sum(best_scores):
            best, best_scores = candidate, scores
            print(f"#{i:<5} Y={best.youngs_modulus_mpa:10.4g} G={best.shear_modulus_mpa:10.4g} "
                  f"stretch={best.stretch_factor:8.3g}  "
                  f"PA {scores[0]:.3f} mm  PA+L {scores[1]:.3f} mm  (best so far)")
    elapsed = time.perf_counter() - start
    print(f"best   Y={best.youngs_modulus_mpa:.4g} MPa G={best.shear_modulus_mpa:.4g} MPa "
          f"stretch factor {best.stretch_factor:.4g}: "
          f"PA {best_scores[0]:.3f} mm, PA+L {best_scores[1]:.3f} mm on {len(spines)} dev spines ({elapsed:.0f} s)")
    if args.write:
        record = {
            "method": "rest shape = mean sagittal shape of the training spines; then Monte Carlo over "
                      f"{', '.join(searched(base))} (log-uniform), benches.calibrate",
            "command": f"spine bench calibrate --samples {args.samples} --seed {args.seed} "
                       f"--decades {args.decades} --start {args.start} --write {args.write}",
            "training_set": f"VerSe dev split ({len(spines)} spines), {path.name}",
            "score_dev_mean_3d_error_mm": {"PA-17": round(best_scores[0], 4), "PA-17+L-17": round(best_scores[1], 4)},
            "date": dt.date.today().isoformat(),
        }
        record["started_from"] = {"profile": args.start, **{k: getattr(base, k) for k in MECHANICAL},
                                  "provenance": base.provenance}
        chosen = dataclasses.replace(best, name=args.write, provenance=record)
        save_profile(chosen, PROFILES_DIR / f"{args.write}.json")
        print(f"wrote profile {args.write!r} to {PROFILES_DIR / (args.write + '.json')}")
    return 0


def check(profile: Profile, path: Path, out: Path | None) -> int:
    """``--check``: print (and write to ``out``/calibrate-check.json) ``stretch_check``'s table."""
    if "noise_calibration" not in profile.provenance:
        print(f"error: profile {profile.name!r} has no landmark-weight calibration to take the clinic's cases from")
        return 2
    rows = stretch_check(profile, path)
    print(format_table(
        ["x stretch", "stretch factor", "PA-17", "PA-17+L-17", "paper score",
         *(f"({k})" for k in rows[0]["clinic_mm"]), "clinic score"],
        [[r["multiplier"], r["stretch_factor"], r["paper_mm"]["PA-17"], r["paper_mm"]["PA-17+L-17"],
          r["paper_score_mm"], *r["clinic_mm"].values(), r["clinic_score_mm"]] for r in rows]))
    if out is not None:
        write_json(out / "calibrate-check.json", {
            "command": f"spine bench calibrate --check --start {profile.name}", "data": path.name,
            "profile": profile.name, "searched": list(searched(profile)), "rows": rows})
        print(f"wrote {out / 'calibrate-check.json'}")
    return 0
