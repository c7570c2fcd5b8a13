"""``spine bench recalibrate``: re-run, in order, the calibrations that follow the engine.

Each shipped calibration is computed through the engine, so a change to the engine can leave it
describing an engine that no longer exists; ``tests/benches/test_shipped_calibrations.py`` fails
until this command is re-run. The order is the chain of what each step reads (tuning splits only:
VerSe dev, AASCE training):

1. the rod's population prior (``spine bench prior --write default``): VerSe dev and AASCE
   training's spreads, scaled by the prior predictive;
2. the PA film's kyphosis reading (``spine bench pa-reading --write``): VerSe dev's chord shares,
   inclinations and modes, and its weight chosen through the fits of 1;
3. the tilt prior (``spine bench aasce --calibrate``): its coefficients, and its weight fraction
   chosen through ``register()``, which fits with the prior of 1;
4. the uncertainty constants (``spine bench clinic --split dev --calibrate-uncertainty``): λ and c
   from the fits of 1 and 3, and the PA-only readings, of 2;
5. the tilt prior's ``cobb_sd_deg`` (``spine bench aasce --calibrate-cobb-sd``): from the reported
   Cobb SD, which holds λ and c of 4 (step 3 also sets it, before 4 has moved them).

Upstream of these, the rest shape and the stretch stiffness (``spine bench calibrate``) and the
landmark weight (``spine bench noise-weight``) were chosen once by searches and are kept
(docs/engine.md); the test checks that the rest shape is VerSe dev's mean and that the weight is
still the best of ``noise-weight``'s grid (``spine bench calibrate --check`` shows where the
stretch factor sits).

Exit code 0 when every step ran; the prior predictive's bands are printed by step 1, whose sagittal
SDs are wider than the population's by design (docs/accuracy.md).
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence
from pathlib import Path

from benches import aasce, clinic, pa_reading, prior
from benches.report import shared_data_dir


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="spine bench recalibrate", description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--verse", type=Path, default=shared_data_dir("verse"), help="VerSe folder with dev.csv")
    parser.add_argument("--aasce", type=Path, default=shared_data_dir("aasce2019"),
                        help="AASCE 2019 folder with training/")
    parser.add_argument("--out", type=Path, default=Path("bench-out/recalibrate"), help="folder of the steps' output")
    ns = parser.parse_args(argv)
    ns.verse, ns.aasce = Path(os.path.relpath(ns.verse)), Path(os.path.relpath(ns.aasce))  # as provenance shows them
    if not (ns.verse / "dev.csv").is_file() or not (ns.aasce / "training").is_dir():
        print(f"error: tuning data not found ({ns.verse}/dev.csv, {ns.aasce}/training); pass --verse and --aasce")
        return 2
    print("== 1. population prior")
    prior.main(["--write", "default", "--verse", str(ns.verse / "dev.csv"), "--aasce", str(ns.aasce / "training"),
                "--out", str(ns.out)])  # its exit code reports the bands, not the write
    steps: list[tuple[str, int]] = []
    print("== 2. PA film's kyphosis reading")
    steps.append(("pa reading", pa_reading.main(["--write", "--data", str(ns.verse), "--out", str(ns.out)])))
    print("== 3. tilt prior")
    steps.append(("tilt prior", aasce.main(["--calibrate", "--split", "training", "--data", str(ns.aasce),
                                            "--out", str(ns.out)])))
    print("== 4. uncertainty constants")
    steps.append(("uncertainty", clinic.main(["--split", "dev", "--calibrate-uncertainty", "--data", str(ns.verse)])))
    print("== 5. Cobb SD of model tilts")
    steps.append(("cobb sd", aasce.main(["--calibrate-cobb-sd", "--split", "training", "--data", str(ns.aasce),
                                         "--out", str(ns.out)])))
    failed = [name for name, code in steps if code != 0]
    print("recalibrated: population prior, PA reading, tilt prior, uncertainty constants, Cobb SD" if not failed
          else f"error: {', '.join(failed)} did not finish")
    return 1 if failed else 0
