"""The drawing of a reconstruction's figure with matplotlib (Agg; no pyplot state, so it is safe in
threads): what ``figures.render_figure`` hands it, drawn into four panels and saved as PNG or SVG.

Kept apart from ``figures`` so that a process imports matplotlib only when it draws a figure: the
API and the worker import ``figures`` at start, and matplotlib was a fifth of their import time.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from matplotlib import colormaps, rc_context
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure

from .levels import LEVEL_INDEX, LEVELS, apex_words
from .projection import Projector

BODY_WIDTH = 1.4
"""Drawn vertebral body width, as a multiple of the segment length (about 36 mm for 26 mm)."""
BODY_HEIGHT = 0.7
"""Drawn vertebral body height along d3, as a multiple of the segment length."""
BENDING_CMAP = "coolwarm"


@dataclass(frozen=True)
class DrawnView:
    """One image panel: its title, the projection of patient points (..., 3), mm, onto it (..., 2),
    detector mm, and the landmarks drawn with their residual lines (level, detector mm)."""

    title: str
    projector: Projector
    landmarks: list[tuple[str, np.ndarray]]


def bending_norm(values: Sequence[float | None]) -> Normalize:
    """Symmetric colour scale of the frontal bending angles (at least ±1°)."""
    finite = [abs(v) for v in values if v is not None]
    limit = max([1.0, *finite])
    return Normalize(vmin=-limit, vmax=limit)


def _segment_lengths(positions: np.ndarray) -> np.ndarray:
    gaps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    return np.append(gaps, gaps[-1] if gaps.size else 25.0)


def _bodies(positions: np.ndarray, directors: np.ndarray, across: int) -> np.ndarray:
    """(n, 4, 3) corners of each vertebra's box: width along d1 (across=0) or d2 (across=1)."""
    seg = _segment_lengths(positions)
    a = directors[:, across, :] * (BODY_WIDTH * seg / 2)[:, None]
    d = directors[:, 2, :] * (BODY_HEIGHT * seg)[:, None]
    p = positions
    return np.stack([p - a, p + a, p + a + d, p - a + d], axis=1)


def _draw_view(
    ax: Axes,
    *,
    title: str,
    positions: np.ndarray,
    directors: np.ndarray,
    across: int,
    projector: Projector,
    colours: np.ndarray,
    landmarks: list[tuple[str, np.ndarray]],
    residuals: Mapping[str, float],
) -> None:
    """Draw the view: the vertebrae as boxes, the model's line through their projected top endplate
    midpoints, and each landmark with its residual line to the model's point of its level."""
    corners = projector(_bodies(positions, directors, across))
    ax.add_collection(PolyCollection(list(corners), facecolors=colours, edgecolors="0.25", linewidths=0.6))
    centre = projector(positions)
    ax.plot(centre[:, 0], centre[:, 1], "-", color="0.2", linewidth=1.0, label="model (endplate midpoints)")
    ax.plot(centre[:, 0], centre[:, 1], ".", color="0.2", markersize=3)
    if landmarks:
        marks = np.array([p for _, p in landmarks])
        segments = [[p, centre[LEVEL_INDEX[lv]]] for lv, p in landmarks]
        ax.add_collection(LineCollection(segments, colors="crimson", linewidths=1.2, label="residual"))
        ax.plot(marks[:, 0], marks[:, 1], "x", color="black", markersize=5, label="landmark")
        worst = max(landmarks, key=lambda item: residuals.get(item[0], 0.0))
        if residuals.get(worst[0], 0.0) > 0:
            ax.annotate(
                f"{worst[0]}: {residuals[worst[0]]:.2f} mm",
                xy=tuple(worst[1]),
                xytext=(8, 0),
                textcoords="offset points",
                fontsize=7,
                color="crimson",
                va="center",
            )
    for i in (0, len(LEVELS) // 2, len(LEVELS) - 1):
        if i < len(centre):
            ax.annotate(LEVELS[i], xy=tuple(centre[i]), xytext=(-30, 0), textcoords="offset points",
                        fontsize=7, va="center", ha="right")  # fmt: skip
    ax.set_title(title, fontsize=10, pad=14)  # room for the legend between the title and the plot
    ax.set_xlabel("column (mm)", fontsize=8)
    ax.set_ylabel("row (mm)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.invert_yaxis()
    # above the plot, under the title: inside, it covered the L5 and worst-residual labels at its foot
    ax.legend(loc="lower center", bbox_to_anchor=(0.5, 1.0), ncols=3, fontsize=6, frameon=False, borderaxespad=0.2)


def _strain_panel(ax: Axes, levels: list[str], values: np.ndarray, names: Sequence[str], title: str,
                  ylabel: str) -> None:  # fmt: skip
    x = np.arange(len(levels))
    for k, (name, marker) in enumerate(zip(names, "os^", strict=True)):
        ax.plot(x, values[:, k], marker=marker, markersize=3, linewidth=1.0, label=name)
    ax.axhline(0.0, color="0.6", linewidth=0.6)
    ax.set_xticks(x, levels, rotation=90, fontsize=7)
    ax.tick_params(axis="y", labelsize=7)
    ax.set_title(title, fontsize=10)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.grid(True, linewidth=0.3, alpha=0.6)
    ax.legend(fontsize=6, frameon=False, ncols=3, loc="upper right")


def _with_trust(value: float, sd: float | None, estimate: bool) -> str:
    """'32.5° ± 2.1°', and ' (model estimate)' when the value comes from the model's prior (fit.unreliable)."""
    text = f"{value:.1f}°" + (f" ± {sd:.1f}°" if sd is not None else "")
    return text + (" (model estimate)" if estimate else "")


def _strain_note(fit: Mapping[str, Any]) -> str:
    """The angular strain panel's note naming the components that are model estimates: u1 without depth
    (``fit.unreliable`` ``depth``), u3 without pedicles (``twist``)."""
    unreliable = set(fit.get("unreliable") or [])
    named = [name for name, flag in (("u1", "depth"), ("u3", "twist")) if flag in unreliable]
    return f" ({' and '.join(named)}: model estimates)" if named else ""


def _summary(result: Mapping[str, Any]) -> str:
    measures = result.get("measures", {})
    fit = result.get("fit", {})
    unreliable = set(fit.get("unreliable") or [])
    parts = []
    major = next((c for c in measures.get("cobb", []) if c.get("major")), None)
    if major:
        angle = _with_trust(major["angle_deg"], major.get("angle_sd_deg"), "cobb" in unreliable)
        apex = apex_words(major["apex"], bool(major.get("apical_disc")))
        where = f"{major['upper']}–{major['lower']}, apex {apex}, {major['convexity']}"
        parts.append(f"major Cobb {angle} ({where})")
    elif largest := measures.get("largest_cobb"):
        angle = _with_trust(largest["angle_deg"], largest.get("angle_sd_deg"), "cobb" in unreliable)
        parts.append(f"no frontal curve of 10°: largest angle {angle} ({largest['upper']}–{largest['lower']})")
    else:
        parts.append("no frontal curve")
    for key, name, flag in (("thoracic_kyphosis_t4_t12", "kyphosis T4–T12", "kyphosis"),
                            ("lumbar_lordosis_l1_l5", "lordosis L1–L5", "lordosis")):  # fmt: skip
        if f"{key}_deg" in measures:
            value = _with_trust(measures[f"{key}_deg"], measures.get(f"{key}_sd_deg"), flag in unreliable)
            parts.append(f"{name} {value}")
    if "mean_registration_error_mm" in fit:
        parts.append(f"mean PA residual {fit['mean_registration_error_mm']:.2f} mm")
    return parts[0] + "\n" + " · ".join(parts[1:])  # two lines: the title fits the figure's width


def draw_figure(result: Mapping[str, Any], pa: DrawnView, lateral: DrawnView, fmt: str, *, dpi: int) -> bytes:
    """The figure of ``result`` (a ``RegistrationResult`` as JSON) with its PA and lateral panels
    ``pa`` and ``lateral``, as PNG or SVG bytes (``fmt``): vertebrae coloured by frontal bending
    u2·Δs, the landmarks' residual lines, the strains u (10⁻³ rad/mm) and v per segment, the
    measures in the title."""
    vertebrae = list(result["vertebrae"])
    levels = [v["level"] for v in vertebrae]
    positions = np.array([v["position"] for v in vertebrae], dtype=float)
    directors = np.array([v["directors"] for v in vertebrae], dtype=float)  # rows d1, d2, d3
    bending = [v.get("frontal_bending_deg", v.get("lateral_bending_deg")) for v in vertebrae]
    norm = bending_norm(bending)
    cmap = colormaps[BENDING_CMAP]
    colours = np.array([cmap(norm(b)) if b is not None else (0.75, 0.75, 0.75, 1.0) for b in bending])

    fit = result["fit"]
    residuals: dict[str, dict[str, float]] = {"pa": {}, "lateral": {}}
    for r in fit.get("residuals", []):
        residuals[r["view"]][r["level"]] = float(r["residual_mm"])

    with rc_context({"svg.hashsalt": "spine-figure", "svg.fonttype": "path", "font.family": "DejaVu Sans"}):
        fig = Figure(figsize=(12.0, 8.0), dpi=dpi, layout="constrained")
        FigureCanvasAgg(fig)
        grid = fig.add_gridspec(2, 3, width_ratios=[1.0, 1.0, 1.5])
        ax_pa = fig.add_subplot(grid[:, 0])
        ax_lat = fig.add_subplot(grid[:, 1])
        ax_u = fig.add_subplot(grid[0, 2])
        ax_v = fig.add_subplot(grid[1, 2])
        for ax, view, across, name in ((ax_pa, pa, 0, "pa"), (ax_lat, lateral, 1, "lateral")):
            _draw_view(ax, title=view.title, positions=positions, directors=directors, across=across,
                       projector=view.projector, colours=colours, landmarks=view.landmarks,
                       residuals=residuals[name])  # fmt: skip

        seg = [v for v in vertebrae if v.get("u") is not None and v.get("v") is not None]
        seg_levels = [v["level"] for v in seg]
        u = np.array([v["u"] for v in seg], dtype=float).reshape(-1, 3) * 1e3
        vv = np.array([v["v"] for v in seg], dtype=float).reshape(-1, 3)
        _strain_panel(ax_u, seg_levels, u, ("u1 sagittal bending", "u2 frontal bending", "u3 twist"),
                      "Angular strain u per segment" + _strain_note(fit), "u (10⁻³ rad/mm)")  # fmt: skip
        _strain_panel(ax_v, seg_levels, vv, ("v1 shear", "v2 shear", "v3 stretch"),
                      "Linear strain v per segment", "v (dimensionless)")  # fmt: skip

        bar = fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=[ax_pa, ax_lat], location="bottom",
                           shrink=0.7, pad=0.02)  # fmt: skip
        bar.set_label("frontal bending u2·Δs of the segment below (degrees); L5 grey", fontsize=8)
        bar.ax.tick_params(labelsize=7)
        fig.suptitle(f"Spine reconstruction ({len(levels)} vertebrae) — {_summary(result)}", fontsize=11)

        buffer = io.BytesIO()
        metadata: dict[str, Any] = {"Date": None} if fmt == "svg" else {"Software": None}
        fig.savefig(buffer, format=fmt, metadata=metadata)
    return buffer.getvalue()
