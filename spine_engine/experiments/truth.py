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

from ..levels import LEVELS, N_LEVELS
from ..projection import image_axes, project
from ..rod import strains

PA_ORIENTATION = ("L", "F")
LATERAL_ORIENTATION = ("A", "F")


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


def payload_from_truth(
    positions: np.ndarray,
    rotations: np.ndarray,
    pa_levels: list[int],
    lateral_levels: list[int] | None = None,
    scale: float = 1.1,
    translation: tuple[float, float] = (150.0, 120.0),
    noise_mm: float = 0.0,
    rng: np.random.Generator | None = None,
) -> dict[str, Any]:
    """The job payload a client would send for this known spine."""
    payload: dict[str, Any] = {
        "pa": _view(positions, pa_levels, PA_ORIENTATION, scale, translation, noise_mm, rng),
        "boundary": {
            level: {"position": positions[i].tolist(), "directors": rotations[i].T.tolist()}
            for level, i in (("T1", 0), ("L5", N_LEVELS - 1))
        },
    }
    if lateral_levels:
        payload["lateral"] = _view(
            positions, lateral_levels, LATERAL_ORIENTATION, scale, translation, noise_mm, rng
        )
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
