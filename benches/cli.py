"""``spine bench ...``: the experiment and benchmark commands of the engine."""

from __future__ import annotations

import argparse
import importlib

COMMANDS = {
    "paper": ("benches.paper", "the paper's experiments on 30 synthetic spines"),
    "verse": ("benches.verse", "3D error on real spines from CT (VerSe)"),
    "perf": ("benches.perf", "time single 17-landmark fits"),
    "calibrate": ("benches.calibrate", "rest shape and Monte Carlo over Y, G, stretch (VerSe dev); --check"),
    "aasce": ("benches.aasce", "Cobb angles on real PA radiographs (AASCE 2019): corners, midpoints"),
    "noise-weight": ("benches.noise_weight", "prior strength, noisy landmarks (VerSe dev)"),
    "prior": ("benches.prior", "calibrate the population prior and check its prior predictive"),
    "clinic": ("benches.clinic", "the clinic's setting: 3D error and interval coverage"),
    "clinic-bound": (
        "benches.clinic_bound",
        "the clinic's setting: the error that an oracle knowing the shape cannot avoid",
    ),
    "recalibrate": (
        "benches.recalibrate",
        "re-run the calibrations that follow the engine (population prior, PA reading, tilt prior, uncertainty, "
        "Cobb SD)",
    ),
    "aasce-bound": (
        "benches.aasce_bound",
        "AASCE training: the major Cobb angle learners read from the endplate midpoints (cross-validated)",
    ),
    "pa-bound": (
        "benches.pa_bound",
        "one PA film: the kyphosis and lordosis a learner trained on the tested population reads",
    ),
    "pa-reading": (
        "benches.pa_reading",
        "one PA film: the kyphosis its foreshortening reads, fitted on VerSe dev (--write: ship it)",
    ),
    "lateral-mirror": (
        "benches.lateral_mirror",
        "lateral films read mirrored: the inverted-profile refusal's false refusals and detection",
    ),
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="spine bench", description=__doc__)
    described = "; ".join(f"{name}: {what}" for name, (_, what) in COMMANDS.items())
    parser.add_argument("command", choices=sorted(COMMANDS), help=described)
    parser.add_argument("args", nargs=argparse.REMAINDER)
    ns = parser.parse_args(argv)
    module = importlib.import_module(COMMANDS[ns.command][0])
    return int(module.main(ns.args))
