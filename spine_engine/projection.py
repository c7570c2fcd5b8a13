"""Weak-perspective projection of patient points (LPS, mm) onto a radiograph (detector mm).

image point p = s · (e_c·r, e_r·r) + T, with e_c and e_r the patient-space unit vectors of the
image's column and row directions (DICOM patient orientation), s the dimensionless magnification
and T (2,) the translation in detector mm.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .models import PATIENT_AXES

FloatArray = NDArray[np.float64]
Projector = Callable[[np.ndarray], np.ndarray]
"""A view's projection: patient points (..., 3), mm → their image (..., 2), detector mm."""


def image_axes(orientation: tuple[str, str]) -> tuple[FloatArray, FloatArray]:
    """Unit vectors (e_c, e_r) in LPS of the column and row directions named by ``orientation``.

    L = +x, R = −x, P = +y, A = −y, H = +z, F = −z. PA ("L", "F") gives e_c = +x, e_r = −z;
    lateral ("A", "F") gives e_c = −y, e_r = −z.
    """
    col, row = orientation
    for name, letter in (("column", col), ("row", row)):
        if letter not in PATIENT_AXES:
            raise ValueError(f"{name} direction {letter!r} is not one of {list(PATIENT_AXES)}")
    e_c = np.array(PATIENT_AXES[col])
    e_r = np.array(PATIENT_AXES[row])
    if abs(float(e_c @ e_r)) > 0.0:
        raise ValueError(f"column and row directions {col!r}, {row!r} are not orthogonal")
    return e_c, e_r


def project(r: ArrayLike, e_c: ArrayLike, e_r: ArrayLike, scale: float, translation: ArrayLike) -> FloatArray:
    """Weak perspective p = s·(e_c·r, e_r·r) + T; r (..., 3) in mm → p (..., 2) in detector mm."""
    r = np.asarray(r, dtype=float)
    E = np.stack((np.asarray(e_c, dtype=float), np.asarray(e_r, dtype=float)))
    return scale * (r @ E.T) + np.asarray(translation, dtype=float)


def estimate_projection(
    points3d: ArrayLike, image: ArrayLike, e_c: ArrayLike, e_r: ArrayLike
) -> tuple[float, FloatArray]:
    """Least-squares scale s and translation T from m ≥ 2 known 3D points and their images.

    With q_k = (e_c·r_k, e_r·r_k) the in-plane coordinates (mm) and p_k the image points
    (detector mm), minimising Σ_k ‖s q_k + T − p_k‖² gives
        s = Σ_k (q_k − q̄)·(p_k − p̄) / Σ_k ‖q_k − q̄‖²,   T = p̄ − s q̄.
    Raises ValueError when the projected 3D points coincide (s undetermined) or when s ≤ 0.
    """
    P3 = np.asarray(points3d, dtype=float)
    p = np.asarray(image, dtype=float)
    if P3.ndim != 2 or P3.shape[1] != 3 or p.shape != (P3.shape[0], 2):
        raise ValueError(f"expected points3d (m, 3) and image (m, 2), got {P3.shape} and {p.shape}")
    if P3.shape[0] < 2:
        raise ValueError(f"estimating a projection needs at least 2 points, got {P3.shape[0]}")
    E = np.array((e_c, e_r), dtype=float)
    q = P3 @ E.T
    # q̄, p̄ once each, as ndarray.mean computes them (add.reduce over the rows, then ÷ m), without its wrapper
    q_mean = np.add.reduce(q, axis=0) / len(q)
    p_mean = np.add.reduce(p, axis=0) / len(p)
    dq = q - q_mean
    dp = p - p_mean
    spread = float(np.sum(dq * dq))
    extent = float(np.max(np.abs(P3))) if P3.size else 0.0
    if spread <= (1e-9 * max(extent, 1.0)) ** 2:
        raise ValueError(
            "cannot estimate the projection: the 3D points project onto the same image point "
            f"(spread {np.sqrt(spread):.3g} mm in the image plane)"
        )
    s = float(np.sum(dq * dp)) / spread
    if not s > 0.0:
        raise ValueError(
            f"estimated projection scale is {s:.4g} ≤ 0: the landmarks are mirrored or swapped "
            "relative to the 3D points (check the patient orientation and the levels)"
        )
    return s, p_mean - s * q_mean
