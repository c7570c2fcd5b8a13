"""``spine bench lateral-mirror``: lateral films read mirrored, and the check that refuses them.

A lateral film whose ``patient_orientation`` is mirrored (displayed flipped, or labelled ["A", "F"] with
the patient's anterior on the other side) reads every depth negated: the thoracic kyphosis as lordosis,
the lumbar lordosis as kyphosis. ``spine_engine.lateral_profile`` refuses a lateral whose thoracic and
lumbar profiles both read inverted beyond its landmark noise. This bench measures, on simulated
scoliosis series (``clinic_films``: every case with a lateral, a, b, c, d, f, g, h; each also with levels
left out, ``clinic.drop_landmarks``):

* ``population``: the kyphosis T4–T12 and lordosis L1–L5 (the engine's conventions, docs/measures.md)
  of VerSe dev and test and of the synthetic spines, and the check's own reading of their noise-free
  lateral films (``lateral_profile.profile_readings``) beside them;
* ``false_refusals``: the payloads as the clinic sends them, through ``validate_payload``, at each noise
  SD and seed: how many are refused as ``lateral_profile_inverted`` (and any other refusal);
* ``detection``: the same payloads with the lateral mirrored, two ways: its orientation's depth letter
  swapped (A ↔ P), and its columns flipped about a 350 mm film's centre (c → 350 − c, the central ray's
  column too) under the stated labels;
* ``profiles`` (stress): straight-frontal spines with the sagittal profile of ``anatomy.sagittal_profile_deg``
  at kyphosis −30–+10° and lordosis −20–+10°, at 1 and 3 mm: where the rule bites a genuinely inverted spine;
* ``fits`` (``--fits``): what the engine reads (``register_model`` on the pydantic model, validation
  skipped, as before the check) on VerSe dev, case (a) and (c), 1 mm, seed 0: the stated and both
  mirrored films' kyphosis and lordosis and ``fit.unreliable``.

VerSe test and the synthetic spines are reported, never tuned on: the rule's bounds are signs from the
cited populations (``lateral_profile``'s docstring) and its noise allowance ``PROFILE_NOISE_SDS``.
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from benches.clinic import drop_landmarks, synthetic_truths, truths_of_csv
from benches.clinic_films import CASES, Truth, build_payload, seed_of, simulate_series
from benches.report import shared_data_dir, write_json
from spine_engine.anatomy import centreline_from_angles, rest_segment_lengths, sagittal_profile_deg
from spine_engine.errors import InvalidInput, SpineEngineError
from spine_engine.frames import frames_from_centreline
from spine_engine.lateral_profile import CHECK_NAME, PROFILE_NOISE_SDS, profile_readings
from spine_engine.levels import LEVEL_INDEX, N_LEVELS
from spine_engine.measures import kyphosis_lordosis_deg
from spine_engine.models import JobPayload
from spine_engine.reconstruction import register_model
from spine_engine.validation import validate_payload

LATERAL_CASES = tuple(key for key, case in CASES.items() if case.lateral_from is not None)
"""The clinic cases whose payload has a lateral film."""
FILM_WIDTH_MM = 350.0
"""Width of the simulated film (35 × 90 cm, ``clinic_films.FILM_OFFSET_MM``): a mirrored display maps
column c to FILM_WIDTH_MM − c."""
NOISES_MM = (1.0, 2.0, 3.0)
PROFILE_GRID = {"kyphosis_deg": (-30.0, -20.0, -10.0, 0.0, 10.0), "lordosis_deg": (-20.0, -10.0, 0.0, 10.0)}
"""Sagittal profiles of the stress spines (``profiles``)."""
FIT_CASES = ("a", "c")


def mirrored_labels(payload: dict[str, Any]) -> dict[str, Any]:
    """``payload`` with the lateral's depth letter swapped (A ↔ P): the same image, labelled mirrored."""
    out = copy.deepcopy(payload)
    swap = {"A": "P", "P": "A"}
    out["lateral"]["patient_orientation"] = [swap.get(d, d) for d in out["lateral"]["patient_orientation"]]
    return out


def mirrored_columns(payload: dict[str, Any]) -> dict[str, Any]:
    """``payload`` with the lateral image flipped left to right (column c → ``FILM_WIDTH_MM`` − c, the
    central ray's column too) and its labels kept: a film displayed mirrored."""
    out = copy.deepcopy(payload)
    lateral = out["lateral"]
    for lm in lateral["landmarks"]:
        if "point" in lm:
            lm["point"][0] = FILM_WIDTH_MM - lm["point"][0]
    ray = (lateral.get("acquisition") or {}).get("central_ray")
    if ray is not None:
        ray[0] = FILM_WIDTH_MM - ray[0]
    return out


def outcome(payload: dict[str, Any]) -> str:
    """ "accepted", "inverted" (refused as ``lateral_profile_inverted``) or "other:<codes>"."""
    try:
        validate_payload(payload)
    except InvalidInput as exc:
        codes = sorted({e.type for e in exc.errors})
        return "inverted" if codes == [CHECK_NAME] else "other:" + ",".join(codes)
    return "accepted"


def payloads(truth: Truth, noise: float, seed: int, drop: bool) -> list[tuple[str, dict[str, Any]]]:
    """(case, JSON payload) of every case with a lateral for one spine, noise SD and seed; with ``drop``
    each view keeps a random subset of its landmarks (``drop_landmarks``, seeded by the seed and the spine)."""
    series = simulate_series(truth, noise, seed)
    rng = np.random.default_rng([seed, seed_of(truth.spine_id), 7])
    out = []
    for key in LATERAL_CASES:
        payload = build_payload(series, CASES[key]).model_dump(mode="json", exclude_none=True)
        if drop:
            drop_landmarks(payload, rng)
        out.append((key, payload))
    return out


def _count(outcomes: Sequence[str]) -> dict[str, Any]:
    others = [o for o in outcomes if o.startswith("other")]
    return {
        "payloads": len(outcomes),
        "refused_inverted": sum(o == "inverted" for o in outcomes),
        "refused_other": len(others),
        "other_codes": sorted(set(others)),
    }


def sweep(datasets: dict[str, list[Truth]], seeds: int) -> dict[str, Any]:
    """False refusals and detection per data set and noise SD (every lateral case, all levels and levels
    left out, ``seeds`` noise seeds); the payloads refused under the stated orientation are listed, and the
    detection rate split by case and by form (a lateral with levels left out may not reach T6–T11 or
    L1–L5: ``lateral_profile.THORACIC_REACH``, ``LUMBAR_REACH``; such a film is not judged)."""
    result: dict[str, Any] = {}
    for name, truths in datasets.items():
        per_noise: dict[str, Any] = {}
        for noise in NOISES_MM:
            stated, labels, columns, refused = [], [], [], []
            per_case: dict[str, list[str]] = {key: [] for key in LATERAL_CASES}
            per_form: dict[str, list[str]] = {"all_levels": [], "levels_left_out": []}
            for truth in truths:
                for seed in range(seeds):
                    for drop in (False, True):
                        for key, payload in payloads(truth, noise, seed, drop):
                            o = outcome(payload)
                            stated.append(o)
                            if o == "inverted":
                                refused.append({"spine": truth.spine_id, "case": key, "seed": seed, "drop": drop})
                            labels.append(outcome(mirrored_labels(payload)))
                            columns.append(outcome(mirrored_columns(payload)))
                            per_case[key].append(labels[-1])
                            per_form["levels_left_out" if drop else "all_levels"].append(labels[-1])
            per_noise[f"{noise:g}"] = {
                "stated": _count(stated) | {"refused_payloads": refused},
                "mirrored_labels": _count(labels),
                "mirrored_columns": _count(columns),
                "detection_rate_labels": sum(o == "inverted" for o in labels) / len(labels),
                "detection_rate_columns": sum(o == "inverted" for o in columns) / len(columns),
                "detection_rate_labels_per_case": {
                    k: sum(o == "inverted" for o in v) / len(v) for k, v in per_case.items()
                },
                "detection_rate_labels_per_form": {
                    k: sum(o == "inverted" for o in v) / len(v) for k, v in per_form.items()
                },
            }
        result[name] = per_noise
    return result


def _summary(values: Sequence[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=float)
    return {"min": float(a.min()), "mean": float(a.mean()), "max": float(a.max()), "sd": float(a.std(ddof=1))}


def population(datasets: dict[str, list[Truth]]) -> dict[str, Any]:
    """Each data set's kyphosis T4–T12 and lordosis L1–L5 (engine conventions, on the centreline's frames)
    and the check's reading of its noise-free lateral film (case (a), seed 0): values and the reading's
    difference (kyphosis) and ratio (lordosis) to the measure."""
    out: dict[str, Any] = {}
    for name, truths in datasets.items():
        rows: list[dict[str, Any]] = []
        for truth in truths:
            k4, _, lo = kyphosis_lordosis_deg(frames_from_centreline(truth.positions))
            payload = build_payload(simulate_series(truth, 0.0, 0), CASES["a"]).model_dump(mode="json")
            view = payload["lateral"]
            landmarks = [(LEVEL_INDEX[lm["level"]], *lm["point"]) for lm in view["landmarks"]]
            thoracic, lumbar = profile_readings(tuple(view["patient_orientation"]), landmarks, 1.0)
            assert thoracic is not None and lumbar is not None
            rows.append({"spine": truth.spine_id, "kyphosis_t4_t12_deg": k4, "lordosis_l1_l5_deg": lo,
                         "reading_kyphosis_deg": thoracic.angle_deg, "reading_lordosis_deg": -lumbar.angle_deg,
                         "reading_sd_at_1mm_deg": [thoracic.sd_deg, lumbar.sd_deg]})  # fmt: skip
        out[name] = {
            "kyphosis_t4_t12_deg": _summary([r["kyphosis_t4_t12_deg"] for r in rows]),
            "lordosis_l1_l5_deg": _summary([r["lordosis_l1_l5_deg"] for r in rows]),
            "reading_kyphosis_deg": _summary([r["reading_kyphosis_deg"] for r in rows]),
            "reading_lordosis_deg": _summary([r["reading_lordosis_deg"] for r in rows]),
            "reading_minus_kyphosis_deg": _summary(
                [r["reading_kyphosis_deg"] - r["kyphosis_t4_t12_deg"] for r in rows]
            ),
            "reading_over_lordosis": _summary([r["reading_lordosis_deg"] / r["lordosis_l1_l5_deg"] for r in rows]),
            "spines": rows,
        }
    return out


def profile_spine(kyphosis: float, lordosis: float) -> Truth:
    """A spine straight in the frontal plane with the sagittal profile ``sagittal_profile_deg(kyphosis,
    lordosis)`` on the rest segment lengths, directors from its centreline."""
    beta = sagittal_profile_deg(kyphosis, lordosis)
    positions = centreline_from_angles(rest_segment_lengths(), np.zeros(N_LEVELS), beta - beta.mean())
    return Truth(f"profile-k{kyphosis:g}-l{lordosis:g}", positions, frames_from_centreline(positions))


def profiles(seeds: int) -> list[dict[str, Any]]:
    """Refused fraction of the stress spines' stated payloads (``PROFILE_GRID``), at 1 and 3 mm."""
    rows = []
    for kyphosis in PROFILE_GRID["kyphosis_deg"]:
        for lordosis in PROFILE_GRID["lordosis_deg"]:
            truth = profile_spine(kyphosis, lordosis)
            k4, _, lo = kyphosis_lordosis_deg(truth.rotations)
            row: dict[str, Any] = {"kyphosis_deg": k4, "lordosis_deg": lo}
            for noise in (1.0, 3.0):
                got = [outcome(p) for seed in range(seeds) for _, p in payloads(truth, noise, seed, False)]
                row[f"refused_fraction_{noise:g}mm"] = sum(o == "inverted" for o in got) / len(got)
            rows.append(row)
    return rows


def _read(payload: dict[str, Any]) -> dict[str, Any]:
    """The engine's kyphosis, lordosis and ``fit.unreliable`` for a payload, validation skipped."""
    try:
        result = register_model(JobPayload.model_validate(payload)).model_dump(mode="json")
    except SpineEngineError as exc:
        return {"error": f"{type(exc).__name__}: {exc}"[:200]}
    m = result["measures"]
    return {
        "kyphosis_t4_t12_deg": m["thoracic_kyphosis_t4_t12_deg"],
        "lordosis_l1_l5_deg": m["lumbar_lordosis_l1_l5_deg"],
        "unreliable": result["fit"]["unreliable"],
    }


def fits(truths: list[Truth]) -> dict[str, Any]:
    """What the engine reads of each spine's stated and mirrored lateral (cases ``FIT_CASES``, 1 mm, seed 0)."""
    out: dict[str, Any] = {}
    for key in FIT_CASES:
        rows: list[dict[str, Any]] = []
        for truth in truths:
            payload = build_payload(simulate_series(truth, 1.0, 0), CASES[key]).model_dump(
                mode="json", exclude_none=True
            )
            k4, _, lo = kyphosis_lordosis_deg(truth.rotations)
            rows.append({"spine": truth.spine_id, "truth": {"kyphosis_t4_t12_deg": k4, "lordosis_l1_l5_deg": lo},
                         "stated": _read(payload), "mirrored_labels": _read(mirrored_labels(payload)),
                         "mirrored_columns": _read(mirrored_columns(payload))})  # fmt: skip
        summary: dict[str, Any] = {}
        for form in ("stated", "mirrored_labels", "mirrored_columns"):
            ok = [r[form] for r in rows if "error" not in r[form]]
            summary[form] = {
                "failed": len(rows) - len(ok),
                "kyphosis_t4_t12_deg": _summary([r["kyphosis_t4_t12_deg"] for r in ok]),
                "lordosis_l1_l5_deg": _summary([r["lordosis_l1_l5_deg"] for r in ok]),
                "flagged_kyphosis_or_lordosis": sum(bool({"kyphosis", "lordosis"} & set(r["unreliable"])) for r in ok),
            }
        out[key] = {"summary": summary, "spines": rows}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="spine bench lateral-mirror", description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="VerSe folder with dev.csv and test.csv")
    parser.add_argument("--seeds", type=int, default=5, help="noise seeds per spine, case and SD (default 5)")
    parser.add_argument("--synthetic", type=int, default=24, help="synthetic spines per split (default 24)")
    parser.add_argument("--fits", action="store_true", help="also run the engine on VerSe dev's mirrored films")
    parser.add_argument("--out", type=Path, default=Path("bench-out"), help="folder of lateral-mirror.json")
    args = parser.parse_args(argv)
    verse = args.data or shared_data_dir("verse")
    datasets: dict[str, list[Truth]] = {}
    for split in ("dev", "test"):
        path = verse / f"{split}.csv"
        if path.is_file():
            datasets[f"verse-{split}"] = truths_of_csv(path)
        elif split == "dev":
            datasets["verse-dev"] = truths_of_csv(
                Path(__file__).resolve().parents[1] / "tests" / "data" / "verse_dev.csv"
            )
        else:
            print(f"note: {path} not found; VerSe test left out", file=sys.stderr)
    if args.synthetic > 0:
        for split in ("dev", "test"):
            datasets[f"synthetic-{split}"] = synthetic_truths(args.synthetic, 0, split)
    start = time.perf_counter()
    report: dict[str, Any] = {
        "command": "spine bench lateral-mirror " + " ".join(argv if argv is not None else sys.argv[1:]),
        "noise_sds": PROFILE_NOISE_SDS,
        "cases": list(LATERAL_CASES),
        "seeds": args.seeds,
        "noises_mm": list(NOISES_MM),
        "population": population(datasets),
        "sweep": sweep(datasets, args.seeds),
        "profiles": profiles(args.seeds),
    }
    if args.fits:
        report["fits"] = fits(datasets["verse-dev"])
    report["runtime_s"] = round(time.perf_counter() - start, 1)
    write_json(args.out / "lateral-mirror.json", report)
    for name, per_noise in report["sweep"].items():
        for noise, row in per_noise.items():
            print(
                f"{name:16s} {noise} mm: stated {row['stated']['refused_inverted']}/{row['stated']['payloads']} "
                f"refused (other {row['stated']['refused_other']}); mirrored labels "
                f"{row['detection_rate_labels']:.3f}, columns {row['detection_rate_columns']:.3f}"
            )
    print(f"wrote {args.out / 'lateral-mirror.json'}")
    false = sum(row["stated"]["refused_inverted"] for per in report["sweep"].values() for row in per.values())
    return 1 if false else 0
