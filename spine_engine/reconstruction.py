"""The public entry point: a job payload in, a reconstruction result out.

``register(payload)`` validates the payload, turns it into arrays (``prepare_inputs``: landmarks
in detector mm, each view's camera, the boundary and the clinical observations), registers the
patient-scaled generic rod to the landmarks (``fit_patient_rod``, the solver of ``spine_engine.fit``)
and reports strains and measures.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import TypeAdapter
from threadpoolctl import ThreadpoolController

from .anatomy import (
    Profile,
    RestModel,
    length_correction,
    load_profile,
    population_prior,
    rest_model,
    rest_shape_unit,
)
from .clinical import (
    PA_MAGNIFICATION_PRIOR,
    LandmarkArrays,
    PinholeGeometry,
    calibrated_magnification,
    detector_spacing,
    landmark_arrays,
    observed_frontal_tilts,
    pinhole_geometry,
    place_without_boundary,
    polyline_length,
    projected_length,
    size_factor,
    with_observations,
)
from .errors import FieldError, FitFailed, InvalidInput
from .fit import (
    Camera,
    FitOutput,
    Pose,
    PosePrior,
    RegistrationProblem,
    RodParameters,
    Solution,
    ViewData,
    as_pose,
    initial_configuration,
    linearise,
    minimise,
    nearest_rotation,
    solve,
)
from .fit.types import CENTRAL_RAY_PRIOR_SD_MM, DEPTH_PRIOR_SD_MM
from .fit.uncertainty import (
    AXIAL_ROTATION_SD_CAP_DEG,
    PRIOR_ONLY_LENKE,
    PRIOR_ONLY_MEASURES,
    PriorOnlyReading,
    Uncertainty,
    calibration,
    reported_uncertainty,
)
from .fit.unstated_projection import POINT_SOURCE_GATE, with_point_source
from .frames import axial_rotation_deg
from .levels import LEVEL_INDEX, LEVELS
from .measures import compute_measures, frontal_tilts, lenke_probabilities, lenke_with_kyphoses
from .models import (
    FULL_SPINE_SID_MM,
    LANDMARK_SD_MM_DEFAULT,
    SPINE_TO_DETECTOR_MM,
    Assumption,
    AssumptionName,
    EngineInfo,
    FitReport,
    JobPayload,
    LateralView,
    Measures,
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
from .sagittal_reading import ReadingModel, kyphoses_deg, load_reading_model, read_inclinations_deg
from .tilt_prior import TiltPrior, load_tilt_prior
from .validation import validate_payload
from .version import __version__

GAUGE_POSITION_SD_MM = 1000.0
"""No boundary: T1's position is held at the patient origin by a Gaussian of this SD (mm): it fixes
the translation that the estimated film translations leave free (a gauge, not information: 1 m is
far beyond any landmark's pull)."""
GAUGE_ROTATION_SD_DEG = 30.0
"""No boundary: T1's directors are held near their placement by a Gaussian of this SD (degrees): it
fixes the rotations that a single view leaves (almost) free; two views determine them."""
BEAMS = {"pa": np.array([0.0, -1.0, 0.0]), "lateral": np.array([1.0, 0.0, 0.0])}
"""Beam direction (source → detector, LPS) of a perspective view: the PA film is a postero-anterior
projection (beam toward the patient's anterior, −y) and the lateral film a left lateral (the patient's
left side against the detector, beam toward +x), the scoliosis series' usual set-up. The image's
display (its patient orientation) does not say from which side the beam came."""
EXACT_SD = (1e-3, 1e-4)
"""A pose given without SDs in a soft boundary (the other pose has SDs): held within 1 µm and 0.1 mrad."""


@dataclass(frozen=True)
class ViewSetup:
    """How one view's projection enters the fit, for the report."""

    model: str
    """"weak_perspective" or "perspective"."""
    scale_source: str
    pixel_spacing_calibration: str | None
    assumed: tuple[Assumption, ...] = ()
    """What the set-up took because the view did not give it (``FitReport.assumed``)."""
    projection_unstated: bool = False
    """A weak perspective the payload did not state (neither SID and SOD nor ``projection_model``): the
    film may come from a point source (``fit.unstated_projection``)."""


@dataclass(frozen=True)
class RegistrationInputs:
    """A validated payload in arrays, ready to register: views in detector mm with their cameras, the
    boundary and its pose priors, the clinical observations; what ``fit_patient_rod`` needs, nothing of JSON."""

    views: list[ViewData]
    projections: dict[str, ViewProjection]
    top: Pose
    bottom: Pose
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
    observed_sagittal: np.ndarray | None = None
    """(17,) bool: the vertebrae whose sagittal tilt is observed: the lateral view's corners, or T1
    and L5 given exactly (``boundary`` "given")."""
    frontal_observed: np.ndarray | None = None
    """(17,) bool: the levels whose frontal tilt the input shows (``frontal_observed_levels``); a Cobb
    angle that depends on another level is the prior's (``_unseen_cobb``). None: every level."""
    frontal_tilt_seen: np.ndarray | None = None
    """(17,) bool: the levels whose own frontal tilt the input shows (``frontal_tilt_seen_levels``); a
    Cobb curve is the film's only where its end vertebrae and their outer neighbours are such levels
    (``_unseen_cobb``). None: every level."""
    boundary: str = "given"
    """"given" (T1 and L5 exact), "soft" (with SDs) or "estimated" (none: every vertebra free)."""
    pose_priors: tuple[PosePrior, ...] = ()
    """Soft poses and the gauge (all vertebrae free unless ``boundary`` is "given")."""
    setups: dict[str, ViewSetup] = field(default_factory=dict)


def _initial_weak_with_boundary(
    name: str, arrays: LandmarkArrays, e_c: np.ndarray, e_r: np.ndarray, top: Pose, bottom: Pose
) -> tuple[float, np.ndarray]:
    """Starting scale and translation of a view from the boundary: the closed form
    (``projection.estimate_projection``) on the T1 and L5 landmarks when both are given, else on the
    landmarked levels against the T1→L5 chord interpolated by level."""
    n = len(LEVELS)
    ends = [np.flatnonzero(arrays.indices == 0), np.flatnonzero(arrays.indices == n - 1)]
    try:
        if len(ends[0]) and len(ends[1]):
            return estimate_projection(
                np.array((top.position, bottom.position)), arrays.points[[ends[0][0], ends[1][0]]], e_c, e_r
            )
        t = arrays.indices / (n - 1.0)
        chord = (1.0 - t)[:, None] * top.position + t[:, None] * bottom.position
        return estimate_projection(chord, arrays.points, e_c, e_r)
    except ValueError as exc:
        raise InvalidInput([FieldError((name, "landmarks"), str(exc), "projection_not_estimable")]) from None


def mid_plane_offset(profile: Profile, beam: np.ndarray) -> float:
    """b·(g_mid − ḡ), mm: how far along the beam b the mid-spine vertebra (T9) of the profile's
    generic rest shape (length scale 1, 434 mm for ``default``) lies from its centroid. SOD runs to
    the spine's mid-plane (DESIGN.md), the plane of the centroid; the depth prior holds T9, which on
    the PA lies 16.6 mm nearer the source (−16.6 for ``default``: T9 is near the kyphosis' apex)."""
    positions = rest_shape_unit(profile)[1]
    return float(beam @ (positions[len(positions) // 2] - positions.mean(axis=0)))


def make_camera(
    view: PAView | LateralView,
    name: str,
    initial: tuple[float, np.ndarray],
    e_c: np.ndarray,
    e_r: np.ndarray,
    mid_depth: float,
    scale_prior: bool,
    profile: Profile,
    landmark_centre: np.ndarray,
) -> tuple[Camera | None, ViewSetup]:
    """The view's camera (None: the weak perspective ``initial``, fixed) and how it was set up.

    * ``projection`` given: that weak perspective, fixed ("given");
    * ``acquisition`` with SID and SOD, or ``projection_model`` "perspective" (the geometry it lacks
      assumed, ``clinical.pinhole_geometry``; "prior"): a pinhole (``fit.cameras``), magnification SID/SOD at the plane
      through o; c = the central ray when given, else the centre of ``acquisition.image_size`` (recorded as
      assumed, ``_ray_at_centre``), else estimated (o then moves along the beam only),
      o estimated ("acquisition") with the prior b·(r_mid − o) ~ N(d̄, σ²), σ 30 mm, or the assumed SOD's
      ``clinical.ASSUMED_DEPTH_SD_MM``, d̄ = ``mid_plane_offset`` of
      ``profile`` (the spine's mid-plane at SOD), o starting there (``mid_depth``: r_mid's initial b·r);
    * else a weak perspective with T estimated and s from the acquisition's magnification (fixed,
      "acquisition"), else estimated: on the PA with the prior ``clinical.PA_MAGNIFICATION_PRIOR``
      when ``scale_prior`` ("prior"), else from the data ("estimated": the lateral's scale is tied to
      the PA's by the vertical axis both films share).
    The PA film's in-plane rotation ψ is 0 by convention (it defines the patient's frontal plane);
    the lateral's is estimated (Gaussian prior, SD 2°).
    """
    spc = view.pixel_spacing_calibration
    if view.projection is not None:
        return None, ViewSetup("weak_perspective", "given", spc)
    s0, T0 = float(initial[0]), np.asarray(initial[1], dtype=float)
    rotate = name != "pa"
    acq = view.acquisition
    geometry = pinhole_geometry(view, name)
    if acq is not None and geometry is not None:
        sid, sod = geometry.sid_mm, geometry.sod_mm
        m0 = sid / sod
        b = BEAMS[name]
        E = np.stack((e_c, e_r))
        ray = acq.central_ray
        sod_assumed = geometry.depth_prior_sd_mm is not None
        depth_sd = geometry.depth_prior_sd_mm if geometry.depth_prior_sd_mm is not None else DEPTH_PRIOR_SD_MM
        size_assumed = acq.distance_source_to_detector_mm is None and sod_assumed
        assumed: tuple[Assumption, ...] = (
            (_geometry_assumed(name, geometry, depth_sd, size_assumed),) if geometry.assumed else ()
        )
        if ray is None and acq.image_size is not None:
            ray = (0.5 * acq.image_size[0], 0.5 * acq.image_size[1])
            assumed = (*assumed, _ray_at_centre(name, ray, view.units))
        if ray is not None:
            c = np.asarray(ray, dtype=float) * detector_spacing(view)
            o_plane = (c - T0) / m0
            free = np.array([False, False, True, True, True, rotate])
        else:
            c = T0.copy()
            o_plane = np.zeros(2)
            free = np.array([True, True, *(np.abs(b) > 0.5), rotate])
        mid_offset = mid_plane_offset(profile, b)
        o = E.T @ o_plane + b * (mid_depth - mid_offset)
        ray_prior = None if not free[0] else (np.asarray(landmark_centre, dtype=float), CENTRAL_RAY_PRIOR_SD_MM)
        if ray_prior is not None:
            assumed = (*assumed, _assumption("central_ray_near_landmarks", name))
        camera = Camera(
            "perspective", np.array([c[0], c[1], *o, 0.0]), free, sid_mm=sid, sod_mm=sod, beam=b,
            depth_prior_mean_mm=mid_offset, central_ray_prior=ray_prior, depth_prior_sd_mm=depth_sd,
            depth_from_prior=sod_assumed,
        )
        # an assumed SOD sets the scale; an ERMF without SID leaves only the SID assumed
        return camera, ViewSetup("perspective", "prior" if sod_assumed else "acquisition", spc, assumed)
    unstated = acq is None or acq.projection_model is None
    known = acq.magnification if acq is not None and acq.magnification is not None else calibrated_magnification(view)
    if known is not None:
        values = np.array([known, T0[0], T0[1], 0.0])
        return Camera("weak", values, np.array([False, True, True, rotate])), ViewSetup(
            "weak_perspective", "acquisition", spc, projection_unstated=unstated
        )
    prior = PA_MAGNIFICATION_PRIOR if (scale_prior and name == "pa") else None
    camera = Camera("weak", np.array([s0, T0[0], T0[1], 0.0]), np.array([True, True, True, rotate]), scale_prior=prior)
    if prior is None:
        return camera, ViewSetup("weak_perspective", "estimated", spc, projection_unstated=unstated)
    assumed = (_assumption("magnification_prior", name),)
    return camera, ViewSetup("weak_perspective", "prior", spc, assumed, projection_unstated=unstated)


_ASSUMPTION_REASONS: dict[AssumptionName, str] = {
    "central_ray_near_landmarks": "SID and SOD were given without a central ray or an image size: the ray was "
    "estimated under a prior within 50 mm (SD) of the landmarks' centre",
    "magnification_prior": "no magnification, geometry or projection was given: the film's magnification "
    "comes from the full-spine prior 1.125 ± 0.035 (SID/SOD 1800/1600)",
    "standing_orientation": "no lateral film: the spine's lean and its turn about the vertical come from the "
    "prior of a standing patient facing the detector (SD about 11° and 5°)",
    "population_sagittal_shape": "no lateral film: kyphosis and lordosis come from the population prior; "
    "their SDs are at least the population's, a measure one PA film does not predict is the population's "
    "mean, and the kyphosis is read mostly from how much shorter the PA film shows each segment than the "
    "population's sagittal shapes predict",
    "projection_unstated": "the film states neither SID and SOD nor projection_model: it is read in weak "
    "perspective, and how far it comes from a point source (1/SOD) is read from the two films under a prior "
    f"about the parallel beam whose SD is full-spine radiography's 1/{FULL_SPINE_SID_MM - SPINE_TO_DETECTOR_MM:g} "
    f"mm⁻¹; the spine moves toward the point source the films show when it lies {POINT_SOURCE_GATE:g} SD or more "
    "from the parallel beam, and the SDs keep what they cannot rule out (send projection_model, or SID and SOD, "
    "when known)",
    "population_axial_rotation": "no pedicles: each vertebra's axial rotation is the population's mean given "
    "the frontal curves (toward each curve's convexity, at the apex about a third of its Cobb angle for a "
    "thoracic apex and a quarter below T11, 0 at its end vertebrae), with the population's SD; T1 and L5 "
    "given exactly keep the payload's; the directors stay the fit's",
}


def _assumption(name: AssumptionName, view: str | None) -> Assumption:
    """The record of a prior that decided a number (``FitReport.assumed``), with its reason in words."""
    return Assumption(name=name, view=view, reason=_ASSUMPTION_REASONS[name])  # type: ignore[arg-type]


_SIZE_FROM_ASSUMED_SID = (
    "; the spine's size is then right only as far as that geometry is the film's (a film taken at 1000 mm "
    "reads 11 % too large, docs/accuracy.md): send the SID (acquisition.distance_source_to_detector_mm, "
    "DICOM (0018,1110)) when it is known"
)
"""What ``_geometry_assumed`` adds when nothing states the size (no SID, SOD, ERMF or calibrated mm)."""


def _geometry_assumed(name: str, geometry: PinholeGeometry, depth_sd_mm: float, size_assumed: bool) -> Assumption:
    """The record of a point-source film whose SID or SOD was assumed (``clinical.pinhole_geometry``),
    the spine's distance from the source held with ``depth_sd_mm``; ``size_assumed``: nothing states the
    spine's size (no SID, and the SOD held by the assumed depth prior: no SOD, ERMF or calibrated mm)."""
    return Assumption(
        name="full_spine_geometry",
        view=name,  # type: ignore[arg-type]
        reason=f"projection_model perspective without SID or SOD: the film was projected from a point source "
        f"with SID {geometry.sid_mm:g} mm and SOD {geometry.sod_mm:g} mm (full-spine radiography), the spine's "
        f"distance from the source held within {depth_sd_mm:g} mm (SD)"
        + (_SIZE_FROM_ASSUMED_SID if size_assumed else ""),
    )


def _ray_at_centre(name: str, ray: tuple[float, float], units: str) -> Assumption:
    """The record of a central ray taken at the image's centre: DICOM's SID runs from the source to
    the detector's centre (PS3.3 C.8.7.6; the DX Positioning Module C.8.11.5 gives no central-ray
    position), and a full-spine film is taken with the beam centred on the detector."""
    return Assumption(
        name="central_ray_at_image_centre",
        view=name,  # type: ignore[arg-type]
        reason=f"SID and SOD were given without a central ray: the ray was taken at the image's centre "
        f"({ray[0]:g}, {ray[1]:g}) {units}, half of acquisition.image_size",
    )


def _view_data(
    name: str,
    view: PAView | LateralView,
    arrays: LandmarkArrays,
    weight: float,
    camera: Camera | None,
    initial: tuple[float, np.ndarray],
    axes: tuple[np.ndarray, np.ndarray],
) -> ViewData:
    """The view's landmarks (detector mm) with its weight w·(σ_ref/σ)², σ its ``landmark_sd_mm``;
    ``axes``: its image axes (e_c, e_r) (``projection.image_axes``)."""
    e_c, e_r = axes
    scale = camera.reference_scale if camera is not None else float(initial[0])
    sd = view.sd_mm
    return ViewData(
        name=name,
        indices=np.asarray(arrays.indices, dtype=int),
        points=arrays.points,
        e_c=e_c,
        e_r=e_r,
        scale=float(scale),
        translation=np.asarray(initial[1], dtype=float),
        weight=weight * (LANDMARK_SD_MM_DEFAULT / sd) ** 2,
        landmark_sd_mm=sd,
        camera=camera,
    )


def _pose_priors(
    model: JobPayload, top: Pose, bottom: Pose, boundary: str, profile: Profile
) -> tuple[PosePrior, ...]:
    """No boundary: the gauge (T1 at the origin, ``GAUGE_POSITION_SD_MM``) and the orientation prior
    of a standing patient facing the detector: T1's and L5's directors near their placement (the
    generic spine's sagittal inclination unless a lateral film gave the depths, no rotation about
    the vertical) with the profile's SDs about d1 (the lean), d2 (frontal tilt, a gauge) and d3 (the
    spin about the vertical), ``anatomy.PopulationPrior.orientation_sd_deg``; without a population
    prior T1's directors within ``GAUGE_ROTATION_SD_DEG``. Else the soft poses."""
    if boundary == "estimated":
        prior = population_prior(profile)
        if prior is None:
            sd = np.radians(GAUGE_ROTATION_SD_DEG)
            return (PosePrior(0, Pose(np.zeros(3), top.rotation), GAUGE_POSITION_SD_MM, sd),)
        sd_top, sd_bottom = (np.radians(prior.orientation_sd_deg[lv]) for lv in ("T1", "L5"))
        return (
            PosePrior(0, Pose(np.zeros(3), top.rotation), GAUGE_POSITION_SD_MM, sd_top),
            PosePrior(len(LEVELS) - 1, Pose(bottom.position - top.position, bottom.rotation), GAUGE_POSITION_SD_MM,
                      sd_bottom),
        )
    if boundary != "soft":
        return ()
    assert model.boundary is not None
    priors = []
    for index, pose in ((0, model.boundary.T1), (len(LEVELS) - 1, model.boundary.L5)):
        p = as_pose(pose)
        if pose.position_sd_mm is None or pose.directors_sd_deg is None:
            sd_r, sd_t = EXACT_SD
        else:
            sd_r, sd_t = float(pose.position_sd_mm), float(np.radians(pose.directors_sd_deg))
        priors.append(PosePrior(index, Pose(p.position, nearest_rotation(p.rotation)), sd_r, sd_t))
    return tuple(priors)


def prepare_inputs(
    model: JobPayload, profile: Profile, tilt_prior: TiltPrior | None = None
) -> RegistrationInputs:
    """Arrays of a validated payload: views in detector mm with their cameras, the boundary mode and
    its pose priors, the initial end poses, and the clinical observations (corner tilts, pedicles,
    tilt prior; ``clinical``).

    Without ``boundary`` every vertebra is free (gauge: ``GAUGE_POSITION_SD_MM``), starting from
    ``clinical.place_without_boundary``; with a soft boundary every vertebra is free and T1 and L5
    are held by Gaussians; with an exact one T1 and L5 are fixed (the paper). ``tilt_prior``: the
    prior used when the payload asks for one (default the shipped ``tilt_prior.load_tilt_prior()``;
    the AASCE bench passes the priors it cross-validates)."""
    pa_arrays = landmark_arrays(model.pa)
    has_lateral = model.lateral is not None and bool(model.lateral.landmarks)
    lateral_arrays = landmark_arrays(model.lateral) if model.lateral is not None and has_lateral else None
    use_prior = model.options.tilt_prior if model.options.tilt_prior is not None else model.boundary is None
    prior = None if not use_prior else tilt_prior if tilt_prior is not None else load_tilt_prior()
    if model.boundary is None:
        boundary = "estimated"
    elif model.boundary.T1.soft or model.boundary.L5.soft:
        boundary = "soft"
    else:
        boundary = "given"
    placement = None
    if model.boundary is None:
        try:
            placement = place_without_boundary(model, profile, pa_arrays, lateral_arrays, prior)
        except ValueError as exc:
            raise InvalidInput([FieldError(("pa", "landmarks"), str(exc), "spine_not_placeable")]) from None
        top, bottom = placement.top, placement.bottom
    else:
        t1, l5 = as_pose(model.boundary.T1), as_pose(model.boundary.L5)
        top = Pose(t1.position, nearest_rotation(t1.rotation))
        bottom = Pose(l5.position, nearest_rotation(l5.rotation))
    mid = len(LEVELS) // 2
    views: list[ViewData] = []
    projections: dict[str, ViewProjection] = {}
    sources: dict[str, list[str]] = {}
    offsets: dict[str, list[str]] = {}
    setups: dict[str, ViewSetup] = {}
    size = 1.0
    for name, view, arrays, weight in (
        ("pa", model.pa, pa_arrays, profile.fit_weight_pa),
        ("lateral", model.lateral, lateral_arrays, profile.fit_weight_lateral),
    ):
        if view is None or arrays is None:
            continue
        e_c, e_r = image_axes(view.patient_orientation)
        initial: tuple[float, np.ndarray]
        if view.projection is not None:
            initial = (float(view.projection.scale), np.asarray(view.projection.translation, dtype=float))
        elif placement is not None:
            placed = placement.pa if name == "pa" else placement.lateral
            assert placed is not None
            initial = placed
        else:
            initial = _initial_weak_with_boundary(name, arrays, e_c, e_r, top, bottom)
        beam = BEAMS[name]
        if placement is not None and placement.centreline is not None:
            mid_depth = float(placement.centreline[mid] @ beam)
        else:
            mid_depth = float(0.5 * (top.position + bottom.position) @ beam)
        camera, setup = make_camera(
            view, name, initial, e_c, e_r, mid_depth, scale_prior=boundary != "given", profile=profile,
            landmark_centre=np.nanmean(arrays.points, axis=0),
        )
        data = _view_data(name, view, arrays, weight, camera, initial, (e_c, e_r))
        if name == "pa":
            size = size_factor(profile, data)
        data, sources[name], offsets[name] = with_observations(
            data, arrays, size=size, prior=prior if name == "pa" else None,
            prior_tilts=placement.pa_prior_tilts_deg if placement is not None and name == "pa" else None,
        )
        views.append(data)
        setups[name] = setup
        projections[name] = ViewProjection(
            scale=float(data.scale),
            translation=(float(data.translation[0]), float(data.translation[1])),
            estimated=camera is not None and bool(camera.free.any()),
            model=setup.model,  # type: ignore[arg-type]
            scale_source=setup.scale_source,  # type: ignore[arg-type]
            pixel_spacing_calibration=setup.pixel_spacing_calibration,  # type: ignore[arg-type]
        )
    read = point_source_views(views, setups)
    setups = {name: _with_unstated_projection(name, setup) if name in read else setup for name, setup in setups.items()}
    pa = views[0]
    observed, endplates = observed_frontal_tilts(pa_arrays, pa.e_c, pa.e_r)
    observed_sagittal = np.zeros(len(LEVELS), dtype=bool)
    if lateral_arrays is not None:
        observed_sagittal[lateral_arrays.indices[lateral_arrays.has_corners]] = True
    if boundary == "given":  # T1's and L5's directors are given exactly
        observed_sagittal[[0, len(LEVELS) - 1]] = True
    unreliable = [] if placement is None else list(placement.unreliable)
    frontal_observed = frontal_observed_levels(pa_arrays.indices, boundary)
    tilt_seen = frontal_tilt_seen_levels(frontal_observed, pa_arrays.indices[pa_arrays.has_corners], boundary)
    return RegistrationInputs(
        views=views,
        projections=projections,
        top=top,
        bottom=bottom,
        boundary_estimated=placement is not None,
        unreliable=unreliable,
        tilt_prior=prior is not None and "prior" in sources["pa"],
        tilt_sources=sources,
        offset_sources=offsets,
        observed_tilt_deg=observed,
        observed_endplate_tilt_deg=endplates,
        observed_sagittal=observed_sagittal,
        frontal_observed=frontal_observed,
        frontal_tilt_seen=tilt_seen,
        boundary=boundary,
        pose_priors=_pose_priors(model, top, bottom, boundary, profile),
        setups=setups,
    )


def point_source_views(views: Sequence[ViewData], setups: dict[str, ViewSetup]) -> list[str]:
    """The views whose point source the fit reads (``fit.unstated_projection``): those whose projection
    the payload did not state (``ViewSetup.projection_unstated``), when there are two films; one film
    leaves its perspective to the prior."""
    if len(views) != 2:
        return []
    return [view.name for view in views if setups[view.name].projection_unstated]


def _with_unstated_projection(name: str, setup: ViewSetup) -> ViewSetup:
    """``setup`` with the ``projection_unstated`` assumption recorded."""
    return dataclasses.replace(setup, assumed=(*setup.assumed, _assumption("projection_unstated", name)))


def frontal_observed_levels(pa_indices: np.ndarray, boundary: str) -> np.ndarray:
    """(17,) bool: the levels whose frontal tilt the input shows: the levels the PA view landmarks, T1
    and L5 when the boundary gives their directors exactly (``boundary`` "given"), and a level between
    two such levels (one landmark missing in a run: its tilt is the chord of its two neighbours').

    A vertebra's frontal tilt is read from the landmarks around it: its corners, or the curve its
    point and its neighbours' draw. Where two or more levels in a row have no landmark (beyond the
    film's first or last, or a gap: a film of T1, T9 and L5), the tilts are the rod's interpolation or
    extrapolation under its prior, whose mean frontal shape is straight; the Laplace SD of an angle
    there is the prior's spread read at the prior weight calibrated for whole films, too small (the 24
    VerSe dev spines' PA landmarks cut to T1, T9 and L5, no lateral: largest angles 5–27° below the
    whole film's, SDs of 7.1–8.6°, 95 % intervals covering 79 %). A Cobb angle ending on such a level
    is not one the films show, nor is a largest angle sought over such levels (``_unseen_cobb``)."""
    landmarked = np.zeros(len(LEVELS), dtype=bool)
    landmarked[np.asarray(pa_indices, dtype=int)] = True
    if boundary == "given":
        landmarked[[0, len(LEVELS) - 1]] = True
    observed = landmarked.copy()
    observed[1:-1] |= landmarked[:-2] & landmarked[2:]
    return observed


def frontal_tilt_seen_levels(observed: np.ndarray, cornered: np.ndarray, boundary: str) -> np.ndarray:
    """(17,) bool: the levels whose own frontal tilt the input shows: a level with PA corners, T1 and
    L5 when the boundary gives their directors exactly, and a level of ``observed``
    (``frontal_observed_levels``) whose neighbours on both sides are in ``observed`` too (T1 and L5:
    their one neighbour), as the tilt of a point-landmarked level is the chord of its neighbours.

    The first or last landmark of a film cut inside the spine (a point, no corners) is not such a
    level: the rod continues beyond it under its prior, whose mean frontal shape is straight, and
    turns its director toward straight (a synthetic double curve of 73° filmed T1–T8, no lateral:
    T8's tilt 2.8° against the truth's 14.5°; T1–T10: T10's 21.8° against 30.0°)."""
    observed = np.asarray(observed, dtype=bool)
    left = np.concatenate(([True], observed[:-1]))
    right = np.concatenate((observed[1:], [True]))
    seen = observed & left & right
    seen[np.asarray(cornered, dtype=int)] = True
    if boundary == "given":
        seen[[0, len(LEVELS) - 1]] = True
    return seen


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
    rest_arc = projected_length(rest_positions[view.indices], view.e_c, view.e_r)
    image_arc = polyline_length(view.points / view.scale)
    return image_arc / rest_arc


def patient_rest_model(profile: Profile, inputs: RegistrationInputs) -> RestModel:
    """The generic rod turned and scaled to the patient.

    It is turned rigidly so that its T1→L5 chord has the direction of the patient's (known from
    the boundary), then scaled so that its projection on the PA view is as long as the PA
    landmarks' polyline, times the population's ``anatomy.length_correction``; with one PA landmark
    (allowed only with its projection and T1 and L5 given exactly) so that its T1–L5 chord is as long
    as the given one. Strains do not depend on the turn; the scale sets the rest lengths.
    """
    generic = rest_shape_unit(profile)[1]
    chord = inputs.bottom[0] - inputs.top[0]
    turn = rotation_between(generic[-1] - generic[0], chord)
    turned = generic @ turn.T
    if len(inputs.views[0].indices) >= 2:
        scale = projected_arc_scale(turned, inputs.views[0]) * length_correction(profile)
    else:  # one PA landmark (its projection and T1, L5 given exactly): the given T1–L5 chord sets the size
        scale = float(np.linalg.norm(chord) / np.linalg.norm(generic[-1] - generic[0]))
    scaled = rest_model(profile, length_scale=scale)
    return dataclasses.replace(
        scaled, positions=scaled.positions @ turn.T, rotations=np.einsum("ij,njk->nik", turn, scaled.rotations)
    )


def fit_patient_rod(inputs: RegistrationInputs, profile: Profile) -> tuple[Solution, RestModel]:
    """Register the patient-scaled generic rod to the landmarks of ``inputs``: the solver's
    ``Solution`` (optimum, residuals, Jacobian and parameter layout for the Laplace approximation).
    With two films, a view whose projection the payload did not state gets its perspective η = 1/SOD
    under a prior (``fit.unstated_projection.with_point_source``)."""
    rest = patient_rest_model(profile, inputs)
    init_r, init_R = initial_configuration(rest.positions, rest.rotations, inputs.views, inputs.top, inputs.bottom)
    exact = inputs.boundary == "given"
    # κ: a landmark row √w_v (P r − p)/s₀ with w_v = w·(σ_ref/σ)² and noise SD σ has variance
    # w·σ_ref²/s₀² whatever σ, so E = κ(−log posterior) with κ = 2 w σ_ref²/s₀² (first view)
    first = inputs.views[0]
    weight = profile.fit_weight_pa if first.name == "pa" else profile.fit_weight_lateral

    params = rod_parameters(rest)

    def problem(views: Sequence[ViewData]) -> RegistrationProblem:
        return RegistrationProblem(
            params,
            views,
            inputs.top if exact else None,
            inputs.bottom if exact else None,
            pose_priors=inputs.pose_priors,
            energy_unit=2.0 * weight * LANDMARK_SD_MM_DEFAULT**2 / first.scale**2,
        )

    pinned = _pa_scale_pinned(inputs.views)
    if pinned is None:
        solution = solve(problem(inputs.views), init_r, init_R)
    else:
        held = problem(pinned)
        solution = linearise(held.with_views(inputs.views), minimise(held, init_r, init_R))
    unstated = point_source_views(inputs.views, inputs.setups)
    if unstated and solution.output.converged:
        solution = with_point_source(solution, inputs.views, unstated, params.ds, POINT_SOURCE_ETA_SD)
    return solution, rest


POINT_SOURCE_ETA_SD = 1.0 / (FULL_SPINE_SID_MM - SPINE_TO_DETECTOR_MM)
"""σ_η, 1/mm: the SD of the prior on η = 1/SOD of a film whose projection the payload did not state
(``fit.unstated_projection``): full-spine radiography's η (SOD 1600 mm, ``models.FULL_SPINE_SID_MM`` less
``models.SPINE_TO_DETECTOR_MM``) about the parallel beam's 0."""

PINNED_DEPTH_SD_MM = 0.1
"""SD of the depth prior that holds a point-source PA film's spine at its assumed distance from the
source with two films (``_pa_scale_pinned``), mm: 0.1 mm at 1600 mm is a magnification held to 0.006 %."""


def _pa_scale_pinned(views: Sequence[ViewData]) -> list[ViewData] | None:
    """The views with the PA's magnification held at its prior's mean, when two uncalibrated films
    (weak perspective, no geometry) leave it to that prior, or the PA's spine held at its assumed
    distance from the source (``PINNED_DEPTH_SD_MM``) when two point-source films do not state their
    SOD (``Camera.depth_from_prior``); else None.

    Neither film states the magnification: a spine c times larger under a magnification c times
    smaller makes the same images, so only the prior (``clinical.PA_MAGNIFICATION_PRIOR``) knows it
    and the mean of the posterior is the prior's. Estimated with the spine, it was pulled by the rod
    instead: by the rest length, which the PA film had already set at that mean, and by the shear
    rows, which shrink with the spine (docs/engine.md). The fit holds s at the mean; its uncertainty
    is still read with s free under the prior (``linearise``). With one film s stays free: held, the
    PA film's kyphosis was farther from the truth on VerSe (docs/engine.md)."""
    names = [view.name for view in views]
    pa = views[names.index("pa")] if "pa" in names else None
    if pa is None or "lateral" not in names or pa.camera is None:
        return None
    cam = pa.camera
    if cam.kind == "perspective" and cam.depth_from_prior:
        held_camera = dataclasses.replace(cam, depth_prior_sd_mm=PINNED_DEPTH_SD_MM)
        return [dataclasses.replace(pa, camera=held_camera) if view.name == "pa" else view for view in views]
    if cam.kind != "weak" or not cam.free[0] or cam.scale_prior is None:
        return None
    free = np.array(cam.free, dtype=bool)
    free[0] = False
    values = np.array(cam.values, dtype=float)
    values[0] = cam.scale_prior[0]
    held = dataclasses.replace(pa, camera=dataclasses.replace(cam, values=values, free=free))
    return [held if view.name == "pa" else view for view in views]



_VERTEBRA_LIST = TypeAdapter(list[VertebraResult])
"""Validates the 17 vertebra results in one call (cheaper than 17 model constructions)."""
_RESIDUAL_LIST = TypeAdapter(list[Residual])
"""Validates the landmark residual rows in one call."""
_TILT_RESIDUAL_LIST = TypeAdapter(list[TiltResidual])
"""Validates the tilt residual rows in one call."""
_PEDICLE_RESIDUAL_LIST = TypeAdapter(list[PedicleResidual])
"""Validates the pedicle residual rows in one call."""


def _vertebrae(
    out: FitOutput,
    rest: RestModel,
    observed_tilt_deg: np.ndarray | None = None,
    uncertainty: Uncertainty | None = None,
    axial_rotation: np.ndarray | None = None,
) -> list[VertebraResult]:
    """The 17 vertebra results: pose, strains u, v of the segment below (rad/mm, none for L5), its
    bending and twist angles u·Δs (degrees), axial rotation (the directors', or ``axial_rotation``
    (17,) degrees where given), frontal tilt and, with ``uncertainty``
    (``fit.uncertainty.reported_uncertainty``), the SDs of position and axial rotation."""
    n = len(LEVELS)
    angles = np.degrees(out.u * rest.ds[:, None]).tolist()
    tilt, from_corners = frontal_tilts(out.rotations, observed_tilt_deg)
    u, v = out.u.tolist(), out.v.tolist()
    segment: list[tuple[Any, Any, Any]] = [(u[i], v[i], angles[i]) for i in range(n - 1)]
    segment.append((None, None, (None, None, None)))
    position_sd: list[Any] = [None] * n if uncertainty is None else uncertainty.position_sd_mm.tolist()
    rotation_sd: list[Any] = [None] * n if uncertainty is None else uncertainty.axial_rotation_sd_deg.tolist()
    return _VERTEBRA_LIST.validate_python(
        [
            {
                "level": level,
                "position": position,
                "directors": directors,
                "u": u_i,
                "v": v_i,
                "sagittal_bending_deg": angle[0],
                "frontal_bending_deg": angle[1],
                "twist_deg": angle[2],
                "axial_rotation_deg": rotation,
                "frontal_tilt_deg": tilt_i,
                "frontal_tilt_source": "corners" if corners else "model",
                "position_sd_mm": pos_sd,
                "axial_rotation_sd_deg": rot_sd,
            }
            for level, position, directors, (u_i, v_i, angle), rotation, tilt_i, corners, pos_sd, rot_sd in zip(
                LEVELS,
                out.positions.tolist(),
                np.swapaxes(out.rotations, 1, 2).tolist(),
                segment,
                (axial_rotation_deg(out.rotations) if axial_rotation is None else axial_rotation).tolist(),
                tilt.tolist(),
                from_corners.tolist(),
                position_sd,
                rotation_sd,
                strict=True,
            )
        ]
    )


def _projection_report(inputs: RegistrationInputs, out: FitOutput, name: str) -> ViewProjection | None:
    """The view's projection at the optimum: weak perspective s, T, ψ; perspective SID/SOD, c, ψ, o and b,
    so that a client (the figure, the SR's Cobb lines) projects the model as the fit did."""
    given = inputs.projections.get(name)
    view = next((v for v in inputs.views if v.name == name), None)
    if given is None or view is None or view.camera is None or name not in out.cameras:
        return given
    values = out.cameras[name]
    update: dict[str, Any] = {"rotation_deg": float(np.degrees(values[-1]))}
    if view.camera.kind == "weak":
        update |= {"scale": float(values[0]), "translation": (float(values[1]), float(values[2]))}
    else:
        camera = view.camera
        update |= {
            "scale": camera.reference_scale,
            "translation": (float(values[0]), float(values[1])),
            "source_to_detector_mm": float(camera.sid_mm),
            "source_to_patient_mm": float(camera.sod_mm),
            "central_ray_point_mm": tuple(float(v) for v in values[2:5]),
            "beam_direction": tuple(float(v) for v in camera.beam_direction(view.e_c, view.e_r)),
        }
    return given.model_copy(update=update)


def _sagittal_assumptions(inputs: RegistrationInputs) -> list[Assumption]:
    """Without a lateral film (no boundary) the lean, the spin and the sagittal shape come from priors."""
    if inputs.boundary != "estimated" or "lateral" in inputs.setups:
        return []
    return [_assumption("standing_orientation", None), _assumption("population_sagittal_shape", None)]


def _fit_report(
    inputs: RegistrationInputs, out: FitOutput, runtime_ms: float, uncertainty: Uncertainty | None = None,
    population_axial_rotation: bool = False,
) -> FitReport:
    """The fit's report; ``uncertainty``: the SDs reported (their scale and misfit ratio), None when
    not computed; ``population_axial_rotation``: the axial rotations reported are the population's
    (``population_axial_rotation_deg``), which ``assumed`` then names."""
    residuals = _RESIDUAL_LIST.validate_python(
        [
            {"view": view.name, "level": LEVELS[idx], "residual_mm": res}
            for view in inputs.views
            for idx, res in zip(view.indices.tolist(), out.residuals_mm[view.name].tolist(), strict=True)
        ]
    )
    return FitReport(
        residuals=residuals,
        # np.mean's arithmetic (add.reduce, then ÷ k) without its wrapper
        mean_registration_error_mm=float(np.add.reduce(out.residuals_mm["pa"]) / len(out.residuals_mm["pa"])),
        energy_fit=out.energy_fit,
        energy_internal=out.energy_internal,
        iterations=out.iterations,
        converged=out.converged,
        runtime_ms=runtime_ms,
        pa=_projection_report(inputs, out, "pa"),
        lateral=_projection_report(inputs, out, "lateral"),
        boundary=inputs.boundary,  # type: ignore[arg-type]
        unreliable=list(inputs.unreliable),
        tilt_prior=inputs.tilt_prior,
        tilt_residuals=_TILT_RESIDUAL_LIST.validate_python(
            [
                {"view": view.name, "level": LEVELS[idx], "source": src, "residual_deg": res}
                for view in inputs.views
                if view.tilt_indices is not None
                for idx, src, res in zip(
                    view.tilt_indices.tolist(), inputs.tilt_sources[view.name],
                    np.asarray(out.tilt_residuals_deg[view.name], dtype=float).tolist(), strict=True,
                )
            ]
        ),
        pedicle_residuals=_PEDICLE_RESIDUAL_LIST.validate_python(
            [
                {"view": "pa", "level": LEVELS[idx], "side": src, "residual_mm": res}
                for view in inputs.views
                if view.offset_indices is not None
                for idx, src, res in zip(
                    view.offset_indices.tolist(), inputs.offset_sources[view.name],
                    np.asarray(out.offset_residuals_mm[view.name], dtype=float).tolist(), strict=True,
                )
                if src in ("image_left", "image_right")
            ]
        ),
        uncertainty_scale=None if uncertainty is None else uncertainty.scale,
        landmark_misfit_ratio=None if uncertainty is None else uncertainty.landmark_misfit_ratio,
        assumed=[_with_point_source_found(a, out) for setup in inputs.setups.values() for a in setup.assumed]
        + _sagittal_assumptions(inputs)
        + ([_assumption("population_axial_rotation", None)] if population_axial_rotation else []),
    )


def _with_point_source_found(assumption: Assumption, out: FitOutput) -> Assumption:
    """``projection_unstated``'s record with what the two films showed of its view's point source
    (``FitOutput.point_source``): |η̂| ± SD as 1/SOD in m⁻¹ (full-spine radiography's SOD of 1600 mm
    reads 0.62), and whether the spine moved toward it; any other record as it is."""
    found = out.point_source.get(assumption.view or "") if assumption.name == "projection_unstated" else None
    if found is None:
        return assumption
    read = f"1/SOD read {abs(found.eta_per_mm) * 1e3:.2f} ± {found.sd_per_mm * 1e3:.2f} m⁻¹"
    typical = f"full-spine radiography's {POINT_SOURCE_ETA_SD * 1e3:.2f} m⁻¹ is SOD {1.0 / POINT_SOURCE_ETA_SD:.0f} mm"
    words = (
        f"here the films showed a point source and the spine was moved toward it: {read} ({typical})"
        if found.stepped
        else f"here the films showed none that moved the spine: {read}, within {POINT_SOURCE_GATE:g} SD of the "
        f"parallel beam on both films ({typical})"
    )
    return assumption.model_copy(update={"reason": f"{assumption.reason}; {words}"})


@functools.cache
def _blas() -> ThreadpoolController:
    return ThreadpoolController()


def _one_blas_thread() -> contextlib.AbstractContextManager[object]:
    """BLAS held to one thread for a call: nothing to do when every BLAS library already runs one
    (``OPENBLAS_NUM_THREADS=1``, as the service and the benchmarks run), else threadpoolctl's
    limit, which costs about 20 µs a call to set and restore."""
    blas = _blas()
    if all(lib.num_threads == 1 for lib in blas.lib_controllers if lib.user_api == "blas"):
        return contextlib.nullcontext()
    return blas.limit(limits=1, user_api="blas")


def register_model(
    model: JobPayload, tilt_prior: TiltPrior | None = None, profile: Profile | None = None
) -> RegistrationResult:
    """Reconstruct the spine of a validated payload; raise ``FitFailed`` when it does not converge.
    ``tilt_prior``: as ``prepare_inputs``'s (None: the shipped prior); ``profile``: the rod's profile
    (None: the one the payload's ``options.profile`` names), for calibrations that score a profile
    before writing it.

    BLAS runs on one thread here: the fit's matrices are about 110 × 110, too small to share, and a
    threaded BLAS spinning on both cores made a call 5–6 times dearer in CPU (docs/performance.md)."""
    with _one_blas_thread():
        return _register_model(model, tilt_prior, load_profile(model.options.profile) if profile is None else profile)


LANDMARK_SD_CONTRADICTED = 4.0
"""Largest ratio of a view's landmark residual, RMS per image coordinate (√(mean d²/2), d the distance
from each landmark to the fitted spine's projection, detector mm), to its landmark SD (stated, else
``LANDMARK_SD_MM_DEFAULT``) that a fit takes as consistent with it. Measured with the noise stated as
drawn (``spine bench clinic --split dev --seeds 3 --noise-mm N``, column "max residual / SD"; 1320 fits
per N): at most 0.90 in every case at 0.5, 1, 2 and 3 mm ((h), point-source films sent without their
projection, at most 0.79: ``fit.unstated_projection`` reads their perspective); all of AASCE
training's radiographs at the default SD read at most 0.54 (midpoints) and 0.90 (corners) (``spine
bench aasce --split training``, column "max_residual_to_sd").
Beyond 4 the landmarks contradict the SD: a noise stated ten or a hundred times too small (1 mm stated
as 0.01 mm reads about 36), clicks no spine passes through, or a geometry the films do not have (a
lateral ERMF 10–30 % off the PA's scale; films from a point source stated as parallel rays,
``projection_model`` "weak_perspective", with less than about 0.25 mm of stated noise)."""


def residual_per_coordinate_mm(distances: Sequence[float] | np.ndarray) -> float:
    """RMS per image coordinate of landmark residuals given as 2D distances d (mm): √(mean d²/2)."""
    return math.sqrt(float(np.mean(np.square(distances))) / 2.0)


def _check_landmark_sd(model: JobPayload, out: FitOutput) -> None:
    """Raise ``InvalidInput`` naming each view's ``landmark_sd_mm`` that its landmarks contradict
    (``LANDMARK_SD_CONTRADICTED``): the fit would report intervals as narrow as the SD says, or
    crawl without converging when the SD makes the landmarks' weight overwhelm every prior."""
    errors = []
    for name in ("pa", "lateral"):
        view = getattr(model, name)
        distances = out.residuals_mm.get(name)
        if view is None or distances is None or len(distances) == 0:
            continue
        sd = view.sd_mm
        rms = residual_per_coordinate_mm(distances)
        if rms > LANDMARK_SD_CONTRADICTED * sd:
            said = "stated" if view.landmark_sd_mm is not None else "assumed (the default; state landmark_sd_mm)"
            errors.append(FieldError(
                (name, "landmark_sd_mm"),
                f"the {'PA' if name == 'pa' else name} landmarks lie {rms:.3g} mm (RMS per coordinate) from the spine "
                f"fitted to them, {rms / sd:.3g} times the landmark SD {said}, {sd:g} mm: the SD is too small for "
                "these landmarks, some are not where their labels say, or a view's stated geometry (acquisition, "
                "projection) is not its film's",
                "landmark_sd_contradicted",
            ))  # fmt: skip
    if errors:
        raise InvalidInput(errors)


END_ON_PROJECTION = 0.5
"""Shortest projection on its film, as a fraction of its length, of the director whose tilt a view's
corners observe (d1 on the PA) that a fit takes as seen: below it the vertebra is turned 60° or more
out of the film, end-on, where the corners' tilt says almost nothing of its pose and the tilt rows'
derivative (∝ 1/|a|, ``fit.pose_rows``) breaks the Laplace approximation (intervals collapse to
micrometres). Real corners stay far from it: over AASCE training's radiographs the smallest such
projection is 0.65 (``spine bench aasce --split training``, column "smallest_projection"). A fit that
meets corners only by turning vertebrae end-on has corners that contradict the rest of its landmarks
(tilts tens of degrees off the curve the points draw)."""


def _check_corner_tilts(inputs: RegistrationInputs, out: FitOutput) -> None:
    """Raise ``InvalidInput`` naming each view whose corners the fit meets only by turning vertebrae
    end-on to the film (``END_ON_PROJECTION``): |a| = |E R_j e| with E = [e_c; e_r] the film's axes,
    R_j the vertebra's rotation and e the director the tilts observe."""
    errors = []
    for view, lengths in projected_tilt_directors(inputs, out):
        sources = inputs.tilt_sources.get(view.name, [])
        assert view.tilt_indices is not None
        end_on = [LEVELS[j] for j, source, length in zip(view.tilt_indices, sources, lengths, strict=True)
                  if source == "corners" and length < END_ON_PROJECTION]  # fmt: skip
        if end_on:
            errors.append(FieldError(
                (view.name, "landmarks"),
                f"the corners of {', '.join(end_on)} on the {'PA' if view.name == 'pa' else view.name} film tilt "
                "so far from the curve the other landmarks draw that the fit meets them only by turning those "
                "vertebrae end-on to the film (60° or more about their axis): check the corners' order and levels",
                "corners_contradicted",
            ))  # fmt: skip
    if errors:
        raise InvalidInput(errors)


def projected_tilt_directors(inputs: RegistrationInputs, out: FitOutput) -> list[tuple[ViewData, np.ndarray]]:
    """Each view with tilt observations, and the length |E R_j e| (dimensionless, at most 1) of each
    observed vertebra's tilt director projected on the film's axes E = [e_c; e_r]."""
    lengths = []
    for view in inputs.views:
        if view.n_tilts == 0 or view.tilt_director is None or view.tilt_indices is None:
            continue
        axes = np.stack([view.e_c, view.e_r])
        directors = out.rotations[view.tilt_indices] @ view.tilt_director
        lengths.append((view, np.linalg.norm(directors @ axes.T, axis=1)))
    return lengths


def _register_model(model: JobPayload, tilt_prior: TiltPrior | None, profile: Profile) -> RegistrationResult:
    start = time.perf_counter()
    try:
        with np.errstate(over="raise", invalid="raise", divide="raise"):
            inputs = prepare_inputs(model, profile, tilt_prior)
            solution, rest = fit_patient_rod(inputs, profile)
            out = solution.output
    except (ArithmeticError, FloatingPointError, ValueError, np.linalg.LinAlgError) as exc:
        # A degenerate geometry (e.g. landmarks that no spine can have) breaks the numerics.
        raise FitFailed(f"the registration broke down numerically: {exc}") from None
    runtime_ms = (time.perf_counter() - start) * 1e3
    _check_landmark_sd(model, out)
    _check_corner_tilts(inputs, out)
    if not out.converged:
        raise FitFailed(
            f"the registration did not converge in {out.iterations} iterations "
            f"(E_f = {out.energy_fit:.4g} N·mm, E_I = {out.energy_internal:.4g} N·mm)",
            iterations=out.iterations,
        )
    if not (np.isfinite(out.positions).all() and np.isfinite(out.rotations).all()):
        raise FitFailed("the registration produced non-finite coordinates", iterations=out.iterations)
    measures = measure_fit(inputs, out)
    sagittal_from_prior = sagittal_left_to_prior(inputs)
    if sagittal_from_prior:
        measures = _prior_only_reported(measures, calibration().prior_only)
    axial_rotation = None  # the directors' where pedicles observed it, else the population's
    exact_ends = [0, len(LEVELS) - 1] if inputs.boundary == "given" else []
    if not _has_pedicles(inputs):
        axial_rotation = population_axial_rotation_deg(measures)
        axial_rotation[exact_ends] = axial_rotation_deg(out.rotations)[exact_ends]  # the payload's own poses
        measures = _with_population_axial_rotation(measures, axial_rotation)
        if "axial_rotation" not in inputs.unreliable:  # T1 and L5 given: the vertebrae between are the population's
            inputs = dataclasses.replace(inputs, unreliable=[*inputs.unreliable, "axial_rotation"])
    unseen = _unseen_cobb(measures, inputs.frontal_observed, inputs.frontal_tilt_seen)
    if any(unseen) and "cobb" not in inputs.unreliable:
        inputs = dataclasses.replace(inputs, unreliable=[*inputs.unreliable, "cobb"])
    uncertainty: Uncertainty | None
    try:
        with np.errstate(over="raise", invalid="raise", divide="raise"):
            uncertainty = reported_uncertainty(solution, _sd_pairs(measures))
    except (ArithmeticError, FloatingPointError, ValueError, np.linalg.LinAlgError):
        uncertainty = None  # the SDs stay null when the curvature at the optimum is not usable
    if uncertainty is not None:
        measures = _measures_with_sds(measures, uncertainty)
        tilts = tilt_prior if tilt_prior is not None else load_tilt_prior()
        measures = _with_model_tilt_sd(measures, tilts.model_tilt_cobb_sd_deg(inputs.tilt_prior))
        measures = _with_unseen_cobb_floor(measures, unseen, profile)
        if sagittal_from_prior:
            measures = _with_prior_floor(measures, profile, calibration().prior_only)
        if measures.lenke is not None:
            measures = measures.model_copy(update={"lenke": lenke_probabilities(measures.lenke)})
        if axial_rotation is not None:
            uncertainty = _with_axial_rotation_floor(uncertainty, measures, exact_ends)
        inputs = dataclasses.replace(inputs, unreliable=_unreliable_by_sd(measures, profile, inputs.unreliable))
    return RegistrationResult(
        vertebrae=_vertebrae(out, rest, inputs.observed_tilt_deg, uncertainty, axial_rotation),
        measures=measures,
        fit=_fit_report(inputs, out, runtime_ms, uncertainty, population_axial_rotation=axial_rotation is not None),
        engine=EngineInfo(version=__version__, profile=profile.name),
    )


def measure_fit(inputs: RegistrationInputs, out: FitOutput) -> Measures:
    """The measures of a fit, read as its inputs allow (``measures.compute_measures``): the corner
    lines' tilts where given, the directors' sagittal tilt only where observed; where the prior
    decides the kyphosis, it blends the rod's reading with the PA film's foreshortening
    (``with_pa_kyphoses``). No SDs."""
    measures = rod_measures(inputs, out)
    model = load_reading_model()
    return measures if model is None else with_pa_kyphoses(measures, inputs, out, model)


def rod_measures(inputs: RegistrationInputs, out: FitOutput) -> Measures:
    """The measures of the fitted rod alone (``measures.compute_measures``): the corner lines' tilts
    where given, the directors' sagittal tilt only where observed. No SDs."""
    return compute_measures(
        out.positions,
        out.rotations,
        observed_tilt_deg=inputs.observed_tilt_deg,
        observed_endplate_tilt_deg=inputs.observed_endplate_tilt_deg,
        observed_sagittal=inputs.observed_sagittal,
    )


def sagittal_left_to_prior(inputs: RegistrationInputs) -> bool:
    """Whether no film determines the sagittal measures (``fit.unreliable`` names "kyphosis" before the
    fit: no lateral view with two landmarks, no T1 and L5 given): they are then read as calibrated on
    dev's PA-only fits (``with_pa_kyphoses``, ``_prior_only_reported``)."""
    return "kyphosis" in inputs.unreliable


def pa_foreshortening_kyphoses(
    inputs: RegistrationInputs, out: FitOutput, model: ReadingModel
) -> tuple[float, float] | None:
    """(kyphosis T4–T12, T5–T12), degrees, that the PA film's foreshortening reads
    (``sagittal_reading``), or None: the sagittal measures not left to the prior
    (``sagittal_left_to_prior``: a lateral film sees them, or T1 and L5 given inform them, docs/engine.md),
    or too few adjacent PA levels. A point-source film's landmarks are read as in weak perspective first
    (``weak_perspective_points``)."""
    if not sagittal_left_to_prior(inputs):
        return None
    pa = next(view for view in inputs.views if view.name == "pa")
    beta = read_inclinations_deg(model, pa.indices, weak_perspective_points(pa, out), pa.landmark_sd_mm)
    return None if beta is None else kyphoses_deg(beta)


def weak_perspective_points(view: ViewData, out: FitOutput) -> np.ndarray:
    """The view's landmarks (k, 2), detector mm, as a weak perspective at the reference magnification
    SID/SOD would show them. On a point-source film (``fit.types.Camera``) a point at depth
    d_i = b·(r_i − o) along the beam is magnified by SID/(SOD + d_i): each landmark is scaled about the
    central ray's foot c by (SOD + d_i)/SOD, d_i that of its fitted vertebra (a vertebra 30 mm nearer
    the source is magnified 1.9 % more at SOD 1600 mm, as much as a chord's inclination of 11°
    foreshortens it). Weak-perspective views: their points as they are."""
    camera, values = view.camera, out.cameras.get(view.name)
    if camera is None or camera.kind != "perspective" or values is None:
        return view.points
    c, o = np.asarray(values[0:2], dtype=float), np.asarray(values[2:5], dtype=float)
    depth = (out.positions[view.indices] - o) @ camera.beam_direction(view.e_c, view.e_r)
    return np.asarray(c + (view.points - c) * ((camera.sod_mm + depth) / camera.sod_mm)[:, None])


def with_pa_kyphoses(measures: Measures, inputs: RegistrationInputs, out: FitOutput, model: ReadingModel) -> Measures:
    """Where the prior decides the kyphosis (one PA film, no T1 and L5 given), the kyphoses T4–T12 and
    T5–T12 as w·K_PA + (1 − w)·K_rod, K_PA the PA film's foreshortening reading
    (``pa_foreshortening_kyphoses``), K_rod the fitted centreline's and w ``model.weight``; the Lenke
    inputs' T5–T12 follows. Unchanged otherwise."""
    read = pa_foreshortening_kyphoses(inputs, out, model)
    if read is None:
        return measures
    w = model.weight
    t4_t12 = w * read[0] + (1.0 - w) * measures.thoracic_kyphosis_t4_t12_deg
    t5_t12 = w * read[1] + (1.0 - w) * measures.thoracic_kyphosis_t5_t12_deg
    update: dict[str, Any] = {"thoracic_kyphosis_t4_t12_deg": t4_t12, "thoracic_kyphosis_t5_t12_deg": t5_t12}
    lenke = measures.lenke
    if lenke is not None:
        update["lenke"] = lenke_with_kyphoses(lenke, lenke.t2_t5_kyphosis_deg, t5_t12, lenke.t10_l2_kyphosis_deg)
    return measures.model_copy(update=update)


def _sd_pairs(measures: Measures) -> list[tuple[str, str]]:
    """The (upper, lower) end levels whose Cobb angle SDs a result reports: each curve of
    ``measures.cobb`` in order, then the largest angle's when no curve lists it (below the threshold)."""
    pairs: list[tuple[str, str]] = [(c.upper, c.lower) for c in measures.cobb]
    largest = measures.largest_cobb
    if largest is not None and not largest.reported_as_curve:
        pairs.append((largest.upper, largest.lower))
    return pairs


def _measures_with_sds(measures: Measures, uncertainty: Uncertainty) -> Measures:
    """``measures`` with the SDs of kyphosis, lordosis and each Cobb angle (in the order of
    ``_sd_pairs``, as given to ``reported_uncertainty``) filled in; the largest angle's is its major
    curve's when ``cobb`` lists it."""
    n = len(measures.cobb)
    curve_sds, unlisted_sds = list(uncertainty.cobb_sd_deg[:n]), list(uncertainty.cobb_sd_deg[n:])
    cobb = [c.model_copy(update={"angle_sd_deg": sd}) for c, sd in zip(measures.cobb, curve_sds, strict=True)]
    largest = measures.largest_cobb
    if largest is not None:
        major_sd = next((c.angle_sd_deg for c in cobb if c.major), None)
        [sd] = [major_sd] if largest.reported_as_curve else unlisted_sds
        largest = largest.model_copy(update={"angle_sd_deg": sd})
    lenke = measures.lenke
    if lenke is not None:
        lenke = lenke.model_copy(update={
            "t2_t5_kyphosis_sd_deg": uncertainty.kyphosis_t2_t5_sd_deg,
            "t5_t12_kyphosis_sd_deg": uncertainty.kyphosis_t5_t12_sd_deg,
            "t10_l2_kyphosis_sd_deg": uncertainty.kyphosis_t10_l2_sd_deg,
        })
    return measures.model_copy(
        update={
            "cobb": cobb,
            "largest_cobb": largest,
            "thoracic_kyphosis_t4_t12_sd_deg": uncertainty.kyphosis_t4_t12_sd_deg,
            "thoracic_kyphosis_t5_t12_sd_deg": uncertainty.kyphosis_t5_t12_sd_deg,
            "lumbar_lordosis_l1_l5_sd_deg": uncertainty.lordosis_l1_l5_sd_deg,
            "lenke": lenke,
        }
    )


APICAL_ROTATION_PER_COBB = {"thoracic": 22.0 / 68.0, "lumbar": 11.0 / 44.0}
"""Mean axial rotation of a curve's apical vertebra toward its convexity per degree of its Cobb angle,
standing AIS patients before surgery, thoracic and (thoraco)lumbar curves (Brink et al., Scoliosis
Spinal Disord 2017;12:6, doi:10.1186/s13013-017-0111-5: upright apical rotation 22° ± 12° at a
thoracic Cobb angle of 68° ± 15°, 11° ± 13° at a lumbar 44° ± 17°; the ratio of the means). Apical
rotation grows with the Cobb angle (r = 0.68, Morrison et al., Eur Spine J 2015;24:306–312)."""
THORACIC_APEX_LOWEST = "T11"
"""Lowest apex of a thoracic curve for ``APICAL_ROTATION_PER_COBB`` (SRS: thoracic apex T2 to the
T11–T12 disc; thoracolumbar T12–L1, lumbar below, Lenke et al., J Bone Joint Surg Am 2001;83:1169)."""
AXIAL_ROTATION_PER_COBB = 0.30
"""SD of a vertebra's axial rotation that no pedicle observed about the population's mean
(``population_axial_rotation_deg``), per degree of the Cobb angle of the curve it lies in: Brink et
al.'s SD over mean Cobb angle (above), 12/68 = 0.18 thoracic, 13/44 = 0.30 lumbar, the larger taken."""


def population_axial_rotation_deg(measures: Measures) -> np.ndarray:
    """(17,) the population's mean axial rotation of each vertebra given the frontal curves, degrees
    (``frames.axial_rotation_deg``'s sense: > 0 toward patient left). Within a curve, k·C toward its
    convexity at the apex (C its Cobb angle, k = ``APICAL_ROTATION_PER_COBB`` of its region), falling
    linearly with the level to 0 at its end vertebrae (the apical vertebra the most rotated, the end
    vertebrae the least: a modelling choice of the profile's shape); 0 outside every curve; where
    curves meet, the larger in magnitude."""
    levels = np.arange(len(LEVELS))
    psi = np.zeros(len(LEVELS))
    for c in measures.cobb:
        upper, apex, lower = LEVEL_INDEX[c.upper], LEVEL_INDEX[c.apex], LEVEL_INDEX[c.lower]
        region = "thoracic" if apex <= LEVEL_INDEX[THORACIC_APEX_LOWEST] else "lumbar"
        peak = APICAL_ROTATION_PER_COBB[region] * c.angle_deg * (1.0 if c.convexity == "left" else -1.0)
        rising = (levels - upper) / max(apex - upper, 1)
        falling = (lower - levels) / max(lower - apex, 1)
        taper = np.clip(np.where(levels <= apex, rising, falling), 0.0, 1.0)
        value = np.where((levels >= upper) & (levels <= lower), peak * taper, 0.0)
        psi = np.where(np.abs(value) > np.abs(psi), value, psi)
    return psi


def _with_population_axial_rotation(measures: Measures, psi_deg: np.ndarray) -> Measures:
    """``measures`` whose curves' apex axial rotations are ``psi_deg`` at their apexes."""
    cobb = [
        c.model_copy(update={"apex_axial_rotation_deg": float(psi_deg[LEVEL_INDEX[c.apex]])}) for c in measures.cobb
    ]
    return measures.model_copy(update={"cobb": cobb})


def _has_pedicles(inputs: RegistrationInputs) -> bool:
    """Whether a PA landmark carried pedicles (the only observation of axial rotation)."""
    return any(source != "inferior_midpoint" for source in inputs.offset_sources.get("pa", []))


def _with_axial_rotation_floor(uncertainty: Uncertainty, measures: Measures, exact: Sequence[int] = ()) -> Uncertainty:
    """Without pedicles the vertebrae's axial rotations are the population's (``population_axial_rotation_deg``),
    whose spread the rod's Laplace SD (a few degrees, of its twist) does not know. Each SD is then
    √(SD² + (k·C)²), C the largest Cobb angle of the curves the vertebra lies in (0 outside every
    curve), k = ``AXIAL_ROTATION_PER_COBB``; the vertebrae ``exact`` (T1 and L5 given exactly), whose
    axial rotation is the payload's, keep their Laplace SD."""
    cobb = np.zeros(len(LEVELS))
    for c in measures.cobb:
        span = slice(LEVEL_INDEX[c.upper], LEVEL_INDEX[c.lower] + 1)
        cobb[span] = np.maximum(cobb[span], c.angle_deg)
    cobb[list(exact)] = 0.0
    sd = np.hypot(uncertainty.axial_rotation_sd_deg, AXIAL_ROTATION_PER_COBB * cobb)
    return uncertainty._replace(axial_rotation_sd_deg=np.minimum(sd, AXIAL_ROTATION_SD_CAP_DEG))


MODEL_TILT_ENDS = {"corners": 0, "mixed": 1, "model": 2}
"""End vertebrae of a Cobb curve whose tilt is the model's, by ``CobbCurve.tilt_source``."""


def _with_model_tilt_sd(measures: Measures, sigma_deg: float) -> Measures:
    """Each Cobb angle's SD with the endplates' turn from the centreline where no corner observed them:
    SD² = SD_Laplace² + (m/2) σ², m the curve's end vertebrae with a model tilt (``MODEL_TILT_ENDS``),
    σ the tilt prior's calibrated ``cobb_sd_deg`` (degrees), which is a whole curve's (m = 2)."""
    if sigma_deg <= 0.0:
        return measures

    def widened(sd: float | None, source: str | None) -> float | None:
        share = MODEL_TILT_ENDS[source or "model"] / 2.0
        return sd if sd is None or share <= 0.0 else math.sqrt(sd**2 + share * sigma_deg**2)

    cobb = [c.model_copy(update={"angle_sd_deg": widened(c.angle_sd_deg, c.tilt_source)}) for c in measures.cobb]
    largest = measures.largest_cobb
    if largest is not None:
        largest = largest.model_copy(update={"angle_sd_deg": widened(largest.angle_sd_deg, largest.tilt_source)})
    return measures.model_copy(update={"cobb": cobb, "largest_cobb": largest})


def _unseen_cobb(
    measures: Measures, frontal_observed: np.ndarray | None, tilt_seen: np.ndarray | None = None
) -> list[bool]:
    """Per Cobb angle, in the order of ``_sd_pairs`` with the largest angle last (each curve of
    ``measures.cobb``, then ``largest_cobb``): whether it depends on frontal tilts that only the prior
    decides, on levels the input does not show (``frontal_observed``, ``frontal_observed_levels``). A
    curve does when an end vertebra's own tilt is not shown (``tilt_seen``,
    ``frontal_tilt_seen_levels``; without it, ``frontal_observed``) or when the level beyond an end
    vertebra (above the upper one, below the lower one; none beyond T1 and L5) has no tilt shown: the
    end vertebra is the most tilted one of the curve, which only a less tilted neighbour beyond it
    shows, and the curve may go on past the film (synthetic spines filmed from T1 or to L5 with 6–11
    levels, no lateral: curves ending on or next to the last landmark covered the truth's angle 71 %
    and 80 % of the time with the Laplace SD, curves farther in 93 %). The largest angle, the largest
    over all 17 levels, depends on such tilts whenever one level is not in ``frontal_observed``: even
    when its two vertebrae are on the film, whether a larger angle lies beyond it is the prior's
    answer."""
    n = len(measures.cobb) + (measures.largest_cobb is not None)
    if frontal_observed is None:
        return [False] * n
    seen = np.asarray(frontal_observed if tilt_seen is None else tilt_seen, dtype=bool)
    last = len(LEVELS) - 1

    def shown(upper: int, lower: int) -> bool:
        return bool(
            seen[upper] and seen[lower] and (upper == 0 or seen[upper - 1]) and (lower == last or seen[lower + 1])
        )

    unseen = [not shown(LEVEL_INDEX[c.upper], LEVEL_INDEX[c.lower]) for c in measures.cobb]
    if measures.largest_cobb is not None:
        unseen.append(not bool(np.all(frontal_observed)))
    return unseen


def _with_unseen_cobb_floor(measures: Measures, unseen: list[bool], profile: Profile) -> Measures:
    """Cobb angles that depend on a level the films do not show (``unseen``, ``_unseen_cobb``) come from
    the prior, so their SD is at least the population's (``anatomy.PopulationPrior.measure_sd_deg``
    ``major_cobb_deg``, AASCE 2019 training: 18.4°): SD = max(SD, population SD). The rod's Laplace SD
    of such an angle is the prior's spread read at the calibrated prior weight λ (``fit.uncertainty``),
    which was set for the positions of one PA film, not for a tilt no film shows (16–17° with PA
    landmarks on T1–T4, 9° with a full lateral film besides, which sees no frontal coordinate)."""
    prior = population_prior(profile)
    floor = None if prior is None else prior.measure_sd_deg.get("major_cobb_deg")
    if floor is None or not any(unseen):
        return measures

    def floored(sd: float | None) -> float | None:
        return None if sd is None else max(sd, floor)

    n = len(measures.cobb)
    cobb = [c.model_copy(update={"angle_sd_deg": floored(c.angle_sd_deg)}) if unseen[k] else c
            for k, c in enumerate(measures.cobb)]  # fmt: skip
    largest = measures.largest_cobb
    if largest is not None and unseen[n]:
        largest = largest.model_copy(update={"angle_sd_deg": floored(largest.angle_sd_deg)})
    return measures.model_copy(update={"cobb": cobb, "largest_cobb": largest})


def _prior_only_reported(measures: Measures, readings: dict[str, PriorOnlyReading]) -> Measures:
    """Sagittal measures that no film determined (no lateral view) as calibrated on dev
    (``fit.uncertainty.PriorOnlyReading.reported``): the film's reading plus its offset where the
    film predicts the measure, else the population's mean, degrees. The Lenke inputs' T5–T12
    kyphosis is the reported T5–T12 kyphosis, their T2–T5 and T10–L2 kyphoses are reported so too
    (``PRIOR_ONLY_LENKE``), and what they decide follows them (``measures.lenke_with_kyphoses``)."""
    update: dict[str, Any] = {
        PRIOR_ONLY_MEASURES[name]: reading.reported(getattr(measures, PRIOR_ONLY_MEASURES[name]))
        for name, reading in readings.items() if name in PRIOR_ONLY_MEASURES
    }
    lenke = measures.lenke
    if lenke is not None:
        regional = {
            field: readings[name].reported(getattr(lenke, field)) if name in readings else getattr(lenke, field)
            for name, field in PRIOR_ONLY_LENKE.items()
        }
        t5_t12 = update.get(PRIOR_ONLY_MEASURES["kyphosis_t5_t12"], lenke.t5_t12_kyphosis_deg)
        update["lenke"] = lenke_with_kyphoses(
            lenke, regional["t2_t5_kyphosis_deg"], t5_t12, regional["t10_l2_kyphosis_deg"]
        )
    return measures.model_copy(update=update)


def _with_prior_floor(measures: Measures, profile: Profile, readings: dict[str, PriorOnlyReading]) -> Measures:
    """Sagittal measures that no film determined (no lateral view: ``fit.unreliable`` has "kyphosis"
    and "lordosis") come from the population prior, so their SD is at least the population's
    (``anatomy.PopulationPrior.measure_sd_deg``, VerSe dev): SD = max(Laplace SD, population SD). Lenke's
    T5–T12 kyphosis takes the T5–T12 kyphosis's SD; its T2–T5 and T10–L2 kyphoses are floored by their
    SD on dev as the calibration recorded it (``PriorOnlyReading.population_sd_deg``), else by the
    kyphosis's."""
    prior = population_prior(profile)
    if prior is None:
        return measures
    kyphosis = prior.measure_sd_deg["kyphosis_t4_t12_deg"]
    lordosis = prior.measure_sd_deg["lordosis_l1_l5_deg"]
    update: dict[str, Any] = {
        name: max(float(getattr(measures, name) or 0.0), floor)
        for name, floor in (
            ("thoracic_kyphosis_t4_t12_sd_deg", kyphosis),
            ("thoracic_kyphosis_t5_t12_sd_deg", kyphosis),
            ("lumbar_lordosis_l1_l5_sd_deg", lordosis),
        )
    }
    lenke = measures.lenke
    if lenke is not None:
        def floored(name: str, field: str) -> float:
            reading = readings.get(name)
            floor = reading.population_sd_deg if reading is not None and reading.population_sd_deg else kyphosis
            return max(float(getattr(lenke, field) or 0.0), floor)

        update["lenke"] = lenke.model_copy(update={
            "t2_t5_kyphosis_sd_deg": floored("kyphosis_t2_t5", "t2_t5_kyphosis_sd_deg"),
            "t5_t12_kyphosis_sd_deg": update["thoracic_kyphosis_t5_t12_sd_deg"],
            "t10_l2_kyphosis_sd_deg": floored("kyphosis_t10_l2", "t10_l2_kyphosis_sd_deg"),
        })
    return measures.model_copy(update=update)


UNRELIABLE_SD_FRACTION = 0.5
"""A measure is a model estimate (``fit.unreliable``) when its SD exceeds this fraction of the
population's SD (``anatomy.PopulationPrior.measure_sd_deg``): the films then removed less than three
quarters of the population's variance (1 − 0.5² = 0.75). Sagittal measures, and each Cobb angle
against the major Cobb angle's population SD."""


def _unreliable_by_sd(measures: Measures, profile: Profile, unreliable: list[Unreliable]) -> list[Unreliable]:
    """``unreliable`` plus "kyphosis" / "lordosis" when their SD exceeds ``UNRELIABLE_SD_FRACTION`` of
    the population's, and "cobb" when the SD of a curve's or of the largest Cobb angle does (order
    kept, no duplicates)."""
    prior = population_prior(profile)
    if prior is None:
        return list(unreliable)
    out = list(unreliable)
    cobb_sds = [c.angle_sd_deg for c in measures.cobb]
    if measures.largest_cobb is not None:
        cobb_sds.append(measures.largest_cobb.angle_sd_deg)
    checks: list[tuple[Unreliable, list[float | None], float | None]] = [
        ("kyphosis", [measures.thoracic_kyphosis_t4_t12_sd_deg], prior.measure_sd_deg["kyphosis_t4_t12_deg"]),
        ("lordosis", [measures.lumbar_lordosis_l1_l5_sd_deg], prior.measure_sd_deg["lordosis_l1_l5_deg"]),
        ("cobb", cobb_sds, prior.measure_sd_deg.get("major_cobb_deg")),
    ]
    for name, sds, population in checks:
        if population is None or name in out:
            continue
        if any(sd is not None and sd > UNRELIABLE_SD_FRACTION * population for sd in sds):
            out.append(name)
    return out


def register(payload: dict[str, Any]) -> dict[str, Any]:
    """Reconstruct a spine from a job payload (the JSON body of ``POST /v1/jobs``).

    Returns the ``result`` object a client reads back (``RegistrationResult`` as JSON types).
    Raises ``InvalidInput`` naming every bad field, or ``FitFailed`` when the fit fails.
    """
    return register_model(validate_payload(payload)).model_dump(mode="json")
