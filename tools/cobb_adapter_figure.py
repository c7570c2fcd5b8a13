"""The Cobb lines of a job's SR as OHIF's Cornerstone adapters read them, drawn for docs/dicom.md.

A synthetic PA film (``tools.dicom.synthetic``, 0.15 mm square pixels) with 17 endplate midpoints on
an S-curve (px, no boundary: the clinic's path), run by the engine; its SR (``services.dicom.sr``) is
read in Node by ``@cornerstonejs/adapters`` (``tools.sr_adapter``); the figure shows the landmarks and
the four points of each CobbAngle annotation the adapter returns (its image coordinates), labelled
with the angle it read. The SR is written too (``--sr``), for ``dsrdump``.

    python -m tools.cobb_adapter_figure --out docs/img/cobb-adapter.png --sr /tmp/cobb-sr.dcm
"""

from __future__ import annotations

import argparse
import math
import uuid
from pathlib import Path
from typing import Any

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from services.dicom.sr import SourceImage, StudyIdentity, build_sr
from spine_client.dicom.header import read_header
from spine_engine import register
from spine_engine.levels import LEVELS
from tools.dicom import synthetic
from tools.sr_adapter import adapter_missing, adapter_tool_state

SPACING = 0.15
JOB = uuid.UUID("5c0b7d1e-0d9a-4c1e-9a51-3f3e2b7c4a10")


def payload() -> dict[str, Any]:
    """17 PA endplate midpoints (px) on an S-curve: 22 mm to the right at T7, 14 mm to the left at L3."""
    landmarks = []
    for i, level in enumerate(LEVELS):
        t = i / (len(LEVELS) - 1)
        col_mm = 90.0 + 22.0 * math.sin(math.pi * t / 0.62) if t < 0.62 else 90.0 - 14.0 * math.sin(
            math.pi * (t - 0.62) / 0.38)  # fmt: skip
        row_mm = 60.0 + 430.0 * t
        landmarks.append({"level": level, "point": [round(col_mm / SPACING, 2), round(row_mm / SPACING, 2)]})
    return {"pa": {"units": "px", "pixel_spacing": [SPACING, SPACING], "landmarks": landmarks}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.cobb_adapter_figure", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/img/cobb-adapter.png"))
    parser.add_argument("--sr", type=Path, default=Path("/tmp/cobb-sr.dcm"))
    args = parser.parse_args(argv)
    reason = adapter_missing()
    if reason:
        parser.error(reason)
    film = synthetic.radiograph(imager_pixel_spacing=(SPACING, SPACING), rows=3600, columns=1400)
    header = read_header(film)
    job = payload()
    result = register(job)
    source = SourceImage(header.sop_instance_uid, str(header.sop_class_uid), header.series_instance_uid,
                         header.study_instance_uid, pixel_spacing=(SPACING, SPACING))  # fmt: skip
    sr = build_sr(result, job, JOB, StudyIdentity(study_instance_uid=header.study_instance_uid), {"pa": source})
    sr.save_as(args.sr, enforce_file_format=True)
    state = adapter_tool_state(args.sr, header.sop_instance_uid, (SPACING, SPACING))

    fig = Figure(figsize=(3.4, 6.0), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    points = [lm["point"] for lm in job["pa"]["landmarks"]]
    ax.plot([p[0] for p in points], [p[1] for p in points], "o", color="0.3", markersize=3, label="PA landmarks")
    for read, curve in zip(state["CobbAngle"], result["measures"]["cobb"], strict=True):
        p = read["imagePoints"]
        for a, b in ((p[0], p[1]), (p[2], p[3])):
            ax.plot([a[0], b[0]], [a[1], b[1]], "-", color="crimson", linewidth=1.6)
        ax.annotate(f"{curve['upper']}–{curve['lower']}: {read['angle']:.1f}°", xy=(p[1][0], (p[1][1] + p[3][1]) / 2),
                    xytext=(6, 0), textcoords="offset points", fontsize=8, color="crimson", va="center")  # fmt: skip
    ax.plot([], [], "-", color="crimson", label="CobbAngle (adapter)")
    ax.set_xlim(200, 1200)
    ax.set_ylim(3500, 200)
    ax.set_aspect("equal")
    ax.set_xlabel("column (px)", fontsize=8)
    ax.set_ylabel("row (px)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.legend(loc="lower left", fontsize=7, frameon=False)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, metadata={"Software": None})
    for read, curve in zip(state["CobbAngle"], result["measures"]["cobb"], strict=True):
        print(f"{curve['upper']}-{curve['lower']}: SR {curve['angle_deg']:.3f} deg, adapter {read['angle']:.3f} deg, "
              f"image points {[[round(c, 1) for c in q] for q in read['imagePoints']]}")  # fmt: skip
    print(f"adapter tools: {state['tools']}; groups without a tool: {state['skipped']}; wrote {args.out}, {args.sr}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
