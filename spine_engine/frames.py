"""Directors of the vertebrae from a centreline, and their axial rotation.

Frame (``DESIGN.md``): DICOM LPS in mm, +x patient left, +y posterior, +z superior. A vertebra's
rotation matrix has its directors as columns, R = [d1 d2 d3]: d1 ≈ patient left, d2 ≈ anterior,
d3 = centreline tangent pointing caudally (toward L5), d1 × d2 = d3.

Axial rotation ψ (degrees) follows the SRS 3D terminology (Stokes, Spine 1994;19:236–248):
a rotation about the cranial axis, counter-clockwise seen from above, so ψ > 0 turns the
vertebral body (d2, anterior) toward the patient's left (+x) and ψ < 0 toward the right.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .rotations import cross

FloatArray = npt.NDArray[np.float64]

PATIENT_LEFT = np.array([1.0, 0.0, 0.0])
_DEGENERATE = 1e-9


def centreline_tangents(positions: FloatArray) -> FloatArray:
    """Unit tangents (N,3): central differences p_{i+1} − p_{i−1} inside, one-sided differences at the
    ends (the d3 of ``frames_from_centreline``). Raises ValueError where neighbouring points coincide."""
    diff = np.empty_like(positions)
    diff[1:-1] = positions[2:] - positions[:-2]
    diff[0] = positions[1] - positions[0]
    diff[-1] = positions[-1] - positions[-2]
    norm = np.linalg.norm(diff, axis=1)
    if np.any(norm < _DEGENERATE):
        bad = int(np.argmin(norm))
        raise ValueError(f"centreline has no tangent at point {bad}: neighbouring points coincide")
    return diff / norm[:, None]


def frames_from_centreline(positions: npt.ArrayLike, axial_rotation_rad: npt.ArrayLike | None = None) -> FloatArray:
    """Directors R_i = [d1 d2 d3] (N,3,3), as columns, of the points of a centreline ordered T1 → L5.

    - d3 = t / |t|, with t = p_{i+1} − p_{i−1} inside and the one-sided difference at the ends,
      so d3 points caudally.
    - d1 = (e_x − (e_x·d3) d3) / |…| (Gram–Schmidt of the patient-left axis e_x = +x against d3);
      defined whenever the tangent is not parallel to +x, i.e. for any spine standing upright.
    - d2 = d3 × d1 (≈ anterior, −y, for a vertical tangent).
    - With an axial rotation ψ_i (radians), the pair (d1, d2) is turned about the cranial axis −d3
      by ψ_i: d1 ← cos ψ d1 − sin ψ d2, d2 ← sin ψ d1 + cos ψ d2 (R ← R·Rz(−ψ)). This is the SRS
      sense of ``axial_rotation_deg`` (ψ > 0 turns d2 toward patient left), so that
      ``axial_rotation_deg(frames_from_centreline(p, ψ)) == degrees(ψ)`` exactly when the tangent
      is vertical, and with the same sign and nearly the same size when it is inclined.

    Raises ValueError for fewer than 2 points, coinciding neighbours or a tangent along +x.
    """
    p = np.asarray(positions, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 2:
        raise ValueError(f"positions must have shape (N, 3) with N >= 2, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("positions must be finite")
    d3 = centreline_tangents(p)
    d1 = PATIENT_LEFT[None, :] - (d3 @ PATIENT_LEFT)[:, None] * d3
    n1 = np.linalg.norm(d1, axis=1)
    if np.any(n1 < 1e-6):
        bad = int(np.argmin(n1))
        raise ValueError(f"tangent at point {bad} is parallel to the patient-left axis: d1 is undefined")
    d1 /= n1[:, None]
    d2 = cross(d3, d1)
    if axial_rotation_rad is not None:
        psi = np.broadcast_to(np.asarray(axial_rotation_rad, dtype=float), (len(p),))
        c, s = np.cos(psi)[:, None], np.sin(psi)[:, None]
        d1, d2 = c * d1 - s * d2, s * d1 + c * d2
    return np.stack([d1, d2, d3], axis=-1)


def axial_rotation_deg(rotations: npt.ArrayLike) -> FloatArray:
    """Axial rotation of each vertebra, degrees, in (−180, 180].

    ψ = atan2(d2_x, −d2_y): the angle of d2 projected on the transverse (x, y) plane, measured
    from the anterior direction −y, positive toward patient left (+x), i.e. counter-clockwise seen
    from above (SRS sense). A curve convex to the left rotates its apex toward the convexity when
    ψ_apex > 0, a curve convex to the right when ψ_apex < 0. Accepts (3,3) or (N,3,3).
    """
    R = np.asarray(rotations, dtype=float)
    d2 = R[..., :, 1]
    return np.degrees(np.arctan2(d2[..., 0], -d2[..., 1]))
