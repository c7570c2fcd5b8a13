"""Projection of patient points by a view's ``Camera`` and its analytic derivatives.

Weak perspective, parameters π = [s, T_c, T_r, ψ]:
    q = E r (E = [e_c; e_r]),  p = s Rot(ψ) q + T,
    ∂p/∂r = s Rot(ψ) E,  ∂p/∂s = Rot(ψ) q,  ∂p/∂T = I,  ∂p/∂ψ = s Rot'(ψ) q.
Perspective (pinhole), π = [c_c, c_r, o_x, o_y, o_z, ψ]: with d = r − o, q = E d, z = b·d
(b the beam, source → detector) and m = SID / (SOD + z),
    p = c + m Rot(ψ) q,
    ∂p/∂r = m Rot(ψ) E − (m² / SID) (Rot(ψ) q) bᵀ = −∂p/∂o,  ∂p/∂c = I,  ∂p/∂ψ = m Rot'(ψ) q,
with Rot'(ψ) = dRot/dψ = [[−sin ψ, −cos ψ], [cos ψ, −sin ψ]]. The derivatives are checked against
finite differences in ``tests/engine/test_cameras.py``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
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


def _rot(psi: float) -> tuple[FloatArray, FloatArray]:
    c, s = math.cos(psi), math.sin(psi)
    return np.array([[c, -s], [s, c]]), np.array([[-s, -c], [c, -s]])


def project(
    camera: Camera, values: ArrayLike, r: ArrayLike, e_c: ArrayLike, e_r: ArrayLike, beam: FloatArray | None = None
) -> Projected:
    """Project points r (k, 3) with the camera's parameters ``values`` (module docstring); ``beam``:
    the camera's ``beam_direction`` when the caller holds it (a perspective camera's, computed once)."""
    pi = np.asarray(values, dtype=float)
    r = np.asarray(r, dtype=float).reshape(-1, 3)
    E = np.array((e_c, e_r), dtype=float)
    k = len(r)
    Rot, dRot = _rot(float(pi[-1]))
    if camera.kind == "weak":
        s = float(pi[0])
        q = r @ E.T
        u = q @ Rot.T
        points = s * u + pi[1:3]
        d_r = np.empty((k, 2, 3))
        d_r[:] = s * (Rot @ E)
        d_params = np.zeros((k, 2, 4))
        d_params[:, :, 0] = u
        d_params[:, 0, 1] = 1.0
        d_params[:, 1, 2] = 1.0
        d_params[:, :, 3] = s * (q @ dRot.T)
        return Projected(points, d_r, d_params)
    b = camera.beam_direction(E[0], E[1]) if beam is None else beam
    d = r - pi[2:5]
    q = d @ E.T
    z = d @ b
    m = camera.sid_mm / (camera.sod_mm + z)
    u = q @ Rot.T
    points = pi[:2] + m[:, None] * u
    d_r = m[:, None, None] * (Rot @ E)[None] - ((m * m / camera.sid_mm)[:, None] * u)[:, :, None] * b[None, None, :]
    d_params = np.zeros((k, 2, 6))
    d_params[:, 0, 0] = 1.0
    d_params[:, 1, 1] = 1.0
    d_params[:, :, 2:5] = -d_r
    d_params[:, :, 5] = m[:, None] * (q @ dRot.T)
    return Projected(points, d_r, d_params)
