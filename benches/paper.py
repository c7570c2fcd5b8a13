"""The experiments of Li et al. (CAIP 2009), reproduced on synthetic scoliotic spines.

30 synthetic spines (built geometrically by ``spine_engine.synthetic``, not by the registration
they test), T1 and L5 given, PA landmarks on 2..17 levels, and the 17 PA + 17 lateral case.
Per case: mean 3D reconstruction error over T2..L4 (mm), bending and twisting errors (mean
absolute error of the per-segment rotation angles, degrees) and the mean 2D registration error.
The paper reports 2.114 mm at PA-17 and a lower bound of about 1 mm.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from benches.report import format_table, save_figure, subplots, write_json
from benches.truth import errors, landmark_subset, payload_from_truth
from spine_engine.errors import FitFailed
from spine_engine.levels import N_LEVELS
from spine_engine.reconstruction import register
from spine_engine.synthetic import generate_spines

PAPER_PA17_MM = 2.114
PAPER_LOWER_BOUND_MM = 1.0


def cases() -> list[tuple[str, list[int], list[int] | None]]:
    """(name, PA level indices, lateral level indices) of every case of the experiment."""
    out: list[tuple[str, list[int], list[int] | None]] = [
        (f"PA-{k}", landmark_subset(k), None) for k in range(2, N_LEVELS + 1)
    ]
    out.append(("PA-17+L-17", list(range(N_LEVELS)), list(range(N_LEVELS))))
    return out


def run(n_spines: int, seed: int, noise_mm: float, profile: str) -> list[dict[str, Any]]:
    """Every case on every synthetic spine; one summary row per case."""
    spines = generate_spines(n_spines, seed=seed)
    rng = np.random.default_rng(seed)
    rows = []
    for name, pa_levels, lateral_levels in cases():
        err3d, bend, twist, reg, fails, ms = [], [], [], [], 0, []
        for spine in spines:
            payload = payload_from_truth(
                spine.positions, spine.rotations, pa_levels, lateral_levels, noise_mm=noise_mm, rng=rng
            )
            payload["options"] = {"profile": profile}
            try:
                result = register(payload)
            except FitFailed:
                fails += 1
                continue
            e = errors(result, spine.positions, spine.rotations)
            err3d.append(e.mean_interior_mm)
            bend.append(e.bending_deg)
            twist.append(e.twist_deg)
            reg.append(result["fit"]["mean_registration_error_mm"])
            ms.append(result["fit"]["runtime_ms"])
        rows.append(
            {
                "case": name,
                "pa_landmarks": len(pa_levels),
                "lateral_landmarks": len(lateral_levels or []),
                "mean_3d_error_mm": float(np.mean(err3d)) if err3d else float("nan"),
                "sd_3d_error_mm": float(np.std(err3d)) if err3d else float("nan"),
                "bending_error_deg": float(np.mean(bend)) if bend else float("nan"),
                "twisting_error_deg": float(np.mean(twist)) if twist else float("nan"),
                "mean_registration_error_mm": float(np.mean(reg)) if reg else float("nan"),
                "median_fit_ms": float(np.median(ms)) if ms else float("nan"),
                "failed_fits": fails,
            }
        )
    return rows


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    """Error against the number of PA landmarks, like the paper's Fig. 3."""
    pa = [r for r in rows if r["lateral_landmarks"] == 0]
    both = [r for r in rows if r["lateral_landmarks"] > 0]
    x = [r["pa_landmarks"] for r in pa]
    fig, axes = subplots(1, 2, figsize=(10, 4))
    axes[0].plot(x, [r["mean_3d_error_mm"] for r in pa], "o-", label="this engine, PA only")
    for r in both:
        axes[0].plot([17], [r["mean_3d_error_mm"]], "s", label="this engine, PA-17 + lateral-17")
    axes[0].plot([17], [PAPER_PA17_MM], "*", markersize=12, label="Li et al. 2009, PA-17")
    axes[0].axhline(PAPER_LOWER_BOUND_MM, ls="--", c="gray", label="paper's lower bound (1 mm)")
    axes[0].set(xlabel="PA landmarks", ylabel="mean 3D error, T2–L4 (mm)", title="3D reconstruction error")
    axes[0].legend(fontsize=8)
    axes[1].plot(x, [r["bending_error_deg"] for r in pa], "o-", label="bending")
    axes[1].plot(x, [r["twisting_error_deg"] for r in pa], "s-", label="twisting")
    axes[1].set(xlabel="PA landmarks", ylabel="mean abs. error per segment (deg)", title="Strain errors")
    axes[1].legend(fontsize=8)
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="spine bench paper", description=__doc__.splitlines()[0])
    parser.add_argument("--spines", type=int, default=30)
    parser.add_argument("--seed", type=int, default=2009)
    parser.add_argument("--noise-mm", type=float, default=0.0, help="landmark noise SD, detector mm")
    parser.add_argument("--profile", default="default")
    parser.add_argument("--out", type=Path, default=Path("bench-out/paper"))
    args = parser.parse_args(argv)
    start = time.perf_counter()
    rows = run(args.spines, args.seed, args.noise_mm, args.profile)
    columns = list(rows[0].keys())
    print(format_table(columns, [[r[c] for c in columns] for r in rows]))
    print(f"paper (Li et al. 2009): {PAPER_PA17_MM} mm at PA-17, lower bound {PAPER_LOWER_BOUND_MM} mm")
    write_json(args.out / "paper.json", {"args": {k: str(v) for k, v in vars(args).items()}, "rows": rows})
    plot(rows, args.out / "paper.png")
    print(f"wrote {args.out / 'paper.json'} and {args.out / 'paper.png'} in {time.perf_counter() - start:.1f} s")
    return 1 if any(r["failed_fits"] for r in rows) else 0
