"""``spine bench pa-reading``: the kyphosis one PA film's foreshortening reads, fitted on VerSe dev.

The reading (``spine_engine.sagittal_reading``) needs the population's chord shares λ, mean chord
inclinations μ, the first ``MODES`` principal modes of the inclinations about each spine's mean with
their SDs, the SD of a spine's mean inclination (the lean δ) and of its chords' log lengths about
their shares: all read on the 24 VerSe dev spines (``fit_model``).

Its share w in the film's value of a PA-only kyphosis (w·K_PA + (1 − w)·K_rod) is chosen on the grid
``WEIGHTS`` by the clinic bench's PA-only case (e) at 1 mm of noise (seed 0) on both tuning sets:
VerSe dev (each spine read with the model of the other 23) and the clinic bench's 20 synthetic dev
spines, which unlike VerSe's have scoliotic frontal curves. Each value is offset by the median of
truth − value on VerSe dev (as ``fit.uncertainty.PriorOnlyReading`` reports it), and w minimises the
mean over the two sets of the MAE over the floor's (the VerSe dev mean for every spine). The truths'
kyphoses are measured as the clinic bench measures them.

``--write`` writes the model into ``spine_engine/priors/sagittal_reading.json`` with its provenance;
the uncertainty constants read the film's value, so ``spine bench clinic --split dev
--calibrate-uncertainty`` follows (``spine bench recalibrate`` runs both in order).
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from benches.clinic import synthetic_truths, truths_of_csv
from benches.clinic_films import CASES, Truth, build_payload, centreline_measures, simulate_series
from benches.report import format_table, shared_data_dir, write_json
from spine_engine.anatomy import load_profile
from spine_engine.reconstruction import fit_patient_rod, pa_foreshortening_kyphoses, prepare_inputs, rod_measures
from spine_engine.sagittal_reading import ReadingModel, chord_inclinations_deg, write_reading_model
from spine_engine.validation import validate_payload

MODES = 2
"""Principal modes of the inclinations the reading fits: the least mean ratio of ``weight_table`` at its
best w among one, two and three modes (0.831, 0.824 and 0.852; ``--modes K``)."""
WEIGHTS = tuple(np.round(np.linspace(0.0, 1.0, 11), 2))
"""The grid of w."""
BY_COBB_SEED = 1000
"""Seed of ``--by-cobb``'s synthetic spines (with the dev split's offset): others than the 20 the weight is
chosen on."""
NOISE_MM = 1.0
"""Landmark noise of the films the weight is chosen on (the clinic bench's)."""


def fit_model(truths: Sequence[Truth], weight: float = 0.0, modes: int = MODES) -> ReadingModel:
    """The reading's population numbers from ``truths`` (module docstring); ``weight`` is stored as is."""
    positions = np.array([t.positions for t in truths])
    lengths = np.linalg.norm(np.diff(positions, axis=1), axis=2)
    shares = lengths / lengths.sum(axis=1, keepdims=True)
    share = shares.mean(axis=0)
    beta = np.array([chord_inclinations_deg(p) for p in positions])
    mu = beta.mean(axis=0)
    lean = (beta - mu).mean(axis=1)
    about_mean = beta - beta.mean(axis=1, keepdims=True)
    centred = about_mean - about_mean.mean(axis=0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    vt *= np.sign(vt[np.arange(len(vt)), np.argmax(np.abs(vt), axis=1)])[:, None]  # a mode's largest entry > 0
    return ReadingModel(
        chord_share=share,
        mean_inclination_deg=mu,
        modes=vt[:modes],
        mode_sd_deg=s[:modes] / np.sqrt(len(truths) - 1),
        lean_sd_deg=float(lean.std(ddof=1)),
        length_sd=float(np.log(shares / share).std(ddof=1)),
        weight=weight,
        provenance={},
    )


def truth_kyphosis(truth: Truth) -> float:
    """Kyphosis T4–T12 of a truth as the clinic bench measures it (its centreline frames), degrees."""
    return float(centreline_measures(truth.positions).thoracic_kyphosis_t4_t12_deg)


def readings(truths: Sequence[Truth], models: Sequence[ReadingModel]) -> np.ndarray:
    """(n, 3): per spine, the PA film's foreshortening reading with its model, the fitted rod's
    reading and the truth, kyphosis T4–T12 in degrees, on case (e)'s film (``NOISE_MM``, seed 0)."""
    profile = load_profile()
    rows = []
    for truth, model in zip(truths, models, strict=True):
        series = simulate_series(truth, NOISE_MM, 0)
        payload = validate_payload(build_payload(series, CASES["e"]).model_dump(mode="json", exclude_none=True))
        inputs = prepare_inputs(payload, profile)
        solution, _ = fit_patient_rod(inputs, profile)
        read = pa_foreshortening_kyphoses(inputs, solution.output, model)
        assert read is not None, truth.spine_id  # 17 PA landmarks
        rod = rod_measures(inputs, solution.output).thoracic_kyphosis_t4_t12_deg
        rows.append((read[0], rod, truth_kyphosis(truth)))
    return np.array(rows)


def weight_table(verse: np.ndarray, synthetic: np.ndarray) -> list[dict[str, Any]]:
    """Per w of ``WEIGHTS``: the offset (VerSe dev's median of truth − value) and each set's MAE and
    its ratio to the floor's (``readings`` rows)."""
    mean = verse[:, 2].mean()
    rows = []
    for w in WEIGHTS:
        offset = float(np.median(verse[:, 2] - (w * verse[:, 0] + (1 - w) * verse[:, 1])))
        row: dict[str, Any] = {"weight": float(w), "offset_deg": offset}
        for name, data in (("verse_dev", verse), ("synthetic_dev", synthetic)):
            value = w * data[:, 0] + (1 - w) * data[:, 1] + offset
            mae = float(np.mean(np.abs(value - data[:, 2])))
            floor = float(np.mean(np.abs(mean - data[:, 2])))
            row[name] = {"mae_deg": mae, "floor_mae_deg": floor, "ratio": mae / floor}
        row["mean_ratio"] = 0.5 * (row["verse_dev"]["ratio"] + row["synthetic_dev"]["ratio"])
        rows.append(row)
    return rows


def chosen_weight(rows: Sequence[dict[str, Any]]) -> float:
    """The w of the least mean ratio (the first of equal ones)."""
    return float(min(rows, key=lambda r: r["mean_ratio"])["weight"])


def calibrate(
    verse_dev: Sequence[Truth], synthetic_dev: Sequence[Truth], modes: int = MODES
) -> tuple[ReadingModel, list[dict[str, Any]]]:
    """The model of all VerSe dev spines with the chosen w, and the weight table."""
    leave_one_out = [fit_model([u for j, u in enumerate(verse_dev) if j != k], modes=modes)
                     for k in range(len(verse_dev))]  # fmt: skip
    full = fit_model(verse_dev, modes=modes)
    rows = weight_table(readings(verse_dev, leave_one_out), readings(synthetic_dev, [full] * len(synthetic_dev)))
    return fit_model(verse_dev, chosen_weight(rows), modes), rows


COBB_BANDS_DEG = ((10.0, 25.0), (25.0, 45.0), (45.0, 90.0))
"""Bands of the major frontal Cobb angle of ``by_cobb``'s table."""


def major_cobb(truth: Truth) -> float:
    """The major frontal Cobb angle of a truth on its centreline frames (0 without a curve), degrees."""
    cobb = centreline_measures(truth.positions).cobb
    return float(max((c.angle_deg for c in cobb), default=0.0))


def by_cobb(truths: Sequence[Truth], model: ReadingModel) -> list[dict[str, Any]]:
    """Per band of the major Cobb angle (``COBB_BANDS_DEG``), over ``truths``: the Pearson correlation of
    the film's and the rod's readings with the truth and their MAE after each one's median offset
    (kyphosis T4–T12, case (e)'s film, ``readings``)."""
    data = readings(truths, [model] * len(truths))
    angles = np.array([major_cobb(t) for t in truths])
    rows = []
    for low, high in COBB_BANDS_DEG:
        band = data[(angles >= low) & (angles < high)]
        row: dict[str, Any] = {"major_cobb_deg": [low, high], "spines": len(band)}
        for name, column in (("film", 0), ("rod", 1)):
            error = band[:, column] + np.median(band[:, 2] - band[:, column]) - band[:, 2]
            row[name] = {"correlation": float(np.corrcoef(band[:, column], band[:, 2])[0, 1]),
                         "mae_deg": float(np.mean(np.abs(error)))}
        rows.append(row)
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="spine bench pa-reading", description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=shared_data_dir("verse"), help="VerSe folder with dev.csv")
    parser.add_argument("--synthetic", type=int, default=20, help="synthetic dev spines (the clinic bench's)")
    parser.add_argument("--write", action="store_true", help="write the model into spine_engine/priors")
    parser.add_argument("--out", type=Path, default=Path("docs/figures"), help="folder of the JSON")
    parser.add_argument("--modes", type=int, default=MODES, help=f"principal modes fitted (default {MODES})")
    parser.add_argument("--by-cobb", type=int, default=0, metavar="N",
                        help="also read N other synthetic dev spines and tabulate both readings by major Cobb angle")
    ns = parser.parse_args(argv)
    verse = truths_of_csv(ns.data / "dev.csv")
    synthetic = synthetic_truths(ns.synthetic, 0, "dev")
    if ns.write and ns.modes != MODES:
        parser.error(f"--write ships the reading of {MODES} modes (MODES)")
    model, rows = calibrate(verse, synthetic, ns.modes)
    print(format_table(
        ["w", "offset (deg)", "VerSe dev MAE / floor", "synthetic dev MAE / floor", "mean ratio"],
        [[r["weight"], round(r["offset_deg"], 2),
          f"{r['verse_dev']['mae_deg']:.2f} / {r['verse_dev']['floor_mae_deg']:.2f} = {r['verse_dev']['ratio']:.3f}",
          f"{r['synthetic_dev']['mae_deg']:.2f} / {r['synthetic_dev']['floor_mae_deg']:.2f} = "
          f"{r['synthetic_dev']['ratio']:.3f}", round(r["mean_ratio"], 3)] for r in rows],
    ))  # fmt: skip
    command = "spine bench pa-reading " + " ".join(argv if argv is not None else sys.argv[2:])
    record: dict[str, Any] = {"command": command, "modes": ns.modes, "weight": model.weight, "rows": rows}
    if ns.by_cobb:
        others = synthetic_truths(ns.by_cobb, BY_COBB_SEED, "dev")
        record["by_cobb"] = by_cobb(others, model)
        print(format_table(
            ["major Cobb (deg)", "spines", "film's r", "rod's r", "film's MAE", "rod's MAE"],
            [[f"{r['major_cobb_deg'][0]:g}-{r['major_cobb_deg'][1]:g}", r["spines"], round(r["film"]["correlation"], 2),
              round(r["rod"]["correlation"], 2), round(r["film"]["mae_deg"], 2), round(r["rod"]["mae_deg"], 2)]
             for r in record["by_cobb"]],
        ))  # fmt: skip
    write_json(ns.out / "pa-reading.json", record)
    print(f"w = {model.weight:g}; wrote {ns.out / 'pa-reading.json'}")
    if ns.write:
        provenance = {
            "method": (__doc__ or "").split("\n\n")[1].replace("\n", " "),
            "command": command,
            "training_set": f"VerSe dev ({len(verse)} spines, dev.csv); the weight also on the clinic bench's "
                            f"{len(synthetic)} synthetic dev spines",
            "date": dt.date.today().isoformat(),
            "weight_table": rows,
        }
        path = write_reading_model(replace(model, provenance=provenance))
        print(f"wrote {path}")
    return 0
