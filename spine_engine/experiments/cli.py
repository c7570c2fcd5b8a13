"""``spine bench ...``: the experiment and benchmark commands of the engine."""

from __future__ import annotations

import argparse
import importlib

COMMANDS = {
    "paper": ("spine_engine.experiments.paper", "the paper's experiments on 30 synthetic spines"),
    "verse": ("spine_engine.experiments.verse", "3D error on real spines from CT (VerSe)"),
    "perf": ("spine_engine.experiments.perf", "time single 17-landmark fits"),
    "calibrate": ("spine_engine.experiments.calibrate", "Monte Carlo calibration of Y and G on VerSe dev"),
    "aasce": ("spine_engine.experiments.aasce", "Cobb angles on real PA radiographs (AASCE 2019): corners, midpoints"),
    "noise-weight": ("spine_engine.experiments.noise_weight", "prior strength, noisy landmarks (VerSe dev)"),
    "prior": ("spine_engine.experiments.prior", "calibrate the population prior and check its prior predictive"),
    "clinic": ("spine_engine.experiments.clinic", "the clinic's setting (issue #10): 3D error and interval coverage"),
    "clinic-bound": (
        "spine_engine.experiments.clinic_bound",
        "the clinic's setting: the error that an oracle knowing the shape cannot avoid",
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
