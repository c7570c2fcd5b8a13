"""A weak-perspective film that may have come from a point source: its perspective read from the films.

A view whose payload states neither SID and SOD nor ``projection_model`` is fitted in weak
perspective (``models.Acquisition``), yet a CR or DX film is projected from a point source. Its
perspective is a nuisance parameter η = 1/SOD (1/mm) of the weak camera (``cameras``):

    p = T + s Rot(ψ) (q̄ + (q − q̄) / (1 + η z)),   q = E r,  z = b·(r − r̄),

with E = [e_c; e_r] the film's axes, b = e_c × e_r along the beam, r̄ the vertebrae's centre and q̄
its projection, where the central ray is taken to pass (a ray Δ off it adds s Rot(ψ) Δ z η, a
product of two small unknowns that this linear reading leaves out: about 0.75 mm for Δ = 40 mm,
z = 30 mm at 1.6 m). At η = 0 this is the weak camera, and

    ∂p/∂η |η=0 = −s Rot(ψ) (q − q̄) z,

so a landmark row ρ = c (p − p̂) (c = √w/s₀, ``problem``) gets the column c ∂p/∂η, and an offset
point's row the column component of it at r_j + R_j o. The prior is η ~ N(0, σ_η²), one prior row
√(κ/2) η/σ_η per view, with σ_η the η of full-spine radiography's geometry
(``reconstruction.POINT_SOURCE_ETA_SD``): a parallel beam lies at the prior's mean, a film taken
at 1.8 m one SD off.

With two films the fit's own unknowns are at their optimum, so one Gauss–Newton step of the problem
with η added, x ← x − H⁻¹g (g zero but in η, H the Gauss–Newton Hessian of the augmented rows), is
the posterior mean of the linearised problem: it moves the spine as far as the films show a point
source. It is taken when some view's η̂ lies ``POINT_SOURCE_GATE`` of its SD or more from 0;
otherwise the spine stays where the weak fit put it. Either way the Laplace covariance is read with
η free under its prior, so the SDs keep the share of a perspective the films cannot rule out.
One film leaves η to its prior (the depths it would be read against come from the rod's prior), so
only fits of two views take it (``reconstruction.fit_patient_rod``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from ..rod import strains
from ..rotations import exp_so3
from .types import FitOutput, FloatArray, PointSourceReading, Solution, ViewData
from .uncertainty import weighted_gram

POINT_SOURCE_GATE = 2.75
"""Smallest |η̂|/SD(η̂), over the views, at which the fit takes the step toward the point source the
films show: the smallest on a grid of 2, 2.25 … 3 at which the parallel-beam films of the clinic
bench's cases (a) and (b) keep their shape error on VerSe dev and the dev synthetic spines (``spine
bench clinic --split dev``, noise seeds 0–2; at 2 their mean rose by up to 0.01 mm, η's noise moving
the spine). There, case (h)'s point-source films went from 1.34 to 1.29 mm on VerSe dev and from 1.55
to 1.32 mm on the synthetic spines (at 2: 1.22 and 1.27 mm; docs/engine.md)."""


def image_derivative(points: FloatArray, centre: FloatArray, view: ViewData, camera: FloatArray) -> FloatArray:
    """(k, 2) ∂p/∂η at η = 0 of patient points (k, 3) through the view's weak camera [s, T_c, T_r, ψ]
    about ``centre`` r̄ (module docstring): detector mm per (1/mm)."""
    s, psi = float(camera[0]), float(camera[-1])
    E = np.stack([np.asarray(view.e_c, dtype=float), np.asarray(view.e_r, dtype=float)])
    b = np.cross(E[0], E[1])
    q = (points - centre) @ E.T
    z = (points - centre) @ b
    rot = np.array([[math.cos(psi), -math.sin(psi)], [math.sin(psi), math.cos(psi)]])
    return -s * (q * z[:, None]) @ rot.T


def point_source_columns(solution: Solution, views: Sequence[ViewData]) -> FloatArray:
    """(n_rows, len(views)): ∂ρ/∂η_v of every row of ``solution`` at η = 0 for each view v of ``views``
    (module docstring); the rows of other views, of the rod and of the priors are 0."""
    kinds = np.array(solution.row_kinds)
    centre = solution.positions.mean(axis=0)
    columns = np.zeros((len(kinds), len(views)))
    for v, view in enumerate(views):
        camera = np.asarray(solution.cameras[view.name], dtype=float)
        c = math.sqrt(float(view.weight)) / view.get_camera().reference_scale
        d = image_derivative(solution.positions[np.asarray(view.indices)], centre, view, camera)
        columns[kinds == f"landmark:{view.name}", v] = c * d.reshape(-1)
        if view.n_offsets:
            j = np.asarray(view.offset_indices)
            o = np.asarray(view.offset_vectors, dtype=float)
            at = solution.positions[j] + np.einsum("nij,nj->ni", solution.rotations[j], o)
            columns[kinds == f"offset:{view.name}", v] = c * image_derivative(at, centre, view, camera)[:, 0]
    return columns


def augmented(solution: Solution, views: Sequence[ViewData], sd: float) -> Solution:
    """``solution`` with one column η_v per view of ``views`` and its prior row √(κ/2)/σ_η (residual 0
    at η = 0), the rows' kind "camera"."""
    columns = point_source_columns(solution, views)
    n_rows, n_params = solution.jacobian.shape
    k = len(views)
    J = np.zeros((n_rows + k, n_params + k))
    J[:n_rows, :n_params] = solution.jacobian
    J[:n_rows, n_params:] = columns
    J[n_rows:, n_params:] = math.sqrt(0.5 * float(solution.energy_unit)) / sd * np.eye(k)
    residuals = np.concatenate([solution.residuals, np.zeros(k)])
    return solution._replace(
        jacobian=J,
        residuals=residuals,
        weights=np.ones(len(residuals)),
        row_kinds=(*solution.row_kinds, *(["camera"] * k)),
        x=np.concatenate([solution.x, np.zeros(k)]),
    )


def with_point_source(
    solution: Solution,
    views: Sequence[ViewData],
    unstated: Sequence[str],
    ds: FloatArray,
    sd: float,
    gate: float = POINT_SOURCE_GATE,
) -> Solution:
    """``augmented`` with η (prior SD ``sd``, 1/mm) for the views named in ``unstated`` (of the fit's
    ``views``) and, when some |η̂_v|/SD ≥ ``gate``, the Gauss–Newton step δx (module docstring):
    positions r_j + δr_j, rotations
    R_j exp(hat δθ_j), every estimated camera parameter plus its share, and in the output the linearised
    problem's residuals ρ + J δx (energies, landmark and offset residuals, tilts) and the strains u, v
    of the stepped configuration over the rod's rest lengths ``ds`` (mm). Stepped or not, the output's
    ``point_source`` holds each view's η̂, its SD and whether the spine moved; ``solution`` itself when
    no view is in ``unstated`` or the augmented Hessian is not positive definite."""
    chosen = [view for view in views if view.name in unstated]
    if not chosen:
        return solution
    aug = augmented(solution, chosen, sd)
    J = aug.jacobian
    k = len(chosen)
    n = J.shape[1]
    unit = np.zeros((n, k))
    unit[n - k :, :] = np.eye(k)
    try:  # only H⁻¹'s last k columns: g is zero but in η
        H = weighted_gram(J, np.ones(len(J)))
        cov_eta = cho_solve(cho_factor(H, lower=True, check_finite=False), unit, check_finite=False)
    except np.linalg.LinAlgError:  # a curvature the weak fit's own Laplace step would refuse too
        return solution
    dx = -cov_eta @ (J[:, n - k :].T @ aug.residuals)
    eta = dx[n - k :]
    eta_sd = np.sqrt(np.diag(cov_eta[n - k :]) * 0.5 * float(solution.energy_unit))
    steps = bool(np.max(np.abs(eta) / eta_sd) >= gate)
    readings = {view.name: PointSourceReading(float(e), float(d), steps)
                for view, e, d in zip(chosen, eta, eta_sd, strict=True)}  # fmt: skip
    if not steps:
        return aug._replace(output=dataclasses.replace(aug.output, point_source=readings))
    layout = solution.layout
    r = aug.positions.copy()
    R = aug.rotations.copy()
    for j in range(len(r)):
        if layout.position[j, 0] >= 0:
            r[j] = r[j] + dx[layout.position[j]]
            R[j] = R[j] @ exp_so3(dx[layout.rotation[j]])
    cameras = {name: np.array(values, dtype=float) for name, values in aug.cameras.items()}
    for view in views:
        names = view.get_camera().names
        for parameter, column in layout.views.get(view.name, {}).items():
            cameras[view.name][names.index(parameter)] += dx[column]
    residuals = aug.residuals + J @ dx
    output = dataclasses.replace(_stepped_output(aug, views, r, R, residuals, cameras, ds), point_source=readings)
    return aug._replace(positions=r, rotations=R, cameras=cameras, residuals=residuals, x=aug.x + dx, output=output)


def _stepped_output(
    solution: Solution,
    views: Sequence[ViewData],
    r: FloatArray,
    R: FloatArray,
    residuals: FloatArray,
    cameras: dict[str, FloatArray],
    ds: FloatArray,
) -> FitOutput:
    """The ``FitOutput`` of the stepped configuration. A landmark or offset row ρ = √w (p − p̂)/s₀ is
    ρ/√w patient mm (landmarks: the distance of each pair; offsets: signed), a tilt row α = ρ/√w_m rad."""
    kinds = np.array(solution.row_kinds)
    data = np.array([kind.startswith(("landmark:", "offset:", "tilt:")) for kind in solution.row_kinds])
    distances: dict[str, FloatArray] = {}
    offsets: dict[str, FloatArray] = {}
    tilts: dict[str, FloatArray] = {}
    for view in views:
        root_w = math.sqrt(float(view.weight))
        pairs = residuals[kinds == f"landmark:{view.name}"].reshape(-1, 2) / root_w
        distances[view.name] = np.sqrt(np.einsum("ij,ij->i", pairs, pairs))
        if view.n_offsets:
            offsets[view.name] = residuals[kinds == f"offset:{view.name}"] / root_w
        if view.n_tilts:
            alpha = residuals[kinds == f"tilt:{view.name}"] / np.sqrt(np.asarray(view.tilt_weights, dtype=float))
            tilts[view.name] = np.degrees(alpha)
    rod = residuals[kinds == "rod"]
    u, v = strains(r, R, ds)
    return dataclasses.replace(
        solution.output,
        positions=r,
        rotations=R,
        u=u,
        v=v,
        energy_fit=float(residuals[data] @ residuals[data]),
        energy_internal=float(rod @ rod),
        residuals_mm=distances,
        offset_residuals_mm=offsets,
        tilt_residuals_deg=tilts,
        cameras=cameras,
    )
