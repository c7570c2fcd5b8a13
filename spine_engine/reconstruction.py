"""The public entry point: a job payload in, a reconstruction result out.

``register(payload)`` validates the payload, builds the generic rod for the chosen elastic
profile, converts the landmarks to detector mm, fixes the weak perspective of each view,
registers the rod to the landmarks (``registration.fit``) and reports strains and measures.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import __version__
from .anatomy import Profile, RestModel, load_profile, rest_model
from .clinical import landmark_arrays, observed_frontal_tilts, place_without_boundary, size_factor, with_observations
from .errors import FieldError, FitFailed, InvalidInput
from .fit import FitOutput, RegistrationProblem, RodParameters, Solution, ViewData, initial_configuration
from .fit import solve as solve_fit
from .frames import axial_rotation_deg
from .levels import LEVEL_INDEX, LEVELS
from .measures import compute_measures, frontal_tilts
from .models import (
    EngineInfo,
    FitReport,
    JobPayload,
    LateralView,
    PAView,
    PedicleResidual,
    RegistrationResult,
    Residual,
    TiltResidual,
    Unreliable,
    VertebraResult,
    ViewProjection,
)
from .projection import estimate_projection, image_axes
from .rod import strains
from .rotations import rotation_between
from .tilt_prior import load_tilt_prior
from .validation import validate_payload


@dataclass(frozen=True)
class Problem:
    """A validated registration problem in arrays: what ``solve`` needs, nothing of JSON."""

    views: list[ViewData]
    projections: dict[str, ViewProjection]
    top: tuple[np.ndarray, np.ndarray]
    bottom: tuple[np.ndarray, np.ndarray]
    boundary_estimated: bool = False
    """True when T1 and L5 were placed from the generic model (no boundary in the payload)."""
    unreliable: list[Unreliable] = field(default_factory=list)
    """Quantities that then come from the generic model only (``clinical.place_without_boundary``)."""
    tilt_prior: bool = False
    """Whether the tilt prior's observations were added."""
    tilt_sources: dict[str, list[str]] = field(default_factory=dict)
    """Per view, the source ("corners" or "prior") of each tilt observation, in order."""
    offset_sources: dict[str, list[str]] = field(default_factory=dict)
    """Per view, the source of each offset-point observation ("inferior_midpoint", "image_left",
    "image_right" pedicle), in order."""
    observed_tilt_deg: np.ndarray | None = None
    """(17,) frontal tilt of the PA corner lines, NaN where a level has no corners (None: no corners)."""
    observed_endplate_tilt_deg: np.ndarray | None = None
    """(17, 2) superior and inferior endplate tilts from the PA corners, NaN where none."""


def _pose(pose: Any) -> tuple[np.ndarray, np.ndarray]:
    """Position (3,) and rotation matrix with the directors as columns, R = [d1 d2 d3]."""
    return np.asarray(pose.position, dtype=float), np.asarray(pose.directors, dtype=float).T


def _orthonormalise(R: np.ndarray) -> np.ndarray:
    """Nearest rotation to R (polar decomposition): directors valid within 1e-3 become exact."""
    U, _, Vt = np.linalg.svd(R)
    return np.asarray(U @ Vt)


def _detector_mm(view: PAView | LateralView) -> np.ndarray:
    """Landmarks as (column, row) in detector mm; px × DICOM pixel spacing [row, column]. A landmark
    given by its corners counts as its superior endplate midpoint (``clinical.landmark_arrays``)."""
    return landmark_arrays(view).points.reshape(-1, 2)


def build_view(
    name: str,
    view: PAView | LateralView,
    weight: float,
    top: tuple[np.ndarray, np.ndarray],
    bottom: tuple[np.ndarray, np.ndarray],
    placed: tuple[float, np.ndarray] | None = None,
) -> tuple[ViewData, ViewProjection]:
    """One view's landmarks in detector mm with its weak perspective (given, estimated from the
    boundary, or ``placed``: the (scale, translation) of a spine placed without boundary)."""
    e_c, e_r = image_axes(view.patient_orientation)
    indices = np.array([LEVEL_INDEX[lm.level] for lm in view.landmarks], dtype=int)
    points = _detector_mm(view)
    if placed is not None:
        scale, translation = placed[0], np.asarray(placed[1], dtype=float)
        estimated = view.projection is None
    elif view.projection is not None:
        scale = float(view.projection.scale)
        translation = np.asarray(view.projection.translation, dtype=float)  # detector mm
        estimated = False
    else:
        ends = [int(np.flatnonzero(indices == 0)[0]), int(np.flatnonzero(indices == len(LEVELS) - 1)[0])]
        try:
            scale, translation = estimate_projection(
                np.stack([top[0], bottom[0]]), points[ends], e_c, e_r
            )
        except ValueError as exc:
            raise InvalidInput([FieldError((name, "landmarks"), str(exc), "projection_not_estimable")]) from None
        estimated = True
    data = ViewData(
        name=name,
        indices=indices,
        points=points,
        e_c=e_c,
        e_r=e_r,
        scale=float(scale),
        translation=np.asarray(translation, dtype=float),
        weight=weight,
    )
    if view.projection is not None:
        scale_source = "given"
    elif placed is not None and name == "pa":
        scale_source = "prior"  # the generic spine's length (clinical.place_without_boundary)
    else:
        scale_source = "estimated"
    projection = ViewProjection(
        scale=float(scale),
        translation=(float(translation[0]), float(translation[1])),
        estimated=estimated,
        scale_source=scale_source,
        pixel_spacing_calibration=view.pixel_spacing_calibration,
    )
    return data, projection


def build_problem(model: JobPayload, profile: Profile) -> Problem:
    """Arrays of a validated payload: views in detector mm, projections, fixed boundary poses,
    and the clinical observations (corner tilts, pedicles, tilt prior; ``clinical``).

    Without ``boundary`` the T1 and L5 poses and the projections come from
    ``clinical.place_without_boundary``."""
    pa_arrays = landmark_arrays(model.pa)
    has_lateral = model.lateral is not None and bool(model.lateral.landmarks)
    lateral_arrays = landmark_arrays(model.lateral) if model.lateral is not None and has_lateral else None
    use_prior = model.options.tilt_prior if model.options.tilt_prior is not None else model.boundary is None
    prior = load_tilt_prior() if use_prior else None
    placement = None
    if model.boundary is None:
        try:
            placement = place_without_boundary(model, profile, pa_arrays, lateral_arrays, prior)
        except ValueError as exc:
            raise InvalidInput([FieldError(("pa", "landmarks"), str(exc), "spine_not_placeable")]) from None
        top, bottom = placement.top, placement.bottom
    else:
        p1, R1 = _pose(model.boundary.T1)
        p5, R5 = _pose(model.boundary.L5)
        top, bottom = (p1, _orthonormalise(R1)), (p5, _orthonormalise(R5))
    views, projections, sources, offsets = [], {}, {}, {}
    pa, pa_projection = build_view(
        "pa", model.pa, profile.fit_weight_pa, top, bottom, None if placement is None else placement.pa
    )
    size = size_factor(profile, pa)
    pa, sources["pa"], offsets["pa"] = with_observations(pa, pa_arrays, size=size, prior=prior)
    views.append(pa)
    projections["pa"] = pa_projection
    if model.lateral is not None and lateral_arrays is not None:
        lateral, lateral_projection = build_view(
            "lateral",
            model.lateral,
            profile.fit_weight_lateral,
            top,
            bottom,
            None if placement is None else placement.lateral,
        )
        lateral, sources["lateral"], offsets["lateral"] = with_observations(
            lateral, lateral_arrays, size=size, prior=None
        )
        views.append(lateral)
        projections["lateral"] = lateral_projection
    observed, endplates = observed_frontal_tilts(pa_arrays, pa.e_c, pa.e_r)
    return Problem(
        views=views,
        projections=projections,
        top=top,
        bottom=bottom,
        boundary_estimated=placement is not None,
        unreliable=[] if placement is None else placement.unreliable,
        tilt_prior=prior is not None and "prior" in sources["pa"],
        tilt_sources=sources,
        offset_sources=offsets,
        observed_tilt_deg=observed,
        observed_endplate_tilt_deg=endplates,
    )


def rod_parameters(rest: RestModel) -> RodParameters:
    """Rest lengths, rest strains u⁰, v⁰ of the generic shape, and stiffness of the rod."""
    u0, v0 = strains(rest.positions, rest.rotations, rest.ds)
    return RodParameters(ds=rest.ds, u0=u0, v0=v0, alpha=rest.alpha, beta=rest.beta)


def projected_arc_scale(rest_positions: np.ndarray, view: ViewData) -> float:
    """Length scale of the rest rod from one view: the landmarks' polyline length in patient mm
    (image distances / s) over that of the rest rod's projection through the same levels.

    With all 17 PA landmarks it compares the projected arc lengths, so lateral curvature is
    counted; with T1 and L5 alone it compares the projected chords.
    """
    rest_2d = np.stack([rest_positions[view.indices] @ view.e_c, rest_positions[view.indices] @ view.e_r], axis=1)
    rest_arc = float(np.linalg.norm(np.diff(rest_2d, axis=0), axis=1).sum())
    image_arc = float(np.linalg.norm(np.diff(view.points / view.scale, axis=0), axis=1).sum())
    return image_arc / rest_arc


def patient_rest_model(profile: Profile, problem: Problem) -> RestModel:
    """The generic rod turned and scaled to the patient.

    It is turned rigidly so that its T1→L5 chord has the direction of the patient's (known from
    the boundary), then scaled so that its projection on the PA view is as long as the PA
    landmarks' polyline. Strains do not depend on the turn; the scale sets the rest lengths.
    """
    generic = rest_model(profile)
    turn = rotation_between(
        generic.positions[-1] - generic.positions[0], problem.bottom[0] - problem.top[0]
    )
    turned = generic.positions @ turn.T
    scale = projected_arc_scale(turned, problem.views[0])
    scaled = rest_model(profile, length_scale=scale)
    return dataclasses.replace(
        scaled, positions=scaled.positions @ turn.T, rotations=np.einsum("ij,njk->nik", turn, scaled.rotations)
    )


def solve_solution(problem: Problem, profile: Profile) -> tuple[Solution, RestModel]:
    """Register the patient-scaled generic rod to the landmarks of ``problem``: the solver's
    ``Solution`` (optimum, residuals, Jacobian and parameter layout for the Laplace approximation)."""
    rest = patient_rest_model(profile, problem)
    init_r, init_R = initial_configuration(rest.positions, rest.rotations, problem.views, problem.top, problem.bottom)
    fit_problem = RegistrationProblem(rod_parameters(rest), problem.views, problem.top, problem.bottom)
    return solve_fit(fit_problem, init_r, init_R), rest


def solve(problem: Problem, profile: Profile) -> tuple[FitOutput, RestModel]:
    """Register the patient-scaled generic rod to the landmarks of ``problem``."""
    solution, rest = solve_solution(problem, profile)
    return solution.output, rest


def _vertebrae(out: FitOutput, rest: RestModel, observed_tilt_deg: np.ndarray | None = None) -> list[VertebraResult]:
    angles = np.degrees(out.u * rest.ds[:, None])
    rotation = axial_rotation_deg(out.rotations)
    tilt, from_corners = frontal_tilts(out.rotations, observed_tilt_deg)
    vertebrae = []
    for i, level in enumerate(LEVELS):
        has_segment = i < len(LEVELS) - 1
        vertebrae.append(
            VertebraResult(
                level=level,  # type: ignore[arg-type]
                position=tuple(out.positions[i].tolist()),
                directors=tuple(tuple(row) for row in out.rotations[i].T.tolist()),  # type: ignore[arg-type]
                u=tuple(out.u[i].tolist()) if has_segment else None,
                v=tuple(out.v[i].tolist()) if has_segment else None,
                sagittal_bending_deg=float(angles[i, 0]) if has_segment else None,
                frontal_bending_deg=float(angles[i, 1]) if has_segment else None,
                twist_deg=float(angles[i, 2]) if has_segment else None,
                axial_rotation_deg=float(rotation[i]),
                frontal_tilt_deg=float(tilt[i]),
                frontal_tilt_source="corners" if from_corners[i] else "model",
            )
        )
    return vertebrae


def _fit_report(problem: Problem, out: FitOutput, runtime_ms: float) -> FitReport:
    residuals = [
        Residual(view=view.name, level=LEVELS[idx], residual_mm=float(res))  # type: ignore[arg-type]
        for view in problem.views
        for idx, res in zip(view.indices, out.residuals_mm[view.name], strict=True)
    ]
    return FitReport(
        residuals=residuals,
        mean_registration_error_mm=float(np.mean(out.residuals_mm["pa"])),
        energy_fit=out.energy_fit,
        energy_internal=out.energy_internal,
        iterations=out.iterations,
        converged=out.converged,
        runtime_ms=runtime_ms,
        pa=problem.projections["pa"],
        lateral=problem.projections.get("lateral"),
        boundary="estimated" if problem.boundary_estimated else "given",
        unreliable=list(problem.unreliable),
        tilt_prior=problem.tilt_prior,
        tilt_residuals=[
            TiltResidual(view=view.name, level=LEVELS[idx], source=src, residual_deg=float(res))
            for view in problem.views
            if view.tilt_indices is not None
            for idx, src, res in zip(
                view.tilt_indices, problem.tilt_sources[view.name], out.tilt_residuals_deg[view.name], strict=True
            )
        ],
        pedicle_residuals=[
            PedicleResidual(view="pa", level=LEVELS[idx], side=src, residual_mm=float(res))
            for view in problem.views
            if view.offset_indices is not None
            for idx, src, res in zip(
                view.offset_indices, problem.offset_sources[view.name], out.offset_residuals_mm[view.name], strict=True
            )
            if src in ("image_left", "image_right")
        ],
    )


def register_model(model: JobPayload) -> RegistrationResult:
    """Reconstruct the spine of a validated payload; raise ``FitFailed`` when it does not converge."""
    profile = load_profile(model.options.profile)
    start = time.perf_counter()
    try:
        with np.errstate(over="raise", invalid="raise", divide="raise"):
            problem = build_problem(model, profile)
            out, rest = solve(problem, profile)
    except (ArithmeticError, FloatingPointError, ValueError, np.linalg.LinAlgError) as exc:
        # A degenerate geometry (e.g. landmarks that no spine can have) breaks the numerics.
        raise FitFailed(f"the registration broke down numerically: {exc}") from None
    runtime_ms = (time.perf_counter() - start) * 1e3
    if not out.converged:
        raise FitFailed(
            f"the registration did not converge in {out.iterations} iterations "
            f"(E_f = {out.energy_fit:.4g} N·mm, E_I = {out.energy_internal:.4g} N·mm)",
            iterations=out.iterations,
        )
    if not (np.all(np.isfinite(out.positions)) and np.all(np.isfinite(out.rotations))):
        raise FitFailed("the registration produced non-finite coordinates", iterations=out.iterations)
    return RegistrationResult(
        vertebrae=_vertebrae(out, rest, problem.observed_tilt_deg),
        measures=compute_measures(
            out.positions,
            out.rotations,
            observed_tilt_deg=problem.observed_tilt_deg,
            observed_endplate_tilt_deg=problem.observed_endplate_tilt_deg,
        ),
        fit=_fit_report(problem, out, runtime_ms),
        engine=EngineInfo(version=__version__, profile=profile.name),
    )


def register(payload: dict[str, Any]) -> dict[str, Any]:
    """Reconstruct a spine from a job payload (the JSON body of ``POST /v1/jobs``).

    Returns the ``result`` object a client reads back (``RegistrationResult`` as JSON types).
    Raises ``InvalidInput`` naming every bad field, or ``FitFailed`` when the fit fails.
    """
    return register_model(validate_payload(payload)).model_dump(mode="json")
