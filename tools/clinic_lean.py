"""Where case (a) of ``spine bench clinic`` loses its accuracy (docs/accuracy.md, "Where case (a)'s
error comes from"): case (a)'s payloads on VerSe dev, and the same with one missing input given
(the PA magnification, both projections, or T1/L5), reconstructed by ``register_model``; mean 3D
error after removing the translation, and the mean |error| per axis (x left, y posterior, z up).

``python -m tools.clinic_lean [noise_mm] [--data ../shared/data/verse]``
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from benches import clinic, clinic_films
from spine_engine.models import JobPayload
from spine_engine.reconstruction import register_model


def variants(series: clinic_films.Series) -> dict[str, dict[str, Any]]:
    """Case (a)'s payload and its variants, as JSON (the public payload)."""
    base = clinic_films.build_payload(series, clinic_films.CASES["a"]).model_dump(mode="json", exclude_none=True)
    paper = clinic_films.build_payload(series, clinic_films.CASES["f"]).model_dump(mode="json", exclude_none=True)
    magnification = {"magnification": clinic_films.SID_MM / clinic_films.PA_SOD_MM}
    with_magnification = {**base, "pa": {**base["pa"], "acquisition": magnification}}
    calibrated = {k: v for k, v in paper.items() if k != "boundary"}
    with_boundary = {**base, "boundary": paper["boundary"]}
    return {
        "(a) as sent": base,
        "(a) + PA magnification": with_magnification,
        "(a) + both projections": calibrated,
        "(a) + T1/L5 poses": with_boundary,
        "(f) paper's case": paper,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("noise_mm", type=float, nargs="?", default=1.0)
    parser.add_argument("--data", type=Path, default=None)
    args = parser.parse_args(argv)
    errors: dict[str, list[tuple[float, np.ndarray]]] = {}
    for truth in clinic.verse_truths("dev", args.data):
        series = clinic_films.simulate_series(truth, args.noise_mm, 0)
        t = truth.positions - truth.positions.mean(axis=0)
        for name, payload in variants(series).items():
            result = register_model(JobPayload.model_validate(payload))
            r = np.array([v.position for v in result.vertebrae])
            diff = (r - r.mean(axis=0)) - t
            errors.setdefault(name, []).append((float(np.linalg.norm(diff, axis=1).mean()), np.abs(diff).mean(axis=0)))
    print(f"VerSe dev, {args.noise_mm:g} mm landmark noise")
    for name, found in errors.items():
        axes = np.mean([a for _, a in found], axis=0)
        print(f"{name:26s} n={len(found)}  3D error {np.mean([e for e, _ in found]):.2f} mm  "
              f"|dx|,|dy|,|dz| {axes[0]:.2f}, {axes[1]:.2f}, {axes[2]:.2f} mm")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
