"""The initial configuration of the fit: the rest shape bent between two end poses, moved onto the landmarks."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg.lapack import dpbtrf, dpbtrs

from ..rotations import rotation_between, slerp
from .banded import UPPER3, accumulate
from .problem import _check_view
from .types import FloatArray, Pose, ViewData, as_pose

DATA_WEIGHT = 1e6
"""Weight of the landmarks against the smoothing of the displacements."""
_KD = 5
"""Half-bandwidth of the displacement system over the extended index 3·vertebra + k."""
_BAND_ROW = _KD + UPPER3[0] - UPPER3[1]
"""Band-storage row of each upper entry (a, b), a ≤ b, of a landmark's 3×3 block (``UPPER3``)."""


@functools.lru_cache(maxsize=64)
def _band_bins(n: int, layout: tuple[tuple[int, ...], ...]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Where the landmarks' terms go in ``initial_configuration``'s displacement system, for N
    vertebrae and the landmarked vertebrae i of each view (``layout``; integers only, no units):
    the flat index (``_BAND_ROW`` · 3N + 3i + b) into the band storage (KD + 1, 3N) of each upper
    entry (a, b) of every landmark's 3×3 block, and the right-hand side's index 3i + k, k = 0, 1, 2,
    of each landmark, all views stacked in order. Read-only; cached per layout (the same few
    layouts recur from job to job)."""
    n_ext = 3 * n
    _, b = UPPER3
    rows, cols, rhs_bins = [], [], []
    for indices in layout:
        idx = np.asarray(indices, dtype=int)
        m = len(idx)
        rows.append(np.broadcast_to(_BAND_ROW, (m, len(_BAND_ROW))).ravel())
        cols.append((3 * idx[:, None] + b).ravel())
        rhs_bins.append((3 * idx[:, None] + np.arange(3)).ravel())
    flat = np.concatenate(rows) * n_ext + np.concatenate(cols)
    bins = np.concatenate(rhs_bins)
    flat.flags.writeable = False
    bins.flags.writeable = False
    return flat, bins


def inplane_targets(view: ViewData) -> FloatArray:
    """The landmarks back-projected into the view's image plane with its camera's initial values:
    (e_c·r, e_r·r) in patient mm. Weak: Rot(−ψ)(p − T)/s; perspective: Rot(−ψ)(p − c)·SOD/SID + E o
    (the magnification of the plane at SOD)."""
    cam = view.get_camera()
    v = cam.values
    c, s = np.cos(v[-1]), np.sin(v[-1])
    rot_back = np.array([[c, s], [-s, c]])
    p = np.asarray(view.points, dtype=float)
    if cam.kind == "weak":
        return ((p - v[1:3]) @ rot_back.T) / v[0]
    E = np.stack((np.asarray(view.e_c, dtype=float), np.asarray(view.e_r, dtype=float)))
    return ((p - v[:2]) @ rot_back.T) * (cam.sod_mm / cam.sid_mm) + E @ v[2:5]


def initial_configuration(
    rest_positions: ArrayLike,
    rest_rotations: ArrayLike,
    views: Sequence[ViewData],
    top: Pose | tuple[ArrayLike, ArrayLike],
    bottom: Pose | tuple[ArrayLike, ArrayLike],
) -> tuple[FloatArray, FloatArray]:
    """A starting configuration: the rest shape bent between ``top`` and ``bottom``, moved onto the landmarks.

    1. Blend: rigid motions G_a, G_b take the rest T1 pose onto ``top`` and the rest L5 pose onto
       ``bottom``; vertebra i with arc-length fraction t_i goes to (1 − t_i) G_a r_i + t_i G_b r_i
       with rotation slerp(R_a, R_b, t_i) R_i. Both ends then match exactly.
    2. Landmarks: displacements d_i (d_0 = d_{N−1} = 0) minimise
       10⁶ Σ_landmarks w ‖E (r_i + d_i) − q‖² + Σ_i ‖d_{i+1} − d_i‖²/ℓ_i,
       E = [e_c; e_r], q the landmark back-projected by the view's initial camera (``inplane_targets``),
       ℓ_i the segment lengths: landmarked vertebrae move in their image planes onto the landmarks,
       the rest follow by linear interpolation in arc length.
    3. Directors: each interior rotation is turned by the smallest rotation taking the blended
       centreline's tangent (central difference) onto the displaced one's.
    Returns positions (N, 3) in mm and rotations (N, 3, 3).
    """
    p = np.asarray(rest_positions, dtype=float)
    Q = np.asarray(rest_rotations, dtype=float)
    n = len(p)
    if n < 3 or p.shape != (n, 3) or Q.shape != (n, 3, 3):
        raise ValueError(f"expected rest positions (N, 3) and rotations (N, 3, 3) with N ≥ 3, got {p.shape}, {Q.shape}")
    for view in views:
        _check_view(view, n)
    r_top, R_top = as_pose(top, "top")
    r_bot, R_bot = as_pose(bottom, "bottom")

    R_a = R_top @ Q[0].T
    R_b = R_bot @ Q[-1].T
    chords = p[1:] - p[:-1]
    t = np.zeros(n)
    np.cumsum(np.sqrt(np.einsum("ij,ij->i", chords, chords)), out=t[1:])
    t /= max(t[-1], 1e-300)
    r = (1.0 - t)[:, None] * ((p - p[0]) @ R_a.T + r_top) + t[:, None] * ((p - p[-1]) @ R_b.T + r_bot)
    R = slerp(R_a, R_b, t) @ Q
    r[0], R[0] = r_top, R_top
    r[-1], R[-1] = r_bot, R_bot

    # Band system (upper storage, half-bandwidth 5) over the extended index 3·vertebra + k; the
    # ends' rows and columns are sliced off before solving.
    kd = _KD
    n_ext = 3 * n
    a, b = UPPER3
    vals, rhs_vals = [], []
    layout = []
    for view in views:
        idx = np.asarray(view.indices, dtype=int)
        layout.append(tuple(idx.tolist()))
        m = len(idx)
        E = np.array((view.e_c, view.e_r), dtype=float)
        wE = DATA_WEIGHT * max(float(view.weight), 1e-12) * E
        target = inplane_targets(view)
        vals.append(np.repeat((E.T @ wE)[None, a, b], m, axis=0).ravel())
        rhs_vals.append(((target - r[idx] @ E.T) @ wE).ravel())
    seg = r[1:] - r[:-1]
    k = 1.0 / np.maximum(np.sqrt(np.einsum("ij,ij->i", seg, seg)), 1e-9)
    ab = np.zeros((kd + 1, n_ext))
    k3 = np.repeat(k, 3)
    ab[kd, :-3] = k3
    ab[kd, 3:] += k3
    ab[kd - 3, 3:] = -k3
    rhs = np.zeros(n_ext)
    if vals:
        flat, rhs_bins = _band_bins(n, tuple(layout))
        ab += accumulate(flat, np.concatenate(vals), minlength=ab.size).reshape(ab.shape)
        rhs = accumulate(rhs_bins, np.concatenate(rhs_vals), minlength=n_ext)
    c, info = dpbtrf(ab[:, 3:-3])
    if info != 0:
        raise ValueError("initial configuration: the displacement system is singular (non-finite input?)")
    d = dpbtrs(c, rhs[3:-3, None])[0].reshape(n - 2, 3)

    r_new = r.copy()
    r_new[1:-1] += d
    tangent_old = r[2:] - r[:-2]
    tangent_new = r_new[2:] - r_new[:-2]
    R_new = R.copy()
    R_new[1:-1] = rotation_between(tangent_old, tangent_new) @ R[1:-1]
    return r_new, R_new
