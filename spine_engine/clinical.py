"""Clinical inputs of a payload as arrays: corners, pedicles, the tilt prior, and a spine placed
without boundary conditions. Used by ``reconstruction.prepare_inputs``; pure functions on arrays
and validated payload models, nothing of JSON.

Without boundary conditions (``place_without_boundary``) the T1 and L5 poses that the registration
holds fixed are estimated from the generic rest model and the PA landmarks:

* **Scale and translation of the PA view**: given, or else s = (length of the PA landmarks'
  polyline in the image) / (length of the generic spine's frontal projection through the same
  levels), and T puts T1's landmark at the patient origin. The patient is then as long as the
  generic spine: lengths in mm are the model's (``fit.unreliable`` has "scale").
* **In-plane coordinates** of every PA-landmarked level are (p − T)/s; levels without a landmark
  are interpolated along the generic spine's arc length.
* **Depth** (along the image normal e_c × e_r) is the generic spine's, unless a lateral view gives
  it: with its projection when given, else with the PA scale and T1's generic depth.
* **Directors** of T1 and L5 follow that centreline (``frames.frames_from_centreline``: d3 the
  one-sided tangent, d1 the patient-left axis made orthogonal to it, no axial rotation), turned
  about the frontal normal so that their frontal tilt is the corners' (when given) or the tilt
  prior's (when on).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from .anatomy import Profile, RestShapeKey, length_correction, rest_shape_key, rest_shape_unit, rest_shape_unit_of
from .fit import FloatArray, Pose, ViewData
from .frames import frames_from_centreline
from .levels import LEVEL_INDEX, N_LEVELS
from .models import JobPayload, LateralView, PAView, Unreliable
from .observations import (
    chord_angles_deg,
    corner_geometry,
    frontal_sign,
    frontal_tilt_deg_of_image_vectors,
    image_vectors_of_frontal_tilt,
    inferior_midpoint_offsets,
    pedicle_offsets_in_image_order,
    tilt_weight,
    transverse_director,
)
from .projection import image_axes
from .rotations import cross, exp_so3
from .tilt_prior import TiltPrior, predict_tilts_deg

_X = np.array([1.0, 0.0, 0.0])
_Y = np.array([0.0, 1.0, 0.0])
_Z = np.array([0.0, 0.0, 1.0])
_NAN_POINTS = {1: (np.nan, np.nan), 2: ((np.nan, np.nan),) * 2, 4: ((np.nan, np.nan),) * 4}
"""m image points (column, row) of NaN: a landmark without point, pedicles (2) or corners (4)."""


@dataclass(frozen=True)
class LandmarkArrays:
    """One view's landmarks in detector mm, sorted by level: level indices (k,), the fitted point
    (k, 2) (the given point, or the superior endplate midpoint of the corners), corners (k, 4, 2)
    and pedicles (k, 2, 2) with NaN where a landmark has none."""

    indices: npt.NDArray[np.intp]
    points: FloatArray
    corners: FloatArray
    pedicles: FloatArray

    @property
    def has_corners(self) -> npt.NDArray[np.bool_]:
        return np.asarray(np.isfinite(self.corners[:, 0, 0]))

    @property
    def has_pedicles(self) -> npt.NDArray[np.bool_]:
        return np.asarray(np.isfinite(self.pedicles[:, 0, 0]))


def detector_spacing(view: PAView | LateralView) -> FloatArray:
    """The one pixel-to-mm conversion: (column, row) mm per unit of the view's coordinates, i.e.
    (1, 1) for mm and the DICOM (0028,0030) pixel spacing [row, column] swapped to (column, row) for px."""
    calibrated = calibrated_magnification(view)
    factor = calibrated if calibrated is not None else 1.0
    if view.units == "px":
        assert view.pixel_spacing is not None  # validate_payload guarantees it
        row_spacing, column_spacing = view.pixel_spacing
        return factor * np.array([column_spacing, row_spacing], dtype=float)
    return np.full(2, factor)


def calibrated_magnification(view: PAView | LateralView) -> float | None:
    """For a view whose mm are in the patient plane (``pixel_spacing_calibration`` 'calibrated', PS3.3
    §10.7.1.1), the factor M that takes them to the detector (detector mm = M · patient mm): the
    acquisition's ERMF (0018,1114), else SID/SOD, else 1 (the calibration already removed the
    magnification, whose value is then unknown and not needed), or, for a point-source film
    (``projection_model`` "perspective") that gives neither, the SID/SOD it is projected with
    (``pinhole_geometry``), so that the pinhole's magnification at the spine gives back the calibrated
    size. None for detector-plane mm."""
    if view.pixel_spacing_calibration != "calibrated":
        return None
    acq = view.acquisition
    if acq is not None and acq.magnification is not None:
        return float(acq.magnification)
    if acq is not None and acq.point_source:
        geometry = pinhole_geometry(view, "lateral" if isinstance(view, LateralView) else "pa")
        assert geometry is not None
        return geometry.sid_mm / geometry.sod_mm
    return 1.0


def _optional_points(values: list[tuple[tuple[float, float], ...] | None], m: int) -> FloatArray:
    """(k, m, 2) image points of an optional landmark field (corners m = 4, pedicles m = 2), NaN
    where a landmark has none."""
    if all(v is None for v in values):
        return np.full((len(values), m, 2), np.nan)
    filled = [_NAN_POINTS[m] if v is None else v for v in values]
    return np.array(filled, dtype=float).reshape(len(values), m, 2)


def landmark_arrays(view: PAView | LateralView) -> LandmarkArrays:
    """Arrays of a validated view in detector mm (``detector_spacing``); a landmark given by its corners
    counts as its superior endplate midpoint, which is the bottom pair on a head-up image (rows toward H)."""
    _, e_r = image_axes(view.patient_orientation)
    landmarks = view.landmarks
    k = len(landmarks)
    spacing = detector_spacing(view)
    indices = np.array([LEVEL_INDEX[lm.level] for lm in landmarks], dtype=np.intp)
    # NaN where a landmark has none (NaN · spacing stays NaN)
    points = np.array([_NAN_POINTS[1] if lm.point is None else lm.point for lm in landmarks], dtype=float)
    points = points.reshape(k, 2) * spacing
    corners = _optional_points([lm.corners for lm in landmarks], 4) * spacing
    pedicles = _optional_points([lm.pedicles for lm in landmarks], 2) * spacing
    with_corners = np.isfinite(corners[:, 0, 0])
    if with_corners.any():
        points[with_corners] = corner_geometry(corners[with_corners], e_r).superior_midpoint
    return LandmarkArrays(indices, points, corners, pedicles)


def is_frontal(e_c: FloatArray, e_r: FloatArray) -> bool:
    """A PA or AP radiograph: columns along ±x and rows along ±z (shown upright), or turned a quarter
    (columns along ±z, rows along ±x). Its chords' frontal angles, and so the tilt prior, are the same
    either way (``observations.chord_angles_deg`` reads them in the patient's frame)."""
    return frontal_sign(e_c, e_r) is not None


def chords_by_level(arrays: LandmarkArrays, e_c: FloatArray, e_r: FloatArray) -> FloatArray:
    """Frontal chord angles (16,) between consecutive levels, NaN where a level has no landmark."""
    points = np.full((N_LEVELS, 2), np.nan)
    points[arrays.indices] = arrays.points
    return chord_angles_deg(points, e_c, e_r)


def prior_tilts_deg(prior: TiltPrior, arrays: LandmarkArrays, e_c: FloatArray, e_r: FloatArray) -> FloatArray:
    """Tilt predicted by the prior for every level (17,), NaN where a needed chord is missing or runs
    toward the head (|φ| ≥ 90°: two levels whose order the landmarks' noise reversed, which validation
    allows within their noise; such a chord's angle says nothing of the tilts, and read as one it turned
    T1 past 90° on a film of 5 mm noise)."""
    chords = chords_by_level(arrays, e_c, e_r)
    chords[np.abs(chords) >= 90.0] = np.nan
    return predict_tilts_deg(prior, chords)


def polyline_length(points: FloatArray) -> float:
    """Σ_k |p_{k+1} − p_k| of points (k, d), in their units: the segment norms as
    ``np.linalg.norm(·, axis=1)`` computes them (√ of the row sums of squares), without its overhead."""
    points = np.asarray(points)
    d = points[1:] - points[:-1]  # np.diff(points, axis=0), without its wrapper
    return float(np.sqrt((d * d).sum(axis=1)).sum())


def generic_arc_scale(profile: Profile, arrays: LandmarkArrays, e_c: FloatArray, e_r: FloatArray) -> float:
    """(length of the landmarks' polyline, detector mm) / (length of the generic spine's projection
    through the same levels, mm): the scale s that makes the patient as long as the generic spine."""
    image = polyline_length(arrays.points)
    model = generic_projected_length(profile, arrays.indices, e_c, e_r)
    if not (image > 0.0 and model > 0.0):
        raise ValueError("the landmarks do not span a length: cannot estimate the scale")
    return image / model


def size_factor(profile: Profile, view: ViewData) -> float:
    """Patient size relative to the generic spine: the PA landmarks' polyline in patient mm over the
    generic spine's frontal projection through the same levels (1 with fewer than 2 landmarks)."""
    if len(view.indices) < 2:
        return 1.0
    patient = polyline_length(np.asarray(view.points) / view.scale)
    model = generic_projected_length(profile, view.indices, view.e_c, view.e_r)
    return patient / model * length_correction(profile) if patient > 0.0 and model > 0.0 else 1.0


def projected_length(points: FloatArray, e_c: FloatArray, e_r: FloatArray) -> float:
    """Σ_k |g_{k+1} − g_k| of the points (k, 3) projected on the image axes, g_k = (e_c·r_k, e_r·r_k),
    in the points' units."""
    projected = np.empty((len(points), 2))  # as np.stack(..., axis=1), without its wrapper
    projected[:, 0], projected[:, 1] = points @ e_c, points @ e_r
    return polyline_length(projected)


def generic_projected_length(
    profile: Profile, indices: npt.ArrayLike, e_c: npt.ArrayLike, e_r: npt.ArrayLike
) -> float:
    """``projected_length`` of the profile's generic rest shape at length scale 1 through the
    vertebrae ``indices``, mm. It depends only on the rest shape, the levels and the axes (a few
    distinct values from job to job), so it is computed once for each."""
    return _generic_projected_length(
        rest_shape_key(profile),
        tuple(np.asarray(indices).tolist()),
        tuple(np.asarray(e_c, dtype=float).tolist()),
        tuple(np.asarray(e_r, dtype=float).tolist()),
    )


@functools.lru_cache(maxsize=64)
def _generic_projected_length(
    shape: RestShapeKey, indices: tuple[int, ...], e_c: tuple[float, ...], e_r: tuple[float, ...]
) -> float:
    return projected_length(rest_shape_unit_of(shape)[1][np.asarray(indices)], np.asarray(e_c), np.asarray(e_r))


def with_observations(
    data: ViewData,
    arrays: LandmarkArrays,
    *,
    size: float,
    prior: TiltPrior | None,
    prior_tilts: FloatArray | None = None,
) -> tuple[ViewData, list[str], list[str]]:
    """``data`` with its tilt observations (corners; the prior for point-only levels when ``prior``)
    and offset-point observations (inferior endplate midpoints of corners, pedicle centres; offsets
    × ``size``); also the source of each tilt ("corners", "prior") and of each offset point
    ("inferior_midpoint", "image_left", "image_right"), in order. ``prior_tilts``: the prior's tilts of
    ``arrays`` (``prior_tilts_deg``) when already computed (``Placement.pa_prior_tilts_deg``)."""
    e_c, e_r = np.asarray(data.e_c), np.asarray(data.e_r)
    tilt_idx: list[int] = []
    tilt_dirs: list[FloatArray] = []
    tilt_w: list[float] = []
    sources: list[str] = []
    offset_idx: list[npt.NDArray[np.intp]] = []
    offset_vec: list[FloatArray] = []
    offset_col: list[FloatArray] = []
    offset_sources: list[str] = []
    with_corners = arrays.has_corners
    if with_corners.any():
        geometry = corner_geometry(arrays.corners[with_corners], e_r)
        levels = arrays.indices[with_corners]
        tilt_idx += levels.tolist()
        tilt_dirs += list(geometry.transverse)
        tilt_w += tilt_weight(levels, data.weight).tolist()
        sources += ["corners"] * len(levels)
        offset_idx.append(levels)
        offset_vec.append(inferior_midpoint_offsets(levels, size))
        offset_col.append(geometry.inferior_midpoint[:, 0])
        offset_sources += ["inferior_midpoint"] * len(levels)
    if prior is not None and is_frontal(e_c, e_r):
        predicted = prior_tilts_deg(prior, arrays, e_c, e_r) if prior_tilts is None else prior_tilts
        levels = arrays.indices[~with_corners]
        levels = levels[np.isfinite(predicted[levels])]
        if len(levels):
            tilt_idx += levels.tolist()
            tilt_dirs += list(image_vectors_of_frontal_tilt(predicted[levels], e_c, e_r))
            tilt_w += (prior.weight_fraction * tilt_weight(levels, data.weight)).tolist()
            sources += ["prior"] * len(levels)
    extra: dict[str, object] = {}
    if tilt_idx:
        extra.update(
            tilt_indices=np.asarray(tilt_idx, dtype=int),
            tilt_directions=np.asarray(tilt_dirs, dtype=float),
            tilt_weights=np.asarray(tilt_w, dtype=float),
            tilt_director=transverse_director(e_c, e_r),
        )
    with_pedicles = arrays.has_pedicles
    if with_pedicles.any():
        levels = arrays.indices[with_pedicles]
        offset_idx.append(np.repeat(levels, 2))
        offset_vec.append(pedicle_offsets_in_image_order(levels, e_c, size))
        offset_col.append(arrays.pedicles[with_pedicles][:, :, 0].ravel())
        offset_sources += ["image_left", "image_right"] * len(levels)
    if offset_idx:
        extra.update(
            offset_indices=np.concatenate(offset_idx).astype(int),
            offset_vectors=np.concatenate(offset_vec),
            offset_columns=np.concatenate(offset_col),
        )
    return (replace(data, **extra) if extra else data), sources, offset_sources  # type: ignore[arg-type]


def observed_frontal_tilts(
    arrays: LandmarkArrays, e_c: FloatArray, e_r: FloatArray
) -> tuple[FloatArray | None, FloatArray | None]:
    """Frontal tilt of each level's corner line (17,) and its superior / inferior endplate tilts
    (17, 2), NaN where a level has no corners; (None, None) without corners or on a non-frontal view."""
    with_corners = arrays.has_corners
    if not with_corners.any() or not is_frontal(e_c, e_r):
        return None, None
    g = corner_geometry(arrays.corners[with_corners], e_r)
    tilt = np.full(N_LEVELS, np.nan)
    endplates = np.full((N_LEVELS, 2), np.nan)
    levels = arrays.indices[with_corners]
    tilt[levels] = frontal_tilt_deg_of_image_vectors(g.transverse, e_c, e_r)
    endplates[levels, 0] = frontal_tilt_deg_of_image_vectors(g.superior_endplate, e_c, e_r)
    endplates[levels, 1] = frontal_tilt_deg_of_image_vectors(g.inferior_endplate, e_c, e_r)
    return tilt, endplates


# ---------------------------------------------------------------- no boundary conditions


PA_MAGNIFICATION_PRIOR = (1.125, 0.035)
"""(mean, SD) of the PA view's magnification at the spine when neither its projection nor its
acquisition says it: a full-spine PA at the usual source–image distance of about 1.8 m (72 inches)
with the spine's mid-plane about 1.6 m from the source gives SID/SOD = 1800/1600 = 1.125 (the
geometry of DESIGN.md's scoliosis series and of ``spine bench clinic``); the SD, 0.035, is a spine
mid-plane 50 mm nearer or farther (patient thickness, position against the stand): 1.125·50/1600.
A model estimate: fit.unreliable then lists "scale" and fit.pa.scale_source is "prior"."""


ASSUMED_DEPTH_SD_MM = {"pa": 50.0, "lateral": 100.0}
"""SD of the prior on the spine's distance from the source when the SOD is assumed, mm: on the PA
the 50 mm of ``PA_MAGNIFICATION_PRIOR`` (its SD of 0.035 is that distance); on the lateral 100 mm,
a modelling choice: the spine's mid-plane lies half the trunk's width from that detector, which
varies with the patient, the arms' position and the gap, and the lateral's magnification is then
read from the vertical extent both films share."""


@dataclass(frozen=True)
class PinholeGeometry:
    """The point-source geometry a view is projected with (``fit.cameras``), and whether it was assumed."""

    sid_mm: float
    sod_mm: float
    depth_prior_sd_mm: float | None
    """SD of the spine's distance from the source about SOD when SOD was assumed; None: the camera's
    default (``fit.types.DEPTH_PRIOR_SD_MM``) for a stated SOD."""
    assumed: bool
    """SID or SOD came from ``FULL_SPINE_SID_MM`` / ``SPINE_TO_DETECTOR_MM`` (fit.assumed names
    full_spine_geometry)."""


def pinhole_geometry(view: PAView | LateralView, name: str) -> PinholeGeometry | None:
    """The view's point-source geometry, or None for a weak perspective (``models.Acquisition``):
    SID and SOD when the acquisition gives both; with ``projection_model`` "perspective", the missing
    ones as ``models.Acquisition.point_source_distances`` fills them (through the ERMF, else
    ``SPINE_TO_DETECTOR_MM`` apart, else ``FULL_SPINE_SID_MM``), and an assumed SOD held with
    ``ASSUMED_DEPTH_SD_MM[name]``, unless the view's mm are 'calibrated' (in the spine's plane): its
    size is then known, the spine held at the SOD by the camera's default depth prior as for a given
    SOD, and only the perspective's strength assumed."""
    acq = view.acquisition
    distances = None if acq is None else acq.point_source_distances()
    if acq is None or distances is None:
        return None
    sid, sod = distances
    given_sid, given_sod = acq.distance_source_to_detector_mm, acq.distance_source_to_patient_mm
    sod_assumed = given_sod is None and acq.magnification is None
    depth_sd = ASSUMED_DEPTH_SD_MM[name] if sod_assumed and view.pixel_spacing_calibration != "calibrated" else None
    assumed = given_sid is None or sod_assumed
    return PinholeGeometry(sid, sod, depth_sd, assumed)


@dataclass(frozen=True)
class Placement:
    """T1 and L5 poses placed without boundary conditions (the fit's initial ends), the views'
    weak perspectives (scale, translation) to start from, and what then comes from the model only.

    Gauge convention (no boundary): the patient origin is T1: the PA translation puts T1's in-plane
    position at (0, 0) and T1's depth is 0."""

    top: Pose
    bottom: Pose
    pa: tuple[float, FloatArray]
    lateral: tuple[float, FloatArray] | None
    pa_estimated: bool
    lateral_estimated: bool
    unreliable: list[Unreliable]
    centreline: FloatArray | None = None
    """(17, 3) the placed centreline, mm (initial positions of every level)."""
    pa_prior_tilts_deg: FloatArray | None = None
    """(17,) the tilt prior's tilts of the PA levels (``prior_tilts_deg``), degrees, when a prior was
    given and the PA is frontal; else None."""


def _turn_to_frontal_tilt(R: FloatArray, target_deg: float) -> FloatArray:
    """R turned about the frontal normal (y) so that d1's frontal tilt atan2(d1_z, d1_x) is
    ``target_deg``: a rotation by a about +y moves every frontal angle by −a, exactly."""
    current = float(np.degrees(np.arctan2(R[2, 0], R[0, 0])))
    return np.asarray(exp_so3(np.radians(current - target_deg) * _Y) @ R)


def _fill_along_generic(values: FloatArray, generic: FloatArray, arc: FloatArray) -> FloatArray:
    """Every level's value (17, d) from the known ones (finite rows): linear in arc length between
    known levels, and beyond the first / last known level the generic spine's offsets from it."""
    out = values.copy()
    known = np.flatnonzero(np.isfinite(values[:, 0]))
    if len(known) == 0:
        return generic.copy()
    for axis in range(values.shape[1]):
        out[:, axis] = np.interp(arc, arc[known], values[known, axis])
    first, last = known[0], known[-1]
    out[:first] = values[first] + (generic[:first] - generic[first])
    out[last + 1 :] = values[last] + (generic[last + 1 :] - generic[last])
    return out


def _scale_prior(view: PAView | LateralView) -> tuple[float, bool]:
    """(initial PA scale, whether it is the model's prior): the payload's projection, else the
    acquisition's magnification, else ``PA_MAGNIFICATION_PRIOR``'s mean."""
    if view.projection is not None:
        return float(view.projection.scale), False
    acq = view.acquisition
    if acq is not None and acq.magnification is not None:
        return float(acq.magnification), False
    if acq is not None and acq.perspective:
        assert acq.distance_source_to_detector_mm is not None and acq.distance_source_to_patient_mm is not None
        return acq.distance_source_to_detector_mm / acq.distance_source_to_patient_mm, False
    calibrated = calibrated_magnification(view)
    if calibrated is not None:
        return calibrated, False
    return PA_MAGNIFICATION_PRIOR[0], True


def place_without_boundary(
    model: JobPayload,
    profile: Profile,
    pa: LandmarkArrays,
    lateral: LandmarkArrays | None,
    prior: TiltPrior | None,
) -> Placement:
    """Estimate T1 and L5 poses and the views' projections from the generic spine and the landmarks,
    any subset of levels on each view (module docstring). The fit then frees every vertebra and
    estimates the projections; this is its starting point."""
    e_c, e_r = image_axes(model.pa.patient_orientation)
    normal = cross(e_c, e_r)
    generic = rest_shape_unit(profile)[1]
    s, from_prior = _scale_prior(model.pa)
    pa_estimated = model.pa.projection is None
    size = size_factor(profile, ViewData("pa", pa.indices, pa.points, e_c, e_r, s, np.zeros(2), 1.0))
    model_positions = generic * size
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(model_positions, axis=0), axis=1))])
    generic_inplane = np.stack([model_positions @ e_c, model_positions @ e_r], axis=1)

    # in-plane coordinates (patient mm, up to the translation): landmarks where given
    scaled = np.full((N_LEVELS, 2), np.nan)
    if model.pa.projection is not None:
        T = np.asarray(model.pa.projection.translation, dtype=float)
        scaled[pa.indices] = (pa.points - T) / s
        inplane = _fill_along_generic(scaled, generic_inplane, arc)
    else:
        scaled[pa.indices] = pa.points / s
        inplane = _fill_along_generic(scaled, generic_inplane, arc)
        T = s * inplane[0]  # gauge: T1 in-plane at the origin
        inplane = inplane - inplane[0]
    depth = model_positions @ normal - float(model_positions[0] @ normal)

    lateral_projection: tuple[float, FloatArray] | None = None
    lateral_estimated = False
    if lateral is not None and model.lateral is not None and len(lateral.indices):
        lc, lr = image_axes(model.lateral.patient_orientation)
        # the lateral's image axis along the vertical, which both films share: its rows, or its columns
        # on a film turned a quarter; the other one runs along the PA's normal (depth)
        vertical = 1 if abs(float(lr @ _Z)) == 1.0 else 0
        across = 1 - vertical
        centre = inplane[:, :1] * e_c + inplane[:, 1:] * e_r + depth[:, None] * normal
        if model.lateral.projection is not None:
            sl = float(model.lateral.projection.scale)
            Tl = np.asarray(model.lateral.projection.translation, dtype=float)
        else:
            lateral_estimated = True
            acq = model.lateral.acquisition
            model_2d = np.stack([centre[lateral.indices] @ lc, centre[lateral.indices] @ lr], axis=1)
            if acq is not None and acq.magnification is not None:
                sl = float(acq.magnification)
            elif len(lateral.indices) >= 2 and np.ptp(model_2d[:, vertical]) > 0:
                # the vertical: the lateral's landmarks along it against the model's
                sl = float(np.polyfit(model_2d[:, vertical], lateral.points[:, vertical], 1)[0])
                sl = sl if sl > 0 else s
            else:
                sl = s
            Tl = (lateral.points - sl * model_2d).mean(axis=0)
        lateral_projection = (sl, Tl)
        # depth along the normal of the PA view from the lateral's other axis (up to its sign)
        along = float((lc, lr)[across] @ normal)
        if abs(along) == 1.0:
            measured = np.full(N_LEVELS, np.nan)
            measured[lateral.indices] = (lateral.points[:, across] - Tl[across]) / sl * along
            ok = np.isfinite(measured)
            if ok.sum() >= 2:
                offset = np.interp(arc, arc[ok], measured[ok] - depth[ok])
                depth = depth + offset

    centreline = inplane[:, :1] * e_c + inplane[:, 1:] * e_r + depth[:, None] * normal
    frames = frames_from_centreline(centreline)
    observed, _ = observed_frontal_tilts(pa, e_c, e_r)
    predicted = prior_tilts_deg(prior, pa, e_c, e_r) if prior is not None and is_frontal(e_c, e_r) else None
    ends = []
    for i in (0, N_LEVELS - 1):
        R = frames[i]
        if observed is not None and np.isfinite(observed[i]):
            R = _turn_to_frontal_tilt(R, float(observed[i]))
        elif predicted is not None and np.isfinite(predicted[i]):
            R = _turn_to_frontal_tilt(R, float(predicted[i]))
        ends.append(Pose(centreline[i], R))

    unreliable: list[Unreliable] = []
    if from_prior:
        unreliable.append("scale")
    depth_known = lateral is not None and len(lateral.indices) >= 2
    if not depth_known:
        unreliable += ["depth", "kyphosis", "lordosis", "plane_of_max_curvature"]
    if not pa.has_pedicles.any():
        unreliable += ["axial_rotation", "twist"]
    return Placement(
        top=ends[0],
        bottom=ends[1],
        pa=(s, T),
        lateral=lateral_projection,
        pa_estimated=pa_estimated,
        lateral_estimated=lateral_estimated,
        unreliable=unreliable,
        centreline=centreline,
        pa_prior_tilts_deg=predicted,
    )
