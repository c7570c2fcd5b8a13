"""Ground truth to payload, and reconstruction errors against the truth.

Shared by the experiment commands: a known spine (positions (17,3) mm, rotations (17,3,3) with
the directors as columns) is projected on a PA (and optionally a lateral) view by weak
perspective, its T1 and L5 poses become the boundary, and the reconstruction is compared with it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from spine_engine.anatomy import VERTEBRA_TABLE, load_profile
from spine_engine.clinical import size_factor
from spine_engine.fit import ViewData
from spine_engine.levels import LEVELS, N_LEVELS
from spine_engine.models import LATERAL_ORIENTATION, PA_ORIENTATION
from spine_engine.observations import pedicle_offsets_in_image_order
from spine_engine.projection import image_axes, project
from spine_engine.rod import strains


def landmark_subset(count: int) -> list[int]:
    """``count`` level indices spread evenly from T1 to L5, both ends always included."""
    if not 2 <= count <= N_LEVELS:
        raise ValueError(f"landmark count must be in 2..{N_LEVELS}, got {count}")
    return sorted({int(i) for i in np.round(np.linspace(0, N_LEVELS - 1, count))})


def _view(
    positions: np.ndarray,
    levels: list[int],
    orientation: tuple[str, str],
    scale: float,
    translation: tuple[float, float],
    noise_mm: float,
    rng: np.random.Generator | None,
) -> dict[str, Any]:
    e_c, e_r = image_axes(orientation)
    points = project(positions[levels], e_c, e_r, scale, np.asarray(translation))
    if noise_mm > 0 and rng is not None:
        points = points + rng.normal(0.0, noise_mm, points.shape)
    return {
        "units": "mm",
        "patient_orientation": list(orientation),
        "landmarks": [
            {"level": LEVELS[i], "point": [float(p[0]), float(p[1])]} for i, p in zip(levels, points, strict=True)
        ],
    }


def truth_size_factor(
    positions: np.ndarray, levels: list[int], orientation: tuple[str, str] = PA_ORIENTATION
) -> float:
    """The size factor the engine will estimate (``clinical.size_factor``, default profile) from
    exact landmarks of this spine at ``levels``: pedicle offsets and boxes are scaled by it."""
    e_c, e_r = image_axes(orientation)
    idx = np.asarray(levels, dtype=int)
    points = project(positions[idx], e_c, e_r, 1.0, np.zeros(2))
    return size_factor(load_profile("default"), ViewData("pa", idx, points, e_c, e_r, 1.0, np.zeros(2), 1.0))


def vertebra_corners_3d(
    positions: np.ndarray, rotations: np.ndarray, levels: list[int], size: float = 1.0
) -> np.ndarray:
    """Corners (k, 4, 3) of a frontal box around each vertebra, mm: its node is the superior
    endplate midpoint, the box is W wide along d1 and H high along d3 (caudal), W and H from
    ``anatomy.VERTEBRA_TABLE`` × ``size``. Order: superior (−d1, +d1), inferior (−d1, +d1)."""
    out = []
    for i in levels:
        height, width, _ = VERTEBRA_TABLE[LEVELS[i]]
        d1, d3 = rotations[i][:, 0], rotations[i][:, 2]
        half = 0.5 * width * size * d1
        down = height * size * d3
        p = positions[i]
        out.append([p - half, p + half, p - half + down, p + half + down])
    return np.asarray(out, dtype=float)


def image_corners(
    corners3d: np.ndarray, orientation: tuple[str, str], scale: float, translation: np.ndarray
) -> np.ndarray:
    """Project box corners (k, 4, 3) (superior pair, inferior pair: ``vertebra_corners_3d``) and
    name them as an annotator does: the superior endplate's corners are the "top" pair when the
    rows run toward the feet (the bottom pair when toward the head), and within a pair the one
    with the smaller column is "left". Order: top-left, top-right, bottom-left, bottom-right."""
    e_c, e_r = image_axes(orientation)
    img = project(corners3d, e_c, e_r, scale, translation)
    superior, inferior = img[:, :2], img[:, 2:]
    top, bottom = (superior, inferior) if float(e_r[2]) < 0 else (inferior, superior)
    out = np.empty_like(img)
    for k in range(len(img)):
        for pair, slot in ((top[k], 0), (bottom[k], 2)):
            out[k, slot : slot + 2] = pair[np.argsort(pair[:, 0], kind="stable")]
    return out


def pedicle_centres_3d(
    positions: np.ndarray, rotations: np.ndarray, levels: list[int], size: float = 1.0
) -> np.ndarray:
    """3D pedicle centres (k, 2, 3), image-left then image-right on a PA ["L", "F"] view: node +
    R·o with the engine's offsets (``observations.pedicle_offsets_in_image_order``) × ``size``."""
    e_c, _ = image_axes(PA_ORIENTATION)
    offsets = pedicle_offsets_in_image_order(levels, e_c, size).reshape(-1, 2, 3)
    idx = np.asarray(levels, dtype=int)
    return positions[idx][:, None, :] + np.einsum("kij,kpj->kpi", rotations[idx], offsets)


EXACT_LANDMARK_SD_MM = 0.17
"""The SD a payload of exact (noise-free) simulated landmarks declares, mm: with the noise-calibrated
weight (``profiles/default.json``, 60 N/mm at 1 mm) it gives them 60/0.17² ≈ 2000 N/mm, the weight the
paper's setting (exact landmarks, T1 and L5 given) was calibrated with, so its benchmarks are unchanged."""


def payload_from_truth(
    positions: np.ndarray,
    rotations: np.ndarray,
    pa_levels: list[int],
    lateral_levels: list[int] | None = None,
    scale: float = 1.1,
    translation: tuple[float, float] = (150.0, 120.0),
    noise_mm: float = 0.0,
    rng: np.random.Generator | None = None,
    *,
    corner_levels: list[int] | None = None,
    pedicle_levels: list[int] | None = None,
    boundary: bool = True,
    projection: bool = False,
    landmark_sd_mm: float | None = None,
) -> dict[str, Any]:
    """The job payload a client would send for this known spine.

    ``corner_levels``: PA landmarks given by the four corners of a box around the vertebra
    (``vertebra_corners_3d``) instead of a point; ``pedicle_levels``: PA pedicle centres
    (``pedicle_centres_3d``); boxes and pedicles are scaled by ``truth_size_factor``. Without
    ``boundary`` the payload has no T1 / L5 poses; ``projection`` sends the PA view's (s, T).
    Each view says its landmarks' noise (``landmark_sd_mm``; default ``noise_mm``, or
    ``EXACT_LANDMARK_SD_MM`` for exact landmarks), so that the fit weighs them as it should.
    """
    sd = landmark_sd_mm if landmark_sd_mm is not None else (noise_mm if noise_mm > 0 else EXACT_LANDMARK_SD_MM)
    payload: dict[str, Any] = {
        "pa": _view(positions, pa_levels, PA_ORIENTATION, scale, translation, noise_mm, rng),
    }
    payload["pa"]["landmark_sd_mm"] = sd
    if boundary:
        payload["boundary"] = {
            level: {"position": positions[i].tolist(), "directors": rotations[i].T.tolist()}
            for level, i in (("T1", 0), ("L5", N_LEVELS - 1))
        }
    if projection:
        payload["pa"]["projection"] = {"scale": scale, "translation": list(translation)}
    if corner_levels or pedicle_levels:
        size = truth_size_factor(positions, pa_levels)
        by_level = {lm["level"]: lm for lm in payload["pa"]["landmarks"]}
        T = np.asarray(translation, dtype=float)
        e_c, e_r = image_axes(PA_ORIENTATION)
        if corner_levels:
            boxes = vertebra_corners_3d(positions, rotations, corner_levels, size)
            quads = image_corners(boxes, PA_ORIENTATION, scale, T)
            for i, quad in zip(corner_levels, quads, strict=True):
                lm = by_level[LEVELS[i]]
                lm.pop("point")
                lm["corners"] = quad.tolist()
        if pedicle_levels:
            centres = project(pedicle_centres_3d(positions, rotations, pedicle_levels, size), e_c, e_r, scale, T)
            for i, pair in zip(pedicle_levels, centres, strict=True):
                by_level[LEVELS[i]]["pedicles"] = pair.tolist()
    if lateral_levels:
        payload["lateral"] = _view(
            positions, lateral_levels, LATERAL_ORIENTATION, scale, translation, noise_mm, rng
        )
        payload["lateral"]["landmark_sd_mm"] = sd
    return payload


@dataclass(frozen=True)
class Errors:
    """Errors of one reconstruction: 3D distance per level (mm), per-segment angles (degrees)."""

    per_level_mm: np.ndarray  # (17,)
    bending_deg: float  # mean |Δφ1|, |Δφ2| over segments
    twist_deg: float  # mean |Δφ3| over segments

    @property
    def mean_interior_mm(self) -> float:
        """Mean 3D error over T2..L4 (T1 and L5 are given exactly, so they are left out)."""
        return float(np.mean(self.per_level_mm[1:-1]))

    @property
    def max_mm(self) -> float:
        return float(np.max(self.per_level_mm))


def segment_angles_deg(rotations: np.ndarray) -> np.ndarray:
    """Relative rotation vector φ_i = vee(log(R_iᵀR_{i+1})) of each segment, degrees (16,3)."""
    unit = np.ones(len(rotations) - 1)
    positions = np.zeros((len(rotations), 3))
    u, _ = strains(positions, rotations, unit)
    return np.degrees(u)


def errors(result: dict[str, Any], positions: np.ndarray, rotations: np.ndarray) -> Errors:
    """Compare a ``register`` result with the true positions and rotations."""
    recon_r = np.array([v["position"] for v in result["vertebrae"]])
    recon_R = np.array([np.asarray(v["directors"]).T for v in result["vertebrae"]])
    d_phi = np.abs(segment_angles_deg(recon_R) - segment_angles_deg(rotations))
    return Errors(
        per_level_mm=np.linalg.norm(recon_r - positions, axis=1),
        bending_deg=float(np.mean(d_phi[:, :2])),
        twist_deg=float(np.mean(d_phi[:, 2])),
    )


def read_verse(path: Path) -> list[tuple[str, np.ndarray]]:
    """Spines of a VerSe split CSV: (id, positions (17,3) in LPS mm)."""
    rows = []
    with path.open() as fh:
        header = fh.readline().strip().split(",")
        expected = ["id"] + [f"{lv}_{a}" for lv in LEVELS for a in "xyz"]
        if header != expected:
            raise ValueError(f"{path}: unexpected header (want id then x,y,z per level T1..L5)")
        for line in fh:
            if line.strip():
                cells = line.strip().split(",")
                rows.append((cells[0], np.array(cells[1:], dtype=float).reshape(N_LEVELS, 3)))
    return rows
