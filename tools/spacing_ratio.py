"""The threshold of the page's skipped-vertebra warning (web/src/checks.ts ``SKIP_RATIO``), derived on data.

A clinician who skips a vertebra on the film (clicks T8's body as "T7") leaves one gap between consecutive
labels about twice its neighbours', and every label below it one level off. The page warns when a gap is more
than ``SKIP_RATIO`` times its neighbours'. Here the ratio is measured on real spines and on the same spines
with one vertebra dropped and the rest relabelled:

- points: top endplate midpoints (the mean of the top-left and top-right corners; what the page has for a
  midpoint or four corners) of AASCE 2019 **training** PA radiographs (px; a radiograph whose midpoints do not
  run down the image in level order is left out, as the page refuses such landmarks), and the body centroids
  of VerSe **dev** spines (mm) in their frontal (x, z) and lateral (y, z) projections;
- gap i, between consecutive placed levels a < b: the distance along the landmark chain
  ``‖p_b − p_a‖ / (b − a)`` (per level spanned; mm on the page, px on AASCE, isotropic);
- ratio_i = gap_i / median(the up to ``NEIGHBOURS`` gaps on each side of gap i), judged with at least
  ``MIN_NEIGHBOURS`` of them (four placed levels);
- a skip: drop interior level d (T2..L4; a dropped T1 or L5 leaves no gap, only the "started one level off"
  the page's relabel buttons mend) and relabel; its ratio is the one of the gap across d.

The threshold is the smallest multiple of ``STEP`` above every real film's largest ratio once the
``OUTLIERS`` largest films are left out (printed with their gap, so the reason can be checked).
``python -m tools.spacing_ratio [--aasce DIR] [--verse FILE] [--out FILE]`` prints the figures, and the JSON
(to stdout, or to ``--out``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from benches.aasce import read_split
from benches.report import shared_data_dir
from benches.truth import read_verse
from spine_engine.levels import LEVELS
from spine_engine.validation import SPACING_RATIO, spacing_ratios

NEIGHBOURS = 2
"""Gaps on each side of a gap whose median it is compared with (checks.ts ``SKIP_NEIGHBOURS``)."""
MIN_NEIGHBOURS = 2
"""A gap is judged only against at least this many neighbouring gaps (checks.ts ``SKIP_MIN_NEIGHBOURS``)."""
OUTLIERS = 1
"""Films with the largest real ratios left out of the threshold: AASCE training's
sunhl-1th-11-Jan-2017-254 L (T1–T2, 1.89), whose T1 corners are misplaced (T1's left side drawn 125 px
tall over a 60 px T2); the next film's largest ratio is 1.71."""
STEP = 0.05
"""The threshold is rounded up to a multiple of this."""
CANDIDATES = (1.5, 1.6, 1.65, 1.7, 1.75, 1.8, 1.85, 1.9, 2.0)


def ratios(points: np.ndarray, levels: Sequence[int]) -> np.ndarray:
    """Ratio of each gap between consecutive placed levels (``levels``: their indices 0 = T1 … 16 = L5,
    increasing; ``points``: (n, 2) in one isotropic unit) to the median of its up to NEIGHBOURS neighbouring
    gaps on each side, a gap being the chain distance per level spanned; NaN where fewer than
    MIN_NEIGHBOURS neighbours exist."""
    steps = np.diff(np.asarray(levels))
    gaps = np.linalg.norm(np.diff(points, axis=0), axis=1) / steps
    out = np.full(len(gaps), np.nan)
    for i in range(len(gaps)):
        near = [gaps[j] for j in range(i - NEIGHBOURS, i + NEIGHBOURS + 1) if j != i and 0 <= j < len(gaps)]
        if len(near) >= MIN_NEIGHBOURS:
            out[i] = gaps[i] / float(np.median(near))
    return out


def skip_ratios(points: np.ndarray) -> np.ndarray:
    """For each interior level d of a 17-level spine: the ratio of the gap across d once d is dropped and the
    levels below it relabelled one up (the clinician's skip)."""
    out = []
    for d in range(1, len(points) - 1):
        kept = np.delete(points, d, axis=0)
        out.append(ratios(kept, range(len(kept)))[d - 1])
    return np.asarray(out)


def films(aasce: Path, verse: Path) -> tuple[list[dict[str, Any]], int]:
    """The films: {name, source, points (17, 2)}; and how many AASCE radiographs were left out (out of order)."""
    out: list[dict[str, Any]] = []
    left_out = 0
    for rad in read_split(aasce):
        top = 0.5 * (rad.corners[:, 0] + rad.corners[:, 1])
        if not np.all(np.diff(top[:, 1]) > 0):
            left_out += 1
            continue
        out.append({"name": rad.name, "source": "aasce-training", "points": top})
    for spine_id, p in read_verse(verse):
        out.append({"name": f"{spine_id} frontal", "source": "verse-dev-frontal", "points": p[:, [0, 2]]})
        out.append({"name": f"{spine_id} lateral", "source": "verse-dev-lateral", "points": p[:, [1, 2]]})
    return out, left_out


def derive(aasce: Path, verse: Path) -> dict[str, Any]:
    """The figures: real films' largest ratios, the threshold, and its false-warning and detection rates."""
    rows, left_out = films(aasce, verse)
    real = np.asarray([np.nanmax(ratios(f["points"], range(len(LEVELS)))) for f in rows])
    where = [int(np.nanargmax(ratios(f["points"], range(len(LEVELS))))) for f in rows]
    skips = np.asarray([skip_ratios(f["points"]) for f in rows])  # (films, 15)
    order = np.argsort(real)[::-1]
    kept = np.sort(real)[: len(real) - OUTLIERS]
    threshold = round(math.floor(kept.max() / STEP + 1) * STEP, 10)
    sources = sorted({f["source"] for f in rows})

    def rates(t: float, pick: np.ndarray) -> dict[str, float]:
        return {"false_warning": float(np.mean(real[pick] > t)), "detection": float(np.mean(skips[pick] > t))}

    everyone = np.ones(len(rows), bool)
    by_source = {s: np.asarray([f["source"] == s for f in rows]) for s in sources}
    return {
        "definition": {
            "points": "top endplate midpoints (AASCE), body centroids (VerSe)",
            "gap": "chain distance per level spanned",
            "neighbours_each_side": NEIGHBOURS,
            "min_neighbours": MIN_NEIGHBOURS,
            "statistic": "median",
        },
        "films": {s: int(m.sum()) for s, m in by_source.items()},
        "aasce_left_out_out_of_order": left_out,
        "largest_real": [
            {
                "film": rows[i]["name"],
                "gap": f"{LEVELS[where[i]]}–{LEVELS[where[i] + 1]}",
                "ratio": round(float(real[i]), 3),
            }
            for i in order[:8]
        ],
        "real_percentiles": {str(q): round(float(np.percentile(real, q)), 3) for q in (50, 90, 99, 99.5)},
        "outliers_left_out": OUTLIERS,
        "threshold": threshold,
        "at_threshold": {
            "all": rates(threshold, everyone),
            **{s: rates(threshold, m) for s, m in by_source.items()},
            "detection_by_dropped_level": {
                LEVELS[d + 1]: round(float(np.mean(skips[:, d] > threshold)), 3) for d in range(skips.shape[1])
            },
            "films_with_every_skip_detected": float(np.mean(np.all(skips > threshold, axis=1))),
            "films_with_most_skips_detected": float(np.mean(np.mean(skips > threshold, axis=1) > 0.5)),
        },
        "skip_percentiles": {str(q): round(float(np.nanpercentile(skips, q)), 3) for q in (1, 5, 10, 50)},
        "candidates": {str(t): rates(t, everyone) for t in CANDIDATES},
        "service_lower_bound": service_lower_bound(rows),
    }


def service_lower_bound(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The service's lower scale-free bound (``validation.SPACING_RATIO``, against the neighbours'
    spacing) on the same films: their lowest ratios, with the ratio against the view's median beside
    (two labels on one vertebra among AASCE's annotations read lowest)."""
    found = []
    for f in rows:
        pairs = spacing_ratios(list(range(len(LEVELS))), [tuple(p) for p in f["points"]])
        k = int(np.argmin([local for _, local in pairs]))
        median, local = pairs[k]
        found.append({"film": f["name"], "gap": f"{LEVELS[k]}–{LEVELS[k + 1]}",
                      "against_neighbours": round(local, 3), "against_view_median": round(median, 3)})  # fmt: skip
    found.sort(key=lambda r: r["against_neighbours"])
    return {"bound": SPACING_RATIO[0], "lowest": found[:8]}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--aasce", type=Path, default=shared_data_dir("aasce2019") / "training",
                        help="AASCE 2019 training folder (never test)")  # fmt: skip
    parser.add_argument("--verse", type=Path, default=shared_data_dir("verse") / "dev.csv",
                        help="VerSe dev CSV (never test)")  # fmt: skip
    parser.add_argument("--out", type=Path, help="write the JSON here instead of stdout")
    ns = parser.parse_args(argv)
    figures = derive(ns.aasce, ns.verse)
    say = sys.stderr if ns.out is None else sys.stdout
    print(f"films: {figures['films']}; AASCE training left out (levels out of order): "
          f"{figures['aasce_left_out_out_of_order']}", file=say)  # fmt: skip
    print(
        "largest real ratios: "
        + ", ".join(f"{r['film']} {r['gap']} {r['ratio']:.2f}" for r in figures["largest_real"]),
        file=say,
    )
    print(f"real films' largest ratio, percentiles: {figures['real_percentiles']}", file=say)
    at = figures["at_threshold"]
    print(f"threshold {figures['threshold']} (above every film but the {OUTLIERS} largest): false warnings "
          f"{at['all']['false_warning']:.1%} of films, skips detected {at['all']['detection']:.1%}",
          file=say)  # fmt: skip
    for s in figures["films"]:
        print(f"  {s}: false warnings {at[s]['false_warning']:.1%}, skips detected {at[s]['detection']:.1%}", file=say)
    print(f"  detection by dropped level: {at['detection_by_dropped_level']}", file=say)
    print(f"  films with every skip detected {at['films_with_every_skip_detected']:.1%}, with most "
          f"{at['films_with_most_skips_detected']:.1%}", file=say)  # fmt: skip
    print(f"skip ratio percentiles: {figures['skip_percentiles']}", file=say)
    for t, r in figures["candidates"].items():
        print(f"  at {t}: false warnings {r['false_warning']:.1%}, skips detected {r['detection']:.1%}", file=say)
    lower = figures["service_lower_bound"]
    print(f"service's lower bound {lower['bound']} (against the neighbours' spacing), lowest films: "
          + ", ".join(f"{r['film']} {r['gap']} {r['against_neighbours']:.2f} ({r['against_view_median']:.2f} of the "
                      "view's median)" for r in lower["lowest"]), file=say)  # fmt: skip
    text = json.dumps(figures, indent=2) + "\n"
    if ns.out is None:
        sys.stdout.write(text)
    else:
        ns.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
