"""Projection of patient points by a view's ``Camera`` and its analytic derivatives.

Weak perspective, parameters π = [s, T_c, T_r, ψ]:
    q = E r (E = [e_c; e_r]),  p = s Rot(ψ) q + T,
    ∂p/∂r = s Rot(ψ) E,  ∂p/∂s = Rot(ψ) q,  ∂p/∂T = I,  ∂p/∂ψ = s Rot'(ψ) q.
Perspective (pinhole), π = [c_c, c_r, o_x, o_y, o_z, ψ]: with d = r − o, q = E d, z = b·d
(b the beam, source → detector) and m = SID / (SOD + z),
    p = c + m Rot(ψ) q,
    ∂p/∂r = m Rot(ψ) E − (m² / SID) (Rot(ψ) q) bᵀ = −∂p/∂o,  ∂p/∂c = I,  ∂p/∂ψ = m Rot'(ψ) q,
with Rot'(ψ) = dRot/dψ = [[−sin ψ, −cos ψ], [cos ψ, −sin ψ]]. The derivatives are checked against
finite differences in ``tests/engine/test_cameras.py``. Both are computed point by point in one numba
kernel (``_project_kernel``), compiled by ``warmup.warm_up``'s weak-perspective fit.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from .types import Camera, FloatArray


class Projected(NamedTuple):
    """Image points and their derivatives for k patient points."""

    points: FloatArray
    """(k, 2) detector mm."""
    d_r: FloatArray
    """(k, 2, 3) ∂p/∂r."""
    d_params: FloatArray
    """(k, 2, P) ∂p/∂π over all the camera's parameters (4 weak, 6 perspective)."""


@njit(cache=True)
def _project_kernel(
    r: FloatArray, E: FloatArray, psi: float, pi: FloatArray, b: FloatArray, sid: float, sod: float, perspective: bool
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(points, ∂p/∂r, ∂p/∂π) of the module docstring, point by point (the small arrays' numpy calls
    cost more than their arithmetic). Weak: π = [s, T_c, T_r, ψ]; perspective: [c_c, c_r, o, ψ]."""
    k = r.shape[0]
    cos, sin = math.cos(psi), math.sin(psi)
    rot = ((cos, -sin), (sin, cos))
    d_rot = ((-sin, -cos), (cos, -sin))
    RE = np.empty((2, 3))
    for a in range(2):
        for j in range(3):
            RE[a, j] = rot[a][0] * E[0, j] + rot[a][1] * E[1, j]
    points = np.empty((k, 2))
    d_r = np.empty((k, 2, 3))
    d_params = np.zeros((k, 2, 6 if perspective else 4))
    for i in range(k):
        if perspective:
            d0, d1, d2 = r[i, 0] - pi[2], r[i, 1] - pi[3], r[i, 2] - pi[4]
        else:
            d0, d1, d2 = r[i, 0], r[i, 1], r[i, 2]
        q0 = d0 * E[0, 0] + d1 * E[0, 1] + d2 * E[0, 2]
        q1 = d0 * E[1, 0] + d1 * E[1, 1] + d2 * E[1, 2]
        u0 = rot[0][0] * q0 + rot[0][1] * q1
        u1 = rot[1][0] * q0 + rot[1][1] * q1
        v0 = d_rot[0][0] * q0 + d_rot[0][1] * q1
        v1 = d_rot[1][0] * q0 + d_rot[1][1] * q1
        if perspective:
            m = sid / (sod + d0 * b[0] + d1 * b[1] + d2 * b[2])
            w = m * m / sid
            points[i, 0] = pi[0] + m * u0
            points[i, 1] = pi[1] + m * u1
            for j in range(3):
                d_r[i, 0, j] = m * RE[0, j] - w * u0 * b[j]
                d_r[i, 1, j] = m * RE[1, j] - w * u1 * b[j]
                d_params[i, 0, 2 + j] = -d_r[i, 0, j]
                d_params[i, 1, 2 + j] = -d_r[i, 1, j]
            d_params[i, 0, 0] = 1.0
            d_params[i, 1, 1] = 1.0
            d_params[i, 0, 5] = m * v0
            d_params[i, 1, 5] = m * v1
        else:
            s = pi[0]
            points[i, 0] = s * u0 + pi[1]
            points[i, 1] = s * u1 + pi[2]
            for j in range(3):
                d_r[i, 0, j] = s * RE[0, j]
                d_r[i, 1, j] = s * RE[1, j]
            d_params[i, 0, 0] = u0
            d_params[i, 1, 0] = u1
            d_params[i, 0, 1] = 1.0
            d_params[i, 1, 2] = 1.0
            d_params[i, 0, 3] = s * v0
            d_params[i, 1, 3] = s * v1
    return points, d_r, d_params


@njit(cache=True)
def landmark_rows_kernel(
    r: FloatArray, idx: np.ndarray, points: FloatArray, c: float, E: FloatArray, pi: FloatArray, b: FloatArray,
    sid: float, sod: float, perspective: bool, free: np.ndarray, border: np.ndarray,
    rho: FloatArray, Jv: FloatArray, Jb: FloatArray, start: int,
) -> None:
    """One view's landmark rows written in place from row ``start`` (two per landmark, column then row):
    ρ = c (p(r_j) − p̂), ∂ρ/∂r_j = c ∂p/∂r into Jv[:, :3] and c ∂p/∂π of the estimated parameters
    ``free`` into their border columns ``border`` of Jb; p and its derivatives are ``_project_kernel``'s
    (ψ = π's last entry), c = √w/s₀ (1/mm · √(N·mm)·mm, as ``problem``'s landmark rows)."""
    k = idx.shape[0]
    rk = np.empty((k, 3))
    for i in range(k):
        for j in range(3):
            rk[i, j] = r[idx[i], j]
    pts, d_r, d_p = _project_kernel(rk, E, pi[pi.shape[0] - 1], pi, b, sid, sod, perspective)
    for i in range(k):
        for a in range(2):
            row = start + 2 * i + a
            rho[row] = c * (pts[i, a] - points[i, a])
            for j in range(3):
                Jv[row, j] = c * d_r[i, a, j]
            for f in range(free.shape[0]):
                Jb[row, border[f]] = c * d_p[i, a, free[f]]


NO_BEAM = np.zeros(3)
"""The beam argument of a weak-perspective camera, which has none (the kernels take arrays only)."""


def project(
    camera: Camera, values: ArrayLike, r: ArrayLike, e_c: ArrayLike, e_r: ArrayLike, beam: FloatArray | None = None
) -> Projected:
    """Project points r (k, 3) with the camera's parameters ``values`` (module docstring); ``beam``:
    the camera's ``beam_direction`` when the caller holds it (a perspective camera's, computed once)."""
    pi = np.ascontiguousarray(values, dtype=float)  # C-contiguous throughout: one compiled signature
    r = np.ascontiguousarray(r, dtype=float).reshape(-1, 3)
    E = np.array((e_c, e_r), dtype=float)
    if camera.kind == "weak":
        return Projected(*_project_kernel(r, E, float(pi[-1]), pi, NO_BEAM, 1.0, 1.0, False))
    b = np.ascontiguousarray(camera.beam_direction(E[0], E[1]) if beam is None else beam, dtype=float)
    return Projected(*_project_kernel(r, E, float(pi[-1]), pi, b, float(camera.sid_mm), float(camera.sod_mm), True))
