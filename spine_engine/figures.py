"""Figures of a reconstruction: PA and lateral views with landmarks and residuals, and strains.

``render_figure(result, payload, fmt)`` is a pure function from a ``RegistrationResult`` dict and
the ``JobPayload`` dict it came from to the bytes of a PNG or SVG image (matplotlib, Agg; no
pyplot state, so it is safe in threads). It knows nothing of HTTP.

The figure has four panels:

- PA view, in the PA image's detector frame (column right, row down, mm): the landmarks, the
  model's vertebrae projected as the fit projected them (``view_projection``: the view's camera,
  weak perspective or point source, with its fitted in-plane rotation), and the residual of each
  landmark (a line to the projected model point, as long as ``fit.residuals`` says);
- lateral view: the lateral image's frame when the payload has one (same content as PA), else
  the model projected laterally (``["A","F"]``) with the PA scale, its mean row the PA panel's;
- per-level angular strain u = (u1, u2, u3) and per-level v = (v1, v2, v3).

Vertebrae are drawn as the projection of a box below their top endplate midpoint, spanned by
d1 (PA) or d2 (lateral) and d3, and coloured by frontal bending (u2·Δs, degrees) on a diverging
map, as in Fig. 2 of Li et al. (CAIP 2009). L5 has no segment below it and is drawn grey.
"""

from __future__ import annotations

import io
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Literal

import numpy as np
from matplotlib import colormaps, rc_context
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure

from .clinical import landmark_arrays
from .fit import Camera
from .fit.cameras import project as project_by_camera
from .levels import LEVEL_INDEX, LEVELS, apex_words
from .models import LATERAL_ORIENTATION, JobPayload
from .projection import image_axes, project

FigureFormat = Literal["png", "svg"]
MEDIA_TYPES: dict[str, str] = {"png": "image/png", "svg": "image/svg+xml"}

BODY_WIDTH = 1.4
"""Drawn vertebral body width, as a multiple of the segment length (about 36 mm for 26 mm)."""
BODY_HEIGHT = 0.7
"""Drawn vertebral body height along d3, as a multiple of the segment length."""
BENDING_CMAP = "coolwarm"


def bending_norm(values: Sequence[float | None]) -> Normalize:
    """Symmetric colour scale of the frontal bending angles (at least ±1°)."""
    finite = [abs(v) for v in values if v is not None]
    limit = max([1.0, *finite])
    return Normalize(vmin=-limit, vmax=limit)


def _detector_mm(view: Any) -> np.ndarray:
    """The view's fitted points in detector mm, as the engine converts them (``clinical.landmark_arrays``:
    px × pixel spacing; corners → the superior endplate midpoint, whichever way up the image is)."""
    return landmark_arrays(view).points.reshape(-1, 2)


Projector = Callable[[np.ndarray], np.ndarray]
"""Patient points (..., 3), mm → their image (..., 2), detector mm."""


def view_projection(result: Mapping[str, Any], payload: JobPayload, name: str) -> Projector:
    """The projection of view ``name`` ("pa" or "lateral") as the fit projected the model, from the
    result's ``fit.<name>`` (``ViewProjection``) through the engine's own ``fit.cameras.project``: weak
    perspective p = s·Rot(ψ)(e_c·r, e_r·r) + T, or the point source (``model`` "perspective")
    p = c + m·Rot(ψ)(e_c·(r − o), e_r·(r − o)), m = SID / (SOD + b·(r − o)), with c = ``translation``,
    o = ``central_ray_point_mm``, b = ``beam_direction``. The drawing and ``model_points`` both
    project through it."""
    proj = result["fit"].get(name)
    view = payload.pa if name == "pa" else payload.lateral
    if view is None or proj is None:
        raise ValueError(f"the {'payload' if view is None else 'result'} has no {name} view")
    e_c, e_r = image_axes(view.patient_orientation)
    psi = math.radians(float(proj.get("rotation_deg", 0.0)))
    c_c, c_r = (float(t) for t in proj["translation"])
    if proj.get("model", "weak_perspective") == "perspective" and proj.get("central_ray_point_mm") is not None:
        values = np.array([c_c, c_r, *(float(v) for v in proj["central_ray_point_mm"]), psi])
        camera = Camera(
            "perspective", values, np.zeros(6, dtype=bool), sid_mm=float(proj["source_to_detector_mm"]),
            sod_mm=float(proj["source_to_patient_mm"]), beam=np.asarray(proj["beam_direction"], dtype=float),
        )  # fmt: skip
    else:  # weak perspective (a result stored before the point source was reported is drawn so too)
        values = np.array([float(proj["scale"]), c_c, c_r, psi])
        camera = Camera("weak", values, np.zeros(4, dtype=bool))

    def projector(points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, dtype=float)
        flat = project_by_camera(camera, values, points.reshape(-1, 3), e_c, e_r).points
        return flat.reshape(*points.shape[:-1], 2)

    return projector


def model_points(result: Mapping[str, Any], payload: Mapping[str, Any], name: str) -> np.ndarray:
    """(17, 2) the model's vertebrae (top endplate midpoints) on view ``name``'s detector, mm, where the
    figure draws them (``view_projection``): each landmark's residual line ends there."""
    positions = np.array([v["position"] for v in result["vertebrae"]], dtype=float)
    return view_projection(result, JobPayload.model_validate(payload), name)(positions)


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
) -> np.ndarray:
    """Draw the view; return the model's projected points (``projector`` of ``positions``)."""
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
    return centre


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


def _depth_note(fit: Mapping[str, Any]) -> str:
    """The lateral projection's second title line when no film places the spine in depth (``fit.unreliable``
    ``depth``): the depths drawn are the population prior's sagittal shape, not a measurement."""
    if "depth" not in set(fit.get("unreliable") or []):
        return ""
    return "\nmodel estimate: no film shows depth"


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


def render_figure(
    result: Mapping[str, Any], payload: Mapping[str, Any], fmt: FigureFormat = "png", *, dpi: int = 110
) -> bytes:
    """The figure of a reconstruction as PNG or SVG bytes.

    ``result`` is a ``RegistrationResult`` as JSON (what a succeeded job holds), ``payload`` the
    ``JobPayload`` it was computed from. Raises ValueError for an unknown format.
    """
    if fmt not in MEDIA_TYPES:
        raise ValueError(f"unknown figure format {fmt!r}; expected one of {sorted(MEDIA_TYPES)}")
    model = JobPayload.model_validate(payload)
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

        pa_proj = fit["pa"]
        pa_points = _detector_mm(model.pa)
        pa_centre = _draw_view(
            ax_pa,
            title="PA view: landmarks, model and residuals",
            positions=positions, directors=directors, across=0, projector=view_projection(result, model, "pa"),
            colours=colours,
            landmarks=[(lm.level, p) for lm, p in zip(model.pa.landmarks, pa_points, strict=True)],
            residuals=residuals["pa"],
        )  # fmt: skip

        lateral = model.lateral
        lat_proj = fit.get("lateral")
        if lateral is not None and lateral.landmarks and lat_proj is not None:
            lat_points = _detector_mm(lateral)
            _draw_view(
                ax_lat,
                title="Lateral view: landmarks, model and residuals",
                positions=positions, directors=directors, across=1,
                projector=view_projection(result, model, "lateral"),
                colours=colours,
                landmarks=[(lm.level, p) for lm, p in zip(lateral.landmarks, lat_points, strict=True)],
                residuals=residuals["lateral"],
            )  # fmt: skip
        else:
            e_c, e_r = image_axes(LATERAL_ORIENTATION)
            scale = float(pa_proj["scale"])  # a point-source PA's: SID/SOD at the spine's mid-plane
            row = float(np.mean(pa_centre[:, 1]) - scale * np.mean(positions @ e_r))  # the PA panel's mean row
            _draw_view(
                ax_lat,
                title="Lateral projection of the model (anterior right)" + _depth_note(fit),
                positions=positions, directors=directors, across=1,
                projector=lambda r: project(r, e_c, e_r, scale, np.array([0.0, row])),
                colours=colours, landmarks=[], residuals={},
            )  # fmt: skip

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
