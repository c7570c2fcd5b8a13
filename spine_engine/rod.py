"""Discrete Cosserat rod: strains of a chain of vertebral frames, and its elastic energy.

A configuration is a stack of positions r (..., N, 3) in mm and rotations R (..., N, 3, 3) whose
columns are the directors [d1 d2 d3] (d1 ≈ patient left, d2 ≈ anterior, d3 = caudal tangent).
Segment i (i = 0..N−2) joins vertebra i to vertebra i+1 and has rest length Δs_i in mm.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .rotations import exp_so3, log_so3

FloatArray = NDArray[np.float64]


def strains(r: ArrayLike, R: ArrayLike, ds: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Angular and linear strains of each segment, in the frame of its upper vertebra.

    u_i = vee(log(R_iᵀ R_{i+1})) / Δs_i   (rad/mm; u1 bending about d1 = sagittal, u2 about d2 =
                                           coronal/lateral, u3 twist about d3)
    v_i = R_iᵀ (r_{i+1} − r_i) / Δs_i      (dimensionless; v1, v2 shear, v3 stretch)

    Shapes: r (..., N, 3), R (..., N, 3, 3), ds (N−1,) → u, v (..., N−1, 3).
    """
    r = np.asarray(r, dtype=float)
    R = np.asarray(R, dtype=float)
    inv_ds = 1.0 / np.asarray(ds, dtype=float)[:, None]
    Rt = R[..., :-1, :, :].swapaxes(-1, -2)
    dr = r[..., 1:, :] - r[..., :-1, :]
    v = np.einsum("...ij,...j->...i", Rt, dr) * inv_ds
    u = log_so3(Rt @ R[..., 1:, :, :]) * inv_ds
    return u, v


def internal_energy(
    u: ArrayLike,
    v: ArrayLike,
    u0: ArrayLike,
    v0: ArrayLike,
    alpha: ArrayLike,
    beta: ArrayLike,
    ds: ArrayLike,
) -> float:
    """Potential energy of the rod (Li et al. 2009, eq. 6), in N·mm.

    E_I = ½ Σ_i Δs_i Σ_k [α_ik (u_ik − u0_ik)² + β_ik (v_ik − v0_ik)²]

    u, u0 in rad/mm and α in N·mm² (bending/twisting stiffness); v, v0 dimensionless and β in N
    (shear/axial stiffness); Δs in mm. All strain and stiffness arrays are (N−1, 3), ds (N−1,).
    """
    du = np.asarray(u, dtype=float) - np.asarray(u0, dtype=float)
    dv = np.asarray(v, dtype=float) - np.asarray(v0, dtype=float)
    per_segment = np.sum(np.asarray(alpha) * du * du + np.asarray(beta) * dv * dv, axis=-1)
    return float(0.5 * np.sum(np.asarray(ds, dtype=float) * per_segment))


def configuration_from_strains(
    r0: ArrayLike, R0: ArrayLike, u: ArrayLike, v: ArrayLike, ds: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """The configuration whose strains are (u, v), starting from vertebra 0 at (r0, R0).

    Inverse of ``strains``: R_{i+1} = R_i exp(hat(Δs_i u_i)), r_{i+1} = r_i + Δs_i R_i v_i.
    Shapes: r0 (3,), R0 (3, 3), u, v (N−1, 3), ds (N−1,) → r (N, 3) in mm, R (N, 3, 3).
    """
    ds = np.asarray(ds, dtype=float)
    steps = exp_so3(np.asarray(u, dtype=float) * ds[:, None])
    chords = np.asarray(v, dtype=float) * ds[:, None]
    n = len(ds) + 1
    r = np.empty((n, 3))
    R = np.empty((n, 3, 3))
    r[0] = r0
    R[0] = R0
    for i in range(n - 1):
        r[i + 1] = r[i] + R[i] @ chords[i]
        R[i + 1] = R[i] @ steps[i]
    return r, R
