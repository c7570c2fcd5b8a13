"""Turn a raw payload (a JSON object) into a validated ``JobPayload`` or a typed ``InvalidInput``."""

import itertools
import math
import statistics
from typing import Any

from pydantic import ValidationError

from .errors import FieldError, InvalidInput, UnknownProfile
from .lateral_profile import inverted_profile_errors
from .levels import LEVEL_INDEX, LEVELS
from .models import LANDMARK_SD_MM_DEFAULT, SPINE_TO_DETECTOR_MM, JobPayload, Landmark, LateralView, PAView
from .profile_files import is_profile, list_profiles

_FIELD_OF_ERROR = {"landmark_point_missing": "point", "landmark_point_and_corners": "corners"}
"""Errors raised by a model validator on a whole landmark, and the field their location names."""

_UPRIGHT_ROWS = ("H", "F")
_FRONTAL_COLUMNS = ("L", "R")
_DEPTH_AXES = ("A", "P")
Point = tuple[float, float]


def _clean_loc(loc: tuple[Any, ...], kind: str = "") -> tuple[str | int, ...]:
    # pydantic adds the type of a union member or a validator tag to the location: drop them.
    clean = tuple(p for p in loc if isinstance(p, int) or not str(p).startswith(("function-", "tagged-union")))
    return (*clean, _FIELD_OF_ERROR[kind]) if kind in _FIELD_OF_ERROR else clean


def _message(error: Any) -> str:
    """A pydantic error's message in the contract's words: a number sent as a string or a boolean (refused by
    ``models.Number``) says which JSON type came and that a number is expected (not the value: messages never
    quote payload content); others as pydantic words them, without its "Value error, " prefix."""
    value = error.get("input")
    if error["type"] == "float_type" and isinstance(value, bool):
        return "a number is expected, not a boolean (true or false)"
    if error["type"] == "float_type" and isinstance(value, str):
        return "a number is expected, not a string: send a JSON number, without quotes"
    return str(error["msg"]).removeprefix("Value error, ")


def _landmark_form_errors(name: str, view: PAView | LateralView, raw: Any) -> list[FieldError]:
    """Corners need an upright view and pedicles a frontal one; locations use the payload's indices."""
    errors: list[FieldError] = []
    raw_landmarks = raw.get("landmarks") if isinstance(raw, dict) else None
    if not isinstance(raw_landmarks, list):
        return errors
    column, row = view.patient_orientation
    for i, lm in enumerate(raw_landmarks):
        if not isinstance(lm, dict):
            continue
        if lm.get("corners") is not None and row not in _UPRIGHT_ROWS:
            errors.append(
                FieldError(
                    (name, "landmarks", i, "corners"),
                    f"corners need an upright image (row direction H or F), got patient orientation {[column, row]}",
                    "corners_need_upright_view",
                )
            )
        if lm.get("pedicles") is not None and (name != "pa" or column not in _FRONTAL_COLUMNS):
            errors.append(
                FieldError(
                    (name, "landmarks", i, "pedicles"),
                    "pedicles are supported on the PA view only, with columns toward the patient's L or R",
                    "pedicles_not_supported",
                )
            )
    return errors


def _top_midpoint(landmark: Landmark, rows_toward_head: bool = False) -> Point:
    """Image (column, row) of a landmark's superior (top) endplate midpoint: its point, or the mean of
    its top corners, the image's bottom ones on a film whose rows run toward the head (the superior
    endplate then lies lower in the image, as ``observations.corner_geometry`` reads it; the model
    requires a point or corners)."""
    if landmark.point is not None:
        return float(landmark.point[0]), float(landmark.point[1])
    assert landmark.corners is not None
    (c0, r0), (c1, r1) = landmark.corners[2:4] if rows_toward_head else landmark.corners[0:2]
    return 0.5 * (c0 + c1), 0.5 * (r0 + r1)


def _top_midpoints(view: PAView | LateralView) -> list[Point]:
    """``_top_midpoint`` of each of the view's landmarks, in its order, read under its orientation."""
    head_up = view.patient_orientation[1] == "H"
    return [_top_midpoint(lm, head_up) for lm in view.landmarks]


def _payload_index(raw: Any) -> dict[Any, int] | None:
    """Each level's index in the payload's own landmark list (errors name it), or None when the view
    has no list."""
    landmarks = raw.get("landmarks") if isinstance(raw, dict) else None
    if not isinstance(landmarks, list):
        return None
    return {lm.get("level"): i for i, lm in enumerate(landmarks) if isinstance(lm, dict)}


def _head_to_feet_axis(view: PAView | LateralView) -> int | None:
    """The image axis that runs head to feet: 1 when the view's rows run toward H or F, else 0 when its
    columns do (a film turned a quarter), else None (patient orientation, DICOM PS3.3 C.7.6.1.1.1)."""
    return next((k for k in (1, 0) if view.patient_orientation[k] in _UPRIGHT_ROWS), None)


def _has_scale(view: PAView | LateralView) -> bool:
    """Whether the view's coordinates convert to mm: given in mm, or px with a pixel spacing."""
    return view.units == "mm" or view.pixel_spacing is not None


def _order_errors(name: str, view: PAView | LateralView, raw: Any, scaled: bool = True) -> list[FieldError]:
    """Along the view's head-to-feet axis (its rows toward F or H, or, on a film turned a quarter, its
    columns) the levels must follow each other head to feet.

    A vertebra drawn above the one cranial to it, by more than its landmarks' noise allows
    (``NOISE_SDS``·√2·σ, σ the view's landmark SD, in rows through the view's row spacing), is an
    annotation error (swapped or misplaced landmarks) that no spine can have; it is refused rather
    than reconstructed into nonsense. Within the noise it is a real spine's film: a segment leaning
    far out of the film (VerSe dev's verse097, T1–T2 8 mm high on the PA) reads reversed under 3 mm
    of noise. With ``scaled`` False (a stand-in spacing until the header is read) the allowance is
    taken in the view's units as the scale-free distance check takes it (the median spacing over
    VerSe dev's mean arcs at the smallest magnification); px without a spacing (refused apart) and
    fewer than three levels without a scale are held strictly. Locations use the payload's own
    indices.
    """
    axis = _head_to_feet_axis(view)
    index = _payload_index(raw)
    if axis is None or index is None:
        return []
    direction = view.patient_orientation[axis]
    toward_feet = 1.0 if direction == "F" else -1.0
    unit = ("column", "row")[axis]
    levels = [LEVEL_INDEX[lm.level] for lm in view.landmarks]  # sorted by level
    points = _top_midpoints(view)
    noise_mm = NOISE_SDS * math.sqrt(2.0) * view.sd_mm
    allowance = 0.0
    if scaled and _has_scale(view):
        allowance = noise_mm / _mm_per_unit(view)[axis]
    elif not scaled and (spacing := _median_spacing(_consecutive_pairs(levels, points))) is not None:
        allowance = _in_stand_in_units(noise_mm, spacing)
    errors = []
    for (_, upper), (lower, below) in itertools.pairwise(zip(levels, points, strict=True)):
        step = (below[axis] - upper[axis]) * toward_feet
        if step < -allowance or (allowance == 0.0 and step == 0.0):
            noise = f" by more than its landmarks' noise allows ({allowance:g} {unit}s)" if allowance else ""
            errors.append(
                FieldError(
                    (name, "landmarks", index.get(LEVELS[lower], 0)),
                    f"level {LEVELS[lower]} ({unit} {below[axis]:g}) is not below the level above it ({unit} "
                    f"{upper[axis]:g}){noise}: on an image whose {unit}s run toward {direction}, landmarks must "
                    "run head to feet",
                    "landmarks_out_of_order",
                )
            )
    return errors


ACROSS_SPAN_LEVELS = 12
"""Landmarks this many levels apart or more are held to ``ACROSS_MAX_DEG`` (below)."""
ACROSS_MAX_DEG = 60.0
"""Largest angle between the head-to-feet axis of a film and the line through its top and bottom
landmarks when they are ``ACROSS_SPAN_LEVELS`` or more levels apart: a spine runs head to feet. On AASCE
2019 training's 454 radiographs whose landmarks run in order (major Cobb up to 94°), endplate midpoints 12
levels apart lie at most 26° from the image's vertical, T1 and L5 at most 12°; on VerSe dev's 24 spines,
12 or more levels apart, at most 9° in the frontal and 25° in the sagittal plane (8 levels apart). 60°, a
head-to-feet run of half the distance, leaves room for the severest curves and imbalance; a film whose
orientation names the wrong axis for its rows and columns reads near 90°."""


def _across_errors(name: str, view: PAView | LateralView) -> list[FieldError]:
    """The top and bottom landmarks, ``ACROSS_SPAN_LEVELS`` or more levels apart, must lie within
    ``ACROSS_MAX_DEG`` of the view's head-to-feet axis (its rows or columns toward F or H): the angle
    atan(|across| / |head to feet|) of their separation in mm. Refused at the view's orientation, the
    likelier mistake than every landmark."""
    axis = _head_to_feet_axis(view)
    if axis is None or len(view.landmarks) < 2:
        return []
    top, bottom = view.landmarks[0], view.landmarks[-1]
    if LEVEL_INDEX[bottom.level] - LEVEL_INDEX[top.level] < ACROSS_SPAN_LEVELS:
        return []
    scale = _mm_per_unit_if_known(view)
    tops = _top_midpoints(view)
    (c0, r0), (c1, r1) = tops[0], tops[-1]
    apart = ((c1 - c0) * scale[0], (r1 - r0) * scale[1])
    along, across = abs(apart[axis]), abs(apart[1 - axis])
    angle = math.degrees(math.atan2(across, along))
    if angle <= ACROSS_MAX_DEG:
        return []
    units = ("columns", "rows")
    length = "mm" if _has_scale(view) else "px"
    return [
        FieldError(
            (name, "patient_orientation"),
            f"{top.level} and {bottom.level} lie {angle:.0f}° from the film's head-to-feet axis (its {units[axis]}, "
            f"toward {view.patient_orientation[axis]}), {along:.0f} {length} apart along it and {across:.0f} {length} "
            "across it: "
            f"a spine runs head to feet (within {ACROSS_MAX_DEG:g}° over {ACROSS_SPAN_LEVELS} levels or more); "
            f"check the orientation, whose {units[1 - axis]} may be the ones that run toward the feet",
            "spine_across_the_film",
        )
    ]


def _raw_landmarks_with(raw: Any, field: str) -> list[tuple[int, dict[str, Any]]]:
    """(index in the payload's list, landmark) of each landmark of a raw view that gives ``field``."""
    landmarks = raw.get("landmarks") if isinstance(raw, dict) else None
    if not isinstance(landmarks, list):
        return []
    return [(i, lm) for i, lm in enumerate(landmarks) if isinstance(lm, dict) and lm.get(field) is not None]


def _corner_errors(name: str, raw: Any) -> list[FieldError]:
    """Each four-corner landmark must be a convex quadrilateral in the order the contract names
    (top-left, top-right, bottom-left, bottom-right as they appear in the image). Taken around the
    outline TL → TR → BR → BL in image (column, row) coordinates (rows run down), every turn is
    clockwise as displayed: the cross product (b − a) × (c − b) = (b−a)_c (c−b)_r − (b−a)_r (c−b)_c
    is > 0 at each of the four corners. Two corners swapped (top-right with bottom-left, or left with
    right) make the outline cross itself or turn the other way; a reflex corner or three corners in
    a line is no vertebral body either. Locations use the payload's indices."""
    errors = []
    for i, lm in _raw_landmarks_with(raw, "corners"):
        tl, tr, bl, br = ((float(c[0]), float(c[1])) for c in lm["corners"])
        outline = (tl, tr, br, bl)
        edges = [_minus(outline[(k + 1) % 4], outline[k]) for k in range(4)]
        turns = [_cross(edges[k], edges[(k + 1) % 4]) for k in range(4)]
        if min(turns) <= 0.0:
            if max(turns) < 0.0:
                kind = "run the wrong way round (two corners swapped)"
            else:
                kind = "cross each other" if _crossed(outline) else "do not form a convex quadrilateral"
            errors.append(
                FieldError(
                    (name, "landmarks", i, "corners"),
                    f"the corners of {lm.get('level')} {kind}: give them as they appear in the image, in the order "
                    "top-left, top-right, bottom-left, bottom-right, forming a convex quadrilateral",
                    "corners_not_convex",
                )
            )
        elif not (tr[0] > tl[0] and br[0] > bl[0]):
            errors.append(
                FieldError(
                    (name, "landmarks", i, "corners"),
                    f"the corners of {lm.get('level')} are turned by 90° or more in the image: its top edge "
                    f"(top-left → top-right) and bottom edge (bottom-left → bottom-right) must run toward the "
                    f"image's right, as an endplate tilted less than 90° does; give the corners as they appear",
                    "corners_not_upright",
                )
            )
    return errors


def _pedicle_errors(name: str, raw: Any) -> list[FieldError]:
    """A landmark's two pedicle centres are given image-left then image-right (the contract's
    order): the first column must be smaller than the second. Swapped, the fit reads them as a
    vertebra turned about 180° about its axis, and at one column as one turned 90° (its pedicles one
    behind the other), so they are refused as a misplaced annotation. Locations use the payload's
    indices."""
    errors = []
    for i, lm in _raw_landmarks_with(raw, "pedicles"):
        (left, _), (right, _) = ((float(c[0]), float(c[1])) for c in lm["pedicles"])
        if not left < right:
            where = "at one column" if left == right else f"image-right first (columns {left:g} then {right:g})"
            errors.append(
                FieldError(
                    (name, "landmarks", i, "pedicles"),
                    f"the pedicles of {lm.get('level')} are given {where}: give the image-left pedicle's centre "
                    "first, then the image-right one; a vertebra's two pedicles lie side by side on a PA film",
                    "pedicles_not_in_order",
                )
            )
    return errors


def _minus(a: Point, b: Point) -> Point:
    return a[0] - b[0], a[1] - b[1]


def _cross(a: Point, b: Point) -> float:
    """z component of the 2D cross product a × b = a_c b_r − a_r b_c."""
    return a[0] * b[1] - a[1] * b[0]


def _crossed(outline: tuple[Point, ...]) -> bool:
    """Whether the outline's opposite sides TL→TR and BR→BL, or TR→BR and BL→TL, intersect."""

    def intersect(a: Point, b: Point, c: Point, d: Point) -> bool:
        def side(p: Point, q: Point, r: Point) -> float:
            return _cross(_minus(q, p), _minus(r, p))

        return side(a, b, c) * side(a, b, d) < 0.0 and side(c, d, a) * side(c, d, b) < 0.0

    tl, tr, br, bl = outline
    return intersect(tl, tr, br, bl) or intersect(tr, br, bl, tl)


MEAN_SEGMENT_MM = (20.3, 20.8, 20.9, 20.9, 22.2, 22.3, 23.0, 23.5, 24.9, 26.4, 28.6, 30.7, 32.7, 34.4, 35.3, 33.8)
"""Mean distance between the centroids of adjacent vertebrae T1–T2 … L4–L5 over the 24 VerSe dev
spines (tests/data/verse_dev.csv, 3D, mm, rounded to 0.1; a test recomputes it). The reference
length of levels i < j is the arc A_ij = Σ_{l=i}^{j−1} MEAN_SEGMENT_MM[l]."""
_ARC = [sum(MEAN_SEGMENT_MM[:k]) for k in range(len(MEAN_SEGMENT_MM) + 1)]
"""A_0j, mm: the VerSe dev mean arc from T1 to level j."""
VERSE_DISTANCE_RATIO = (0.385, 1.289)
"""Smallest and largest ratio |r_j − r_i| / A_ij over every pair of levels of the VerSe dev spines:
0.385 for the distance projected on a PA film (the (x, z) plane: L4–L5, whose segment leans far
forward in the lordosis, is the shortest), 1.289 in 3D (a projection is never longer). A test
recomputes both."""
SMALLEST_SPINE = 0.6
"""Widening of the lower bound for spines smaller than VerSe's adults (vertebral body plus disc
heights scale with the spine's length): at 6–8 years the T1–T12 distance is 71–73 % of its final
length ("Thoracic cage volume and dimension assessment by optoelectronic molding in normal children
and adolescents during growth", 2019, 622 healthy children aged 6–18, science.ulysseus.eu record
r245b-mnc02), and at the adolescent growth spurt's peak the spine is 87 % of its adult length
(Sanders et al., Spine Deform 2025;13(2):519–528, doi:10.1007/s43390-024-01011-w). VerSe dev's
smallest spine is 0.92 of its mean length: 0.92 × 0.71 = 0.65, and 0.6 leaves room below it."""
LARGEST_SPINE = 1.25
"""Widening of the upper bound for spines larger than VerSe dev's (its T1–L5 polylines 388–498 mm,
mean 421): the thoracic vertebral bodies' heights (Panjabi et al., "Thoracic human vertebrae:
quantitative three-dimensional anatomy", Spine 1991;16(8):888–901) and the lumbar ones' (Panjabi
et al., "Human lumbar vertebrae: quantitative three-dimensional anatomy", Spine 1992;17(3):299–306)
have coefficients of variation near 10 % among adults, so a segment 25 % above the dev maximum ratio
(itself 29 % above the mean) is beyond any adult's."""
LABEL_SHIFT = 1
"""Levels by which a landmark's label may be off the anatomy's count without the spine being
implausible: transitional vertebrae (a lumbosacralised or sacralised lowest vertebra, 11 or 13
rib-bearing vertebrae) are common (Apazidis et al., "The prevalence of transitional vertebrae in the
lumbar spine", Spine J 2011;11(9):858–862), so levels labelled i and j may be j − i + 1 segments
apart. The upper bound uses that longer arc; the page's T1 and T2 336 mm apart are still refused."""
MAGNIFICATION_RANGE = (0.9, 1.4)
"""Detector mm per patient mm a view may have when the payload does not say: below 1 for a
calibration that overshot, up to 1.4 for a lateral film of a broad patient at a short distance."""
UNVERIFIED_SCALE = 2.5
"""Without a magnification in the payload nothing ties the stated millimetres to the patient: the
spacing may be nominal (a film digitised without a scale: the AASCE 2019 bench spreads each image's
height over a 36-inch cassette, and on its well-formed training annotations adjacent levels then
read up to 1.7 times the largest VerSe-based bound at magnification 1.4). The range
``MAGNIFICATION_RANGE`` is then widened by this factor both ways: the absolute check still refuses
a label several levels off (the page's T1 and T2 336 mm apart: 95 mm at the widest reading against
at most 33 mm), and the scale-free check does the finer work."""
MAGNIFICATION_SPREAD = 0.1
"""When the payload gives the magnification (ERMF, SID/SOD or a projection's scale): the relative
spread around it of the magnification of points off the mid-plane (± 150 mm of depth at SOD ≈ 1.5 m)."""
NOISE_SDS = 3.0
"""Landmark noise allowed for: a distance may be off by NOISE_SDS · √2 · σ, σ the view's landmark SD."""
SPACING_RATIO = (0.25, 2.5)
"""Scale-free bounds on the ratio q = d / A_ij of one pair of consecutive landmarked levels. Upper:
over the median q of the view's pairs; lower: over the median q of its neighbours, the up to
``SPACING_NEIGHBOURS`` pairs on each side. VerSe dev's within-spine extremes are 0.41–1.21 against
the view's median on the PA projection and 0.80–1.20 on the lateral, synthetic severe curves
(``spine_engine.synthetic``, Cobb up to 80°) reach 0.51–1.30 on the lateral, and the AASCE 2019
training radiographs' well-formed annotations 0.36–1.82 (clicked corners, cropped films); widened
beyond all three, so the upper bound holds landmarks clicked about 1 mm off
(``LANDMARK_SD_MM_DEFAULT``; a larger stated noise widens both, ``_distance_errors``). Against the
neighbours a segment that leans out of the film is compared with segments that lean too: the
lowest ratio is 0.53 on VerSe dev (verse097's T2–T3, 8 mm on the PA between neighbours of 8–19 mm)
and 0.55 on AASCE training's well-formed annotations, two labels on one vertebra read 0.03–0.05
(three AASCE annotations), so the lower bound 0.25 lies 3 SDs of 1 mm clicks below verse097's
(its ratio's SD is about 0.09 there) and refuses a second label on a vertebra clicked within 4.9 mm
of the first between neighbours 19.5 mm apart (``python -m tools.spacing_ratio`` prints the
extremes). Against the view's median, verse097's T2–T3 reads 0.41, 2.2 SDs of 1 mm clicks above
0.25."""
SPACING_NEIGHBOURS = 2
"""Pairs on each side of a pair whose median q its lower scale-free bound compares it with
(``SPACING_RATIO``), as the page's skipped-vertebra warning (web/src/checks.ts)."""


def _mm_per_unit(view: PAView | LateralView) -> Point:
    """(column, row) mm per unit of the view's coordinates: 1 in mm, the pixel spacing [row, column]
    swapped in px (the conversion of ``clinical.detector_spacing`` before any calibration factor;
    not imported from there, which would load the fit's stack with the validation)."""
    if view.units == "px":
        assert view.pixel_spacing is not None  # _view_errors refused px without a spacing first
        return float(view.pixel_spacing[1]), float(view.pixel_spacing[0])
    return 1.0, 1.0


def _mm_per_unit_if_known(view: PAView | LateralView) -> Point:
    """``_mm_per_unit``, or (1, 1) for px without a spacing (refused apart, ``_view_errors``)."""
    return _mm_per_unit(view) if _has_scale(view) else (1.0, 1.0)


def _magnification_range(view: PAView | LateralView) -> tuple[float, float]:
    """Film mm per patient mm at the spine, lowest and highest (``MAGNIFICATION_*``): 1 ± spread for
    a 'calibrated' spacing (mm in the patient's plane, PS3.3 §10.7.1.1)."""
    acq = view.acquisition
    known: float | None = None
    if view.pixel_spacing_calibration == "calibrated":
        known = 1.0
    elif view.projection is not None:
        known = float(view.projection.scale)
    elif acq is not None and acq.magnification is not None:
        known = float(acq.magnification)
    elif acq is not None and acq.perspective:
        assert acq.distance_source_to_detector_mm is not None and acq.distance_source_to_patient_mm is not None
        known = acq.distance_source_to_detector_mm / acq.distance_source_to_patient_mm
    if known is None:
        return MAGNIFICATION_RANGE[0] / UNVERIFIED_SCALE, MAGNIFICATION_RANGE[1] * UNVERIFIED_SCALE
    return known * (1.0 - MAGNIFICATION_SPREAD), known * (1.0 + MAGNIFICATION_SPREAD)


SOURCE_TO_SPINE_MIN_MM = 300.0
"""Smallest distance from the X-ray source to the spine a radiograph can have, mm: regulations hold
even mobile and portable radiographic systems to a source-to-skin distance of at least 30 cm (Oregon
OAR 333-106-0310; New York 10 NYCRR 16.57(a)(6), 12 inches), and the spine lies deeper than the skin."""


def _geometry_errors(name: str, view: PAView | LateralView, scaled: bool = True) -> list[FieldError]:
    """A point-source view's geometry, with what it lacks filled in (``Acquisition.point_source_distances``),
    must hold the spine at least ``SOURCE_TO_SPINE_MIN_MM`` from the source and magnify it at most as
    much as the widest reading of unverified millimetres (``MAGNIFICATION_RANGE`` × ``UNVERIFIED_SCALE``,
    3.5); an ERMF, and a given projection's scale, likewise within that reading both ways (a scale of
    1000 ended in ``FitFailed``). Beyond, the fit would place a spine
    millimetres or metres long (an SID of 150 mm, the SOD assumed 200 mm nearer the source, put it
    behind the source). The central ray's distance from the landmarks is a distance in film mm, so
    with ``scaled`` False (a stand-in spacing until the header is read) it is judged once the header
    gives the spacing, as ``_distance_errors``' absolute bound."""
    low, high = MAGNIFICATION_RANGE[0] / UNVERIFIED_SCALE, MAGNIFICATION_RANGE[1] * UNVERIFIED_SCALE
    errors = []
    if view.projection is not None and not low <= view.projection.scale <= high:
        errors.append(FieldError(
            (name, "projection", "scale"),
            f"a projection scale of {view.projection.scale:g} is beyond any radiograph's: the spine's image is "
            f"{low:.2g}–{high:.2g} times its size (detector mm per patient mm)",
            "implausible_geometry",
        ))  # fmt: skip
    acq = view.acquisition
    if acq is None:
        return errors
    if acq.magnification is not None and not low <= acq.magnification <= high:
        errors.append(FieldError(
            (name, "acquisition", "magnification"),
            f"a magnification of {acq.magnification:g} is beyond any radiograph's: the spine's image is "
            f"{low:.2g}–{high:.2g} times its size (ERMF, DICOM (0018,1114))",
            "implausible_geometry",
        ))  # fmt: skip
    errors += _outside_image_errors(name, view)
    distances = acq.point_source_distances()
    if distances is not None and not errors:
        sid, sod = distances
        stated = {"distance_source_to_detector_mm": acq.distance_source_to_detector_mm,
                  "distance_source_to_patient_mm": acq.distance_source_to_patient_mm}  # fmt: skip
        given = [f for f, v in stated.items() if v is not None]
        loc = (name, "acquisition", given[0]) if len(given) == 1 else (name, "acquisition")
        if sod < SOURCE_TO_SPINE_MIN_MM:
            sod_assumed = acq.distance_source_to_patient_mm is None and acq.magnification is None
            how = f"SID {sid:g} mm puts the spine" if sod_assumed else "the geometry puts the spine"
            assumed = (f" (with no SOD or magnification given, the spine's mid-plane is taken "
                       f"{SPINE_TO_DETECTOR_MM:g} mm before the detector)" if sod_assumed else "")  # fmt: skip
            errors.append(FieldError(
                loc,
                f"{how} {sod:g} mm from the source{assumed}; a radiograph's source lies at least "
                f"{SOURCE_TO_SPINE_MIN_MM:g} mm from the skin, the spine deeper",
                "implausible_geometry",
            ))  # fmt: skip
        elif sid / sod > high:
            errors.append(FieldError(
                loc,
                f"SID {sid:g} mm and SOD {sod:g} mm{' (assumed)' if len(given) < 2 else ''} magnify the spine "
                f"{sid / sod:.3g} times; no radiograph magnifies it more than {high:.2g} times",
                "implausible_geometry",
            ))  # fmt: skip
        elif scaled and (ray := _central_ray(view)) is not None and view.landmarks:
            field_name, (ray_c, ray_r) = ray
            column_mm, row_mm = _mm_per_unit_if_known(view)
            farthest = max(math.hypot((c - ray_c) * column_mm, (r - ray_r) * row_mm)
                           for c, r in _top_midpoints(view))  # fmt: skip
            if farthest > sid * math.tan(math.radians(RAY_OBLIQUITY_MAX_DEG)):
                errors.append(FieldError(
                    (name, "acquisition", field_name),
                    f"the central ray{' (the image centre)' if field_name == 'image_size' else ''} meets the film "
                    f"{farthest:.0f} mm from the farthest landmark, more than the SID ({sid:g} mm): the spine would be "
                    f"filmed by rays more than {RAY_OBLIQUITY_MAX_DEG:g}° from the central ray, which no X-ray tube "
                    "emits",
                    "implausible_geometry",
                ))  # fmt: skip
    return errors


def _outside_image_errors(name: str, view: PAView | LateralView) -> list[FieldError]:
    """With ``acquisition.image_size`` [columns, rows] given, every landmark point (top midpoint, corners,
    pedicles) must lie on the image, (0, 0) to (columns, rows) in the view's units, give or take
    ``NOISE_SDS`` landmark SDs: a click is on the film. Off it, the image size or the landmarks are in
    other units (mm for px), and the image's centre, where the central ray is then taken, is wrong."""
    acq = view.acquisition
    if acq is None or acq.image_size is None:
        return []
    columns, rows = float(acq.image_size[0]), float(acq.image_size[1])
    column_mm, row_mm = _mm_per_unit_if_known(view)
    margin = NOISE_SDS * view.sd_mm
    for lm in view.landmarks:
        points = [p for p in (lm.point, *(lm.corners or ()), *(lm.pedicles or ())) if p is not None]
        for c, r in points:
            if not (-margin / column_mm <= c <= columns + margin / column_mm
                    and -margin / row_mm <= r <= rows + margin / row_mm):  # fmt: skip
                return [FieldError(
                    (name, "acquisition", "image_size"),
                    f"landmark {lm.level} at (column {c:g}, row {r:g}) lies off the image of {columns:g} × {rows:g} "
                    f"(columns × rows, in {view.units}): the image size and the landmarks must be in the same units, "
                    "the landmarks on the image",
                    "landmark_off_image",
                )]  # fmt: skip
    return []


RAY_OBLIQUITY_MAX_DEG = 45.0
"""Largest angle at the source between the central ray and the ray to a landmark that a point-source
view may imply: a diagnostic tube's anode angle, about 12–20°, bounds its field on the anode side
(rays beyond it are absorbed in the anode: the heel effect; Bushberg et al., The Essential Physics
of Medical Imaging, 3rd ed., 2012, ch. 6, anode angle and field coverage), and 45° leaves the
cathode side and any stitched film room. A central ray or image centre farther than the SID from a
landmark (a typo, or coordinates in other units) is refused rather than fitted: at a kilometre the
fit reported intervals of 10⁻¹² ° or did not converge."""


def _central_ray(view: PAView | LateralView) -> tuple[str, Point] | None:
    """The field that places the view's central ray and where it meets the film (view units): the given
    ``central_ray``, else the centre of ``image_size`` (``models.Acquisition``), else None."""
    acq = view.acquisition
    if acq is None:
        return None
    if acq.central_ray is not None:
        return "central_ray", (float(acq.central_ray[0]), float(acq.central_ray[1]))
    if acq.image_size is not None:
        return "image_size", (0.5 * float(acq.image_size[0]), 0.5 * float(acq.image_size[1]))
    return None


def _consecutive_pairs(levels: list[int], points: list[Point]) -> list[tuple[int, int, float, float]]:
    """(i, j, d, A_ij) of each two consecutive landmarked levels i < j: their distance d in the
    points' units and VerSe dev's mean arc A_ij between them (mm)."""
    return [(i, j, math.dist(p, q), _ARC[j] - _ARC[i]) for (i, p), (j, q) in
            itertools.pairwise(zip(levels, points, strict=True))]  # fmt: skip


def _median_spacing(pairs: list[tuple[int, int, float, float]]) -> float | None:
    """The view's spacing q: the median of d / A_ij over its pairs (units per patient mm of arc), None
    below two pairs."""
    return statistics.median(d / a for _, _, d, a in pairs) if len(pairs) >= 2 else None


def _neighbour_spacings(pairs: list[tuple[int, int, float, float]]) -> list[float | None]:
    """For each pair, the median q = d / A_ij of the up to ``SPACING_NEIGHBOURS`` pairs on each side
    of it (units per patient mm of arc), None for a view of one pair."""
    q = [d / a for _, _, d, a in pairs]
    return [
        statistics.median(q[max(0, k - SPACING_NEIGHBOURS) : k] + q[k + 1 : k + 1 + SPACING_NEIGHBOURS])
        if len(q) >= 2 else None
        for k in range(len(q))
    ]  # fmt: skip


def spacing_ratios(levels: list[int], points: list[Point]) -> list[tuple[float, float]]:
    """For each two consecutive landmarked levels (``levels`` increasing, ``points`` in one isotropic
    unit), q = d / A_ij over the view's median q and over its neighbours' (``_neighbour_spacings``): the
    ratios the scale-free bounds ``SPACING_RATIO`` judge, without noise; empty below two pairs."""
    pairs = _consecutive_pairs(levels, points)
    median = _median_spacing(pairs)
    if median is None:
        return []
    local = _neighbour_spacings(pairs)
    return [(d / a / median, d / a / n) for (_, _, d, a), n in zip(pairs, local, strict=True) if n is not None]


def _in_stand_in_units(mm: float, spacing: float) -> float:
    """``mm`` of film in the units of a stand-in spacing (until the header is read), read through the
    view's median spacing at the smallest magnification of ``MAGNIFICATION_RANGE`` (the most lenient
    reading): mm · q / 0.9."""
    return mm * spacing / MAGNIFICATION_RANGE[0]


def _distance_errors(name: str, view: PAView | LateralView, raw: Any, scaled: bool = True) -> list[FieldError]:
    """Distances between consecutive landmarked levels i < j (k = j − i apart; each landmark's
    top-endplate midpoint: its point, or the mean of its top corners) that no spine has.

    Absolute bound. The view's coordinates times ``_mm_per_unit`` are film mm (units mm, or px with
    the pixel spacing the contract requires), so a distance d is known in film mm; the magnification
    m is 1 for a 'calibrated' spacing (patient-plane mm), else the payload's (ERMF, SID/SOD or the
    projection's scale), ± ``MAGNIFICATION_SPREAD``, or else anywhere in ``MAGNIFICATION_RANGE`` widened by
    ``UNVERIFIED_SCALE`` (the stated mm themselves unverified). Refused when even the
    most favourable reading is impossible:
        (d − n)/m_max > LARGEST_SPINE · ρ_max · A_ij    (too far apart), or
        (d + n)/m_min < SMALLEST_SPINE · ρ_min · A_ij   (too close),
    with n = NOISE_SDS·√2·σ, (ρ_min, ρ_max) = ``VERSE_DISTANCE_RATIO``, A_ij the VerSe dev mean arc
    (in the upper bound extended by ``LABEL_SHIFT`` segments below level j).
    The ratio bounds hold for every k (a chord is at most its arc); for adjacent levels the lower
    bound is below the noise allowance and catches only two clicks on one vertebra.

    Scale-free bounds. The film's scale (weak perspective s) is estimated in the fit and the stated
    millimetres may be nominal (e.g. a spacing spread over a cassette's height when the image has
    none), so with three or more landmarked levels the pairs are also compared with each other, for
    some distance within e of d: refused when (d − e)/A_ij > SPACING_RATIO[1]·median, the median q =
    d / A_ij of the view's pairs, or (d + e)/A_ij < SPACING_RATIO[0]·local, the median q of the up to
    ``SPACING_NEIGHBOURS`` pairs on each side (``_neighbour_spacings``: a segment leaning far out of
    the film, as VerSe dev's verse097's upper thoracic spine, 8 mm on the PA against 19 mm of arc,
    is compared with its neighbours, which lean too). The bounds hold clicks of the default 1 mm
    (``SPACING_RATIO``), so e allows for the stated noise beyond it, e = NOISE_SDS·√(2(σ² − 1 mm²)).
    A label on the wrong vertebra (a click meant as L5 labelled T2) breaks both checks whatever the
    scale, and two labels on one vertebra the lower scale-free one.
    The error names both levels, at the lower level's landmark. Locations use the payload's indices.
    ``scaled`` False (a stand-in spacing until the image's header is read): the scale-free check only,
    its e in the view's units taken at the smallest magnification of ``MAGNIFICATION_RANGE``
    (e · median / 0.9: the median q is film mm per patient mm over the unknown spacing).
    """
    index = _payload_index(raw)
    if index is None:
        return []
    column_mm, row_mm = _mm_per_unit(view)
    levels = [LEVEL_INDEX[lm.level] for lm in view.landmarks]  # sorted by level
    points = [(column * column_mm, row * row_mm) for column, row in _top_midpoints(view)]  # film mm
    m_min, m_max = _magnification_range(view)
    sigma = view.sd_mm
    noise = NOISE_SDS * math.sqrt(2.0) * sigma
    lo, hi = VERSE_DISTANCE_RATIO
    pairs = _consecutive_pairs(levels, points)
    median = _median_spacing(pairs)
    excess = NOISE_SDS * math.sqrt(2.0 * max(sigma**2 - LANDMARK_SD_MM_DEFAULT**2, 0.0))
    n_units = excess if scaled or median is None else _in_stand_in_units(excess, median)
    errors = []
    for (i, j, d, a), local in zip(pairs, _neighbour_spacings(pairs), strict=True):
        upper, lower = LEVELS[i], LEVELS[j]
        apart = "adjacent levels" if j - i == 1 else f"levels {j - i} apart"
        reason = None
        a_up = a + sum(MEAN_SEGMENT_MM[min(j + k, len(MEAN_SEGMENT_MM) - 1)] for k in range(LABEL_SHIFT))
        if scaled and (d - noise) / m_max > LARGEST_SPINE * hi * a_up:
            reason = (f"are {d:.0f} mm apart on the film; {apart} of any spine are at most "
                      f"{LARGEST_SPINE * hi * a_up * m_max + noise:.0f} mm apart at magnification up to {m_max:.3g}")
        elif scaled and (d + noise) / m_min < SMALLEST_SPINE * lo * a:
            reason = (f"are {d:.1f} mm apart on the film; {apart} of any spine are at least "
                      f"{max(SMALLEST_SPINE * lo * a * m_min - noise, 0.0):.1f} mm apart at magnification down to "
                      f"{m_min:.3g}")
        elif median is not None and median > 0.0 and (d - n_units) / a / median > SPACING_RATIO[1]:
            stated = f", give or take {excess:.1f} mm for the stated landmark noise" if excess else ""
            reason = (f"are {d / a / median:.2f} times as far apart as the other landmarks' spacing predicts; no "
                      f"spine's spacing varies that much (allowed up to {SPACING_RATIO[1]:g}{stated})")
        elif local is not None and local > 0.0 and (d + n_units) / a / local < SPACING_RATIO[0]:
            stated = f", give or take {excess:.1f} mm for the stated landmark noise" if excess else ""
            reason = (f"are {d / a / local:.2f} times as far apart as the neighbouring landmarks' spacing predicts, as "
                      f"if both were on one vertebra; no spine's spacing shrinks that much from one level to the next "
                      f"(allowed down to {SPACING_RATIO[0]:g}{stated})")
        if reason is not None:
            errors.append(
                FieldError(
                    (name, "landmarks", index.get(lower, 0)),
                    f"{upper} and {lower} {reason}: check which vertebra each landmark is on",
                    "implausible_distance",
                )
            )
    return errors


MIN_LEVELS_PROJECTION_GIVEN = 1
"""A view whose projection is given (and, for the PA, with T1 and L5 given exactly) needs one level."""
MIN_LEVELS_PA = 2
"""The PA view otherwise needs two levels: its translation (2 unknowns) and, with the magnification
from the prior or the acquisition, the spine's extent along the film; below that the placement of
the spine in the film is undetermined."""
MIN_LEVELS_LATERAL = 3
"""A lateral view with its projection estimated needs three levels: its scale and vertical
translation are tied to the PA by the vertical axis both films share (two levels), and its in-plane
rotation needs a third. With fewer, leave the lateral out (a lateral with no landmark is ignored)."""


def minimum_levels(name: str, view: PAView | LateralView, exact_boundary: bool) -> int:
    """The fewest landmarked levels the view needs (``MIN_LEVELS_*``); 0 for an empty lateral."""
    if name != "pa" and not view.landmarks:
        return 0
    if view.projection is not None and (name != "pa" or exact_boundary):
        return MIN_LEVELS_PROJECTION_GIVEN
    return MIN_LEVELS_PA if name == "pa" else MIN_LEVELS_LATERAL


def _plane_errors(name: str, view: PAView | LateralView) -> list[FieldError]:
    """A view's patient orientation must name its film's plane (DICOM PS3.3 C.7.6.1.1.1, Patient
    Orientation: L/R, A/P and H/F, the directions of the image's columns and rows). The PA film is a
    frontal projection, its image in the patient's (x, z) plane: neither axis may run toward A or P.
    The lateral film is a sagittal projection, its image in the (y, z) plane: neither axis may run
    toward L or R. Named otherwise, the PA film would show no frontal coordinate (every Cobb angle the
    prior's, reported as if the film showed it) and the lateral no depth (kyphosis and lordosis read
    from two frontal films)."""
    column, row = view.patient_orientation
    excluded, plane = (_DEPTH_AXES, "frontal (x, z)") if name == "pa" else (_FRONTAL_COLUMNS, "sagittal (y, z)")
    if column in excluded or row in excluded:
        return [
            FieldError(
                (name, "patient_orientation"),
                f"the {name} view is a {plane} film, so neither its column nor its row direction can be"
                f" {' or '.join(excluded)}; got {[column, row]}: check which film is which and its orientation",
                "orientation_not_of_view",
            )
        ]
    return []


def _view_errors(name: str, view: PAView | LateralView, exact_boundary: bool) -> list[FieldError]:
    """px units need a pixel spacing; a view needs at least ``minimum_levels`` landmarked levels
    (any levels: none is required on either view)."""
    errors = []
    if view.units == "px" and view.pixel_spacing is None:
        errors.append(
            FieldError((name, "pixel_spacing"), "pixel_spacing is required when units is 'px'", "missing")
        )
    need = minimum_levels(name, view, exact_boundary)
    have = len({lm.level for lm in view.landmarks})
    if have < need:
        why = (
            "to place the spine in the film" if name == "pa" else
            "to estimate its scale, translation and rotation against the PA (or give lateral.projection, "
            "or leave the lateral out)"
        )  # fmt: skip
        errors.append(
            FieldError(
                (name, "landmarks"),
                f"the {name} view has {have} landmarked level(s); at least {need} are needed {why}",
                "too_few_landmarks",
            )
        )
    return errors


def _profile_errors(name: str, view: LateralView) -> list[FieldError]:
    """A lateral view whose thoracic and lumbar profiles both read inverted under its stated orientation
    (``lateral_profile.inverted_profile_errors``: a film mirrored left to right), on its landmarks' top
    endplate midpoints in film mm (``_mm_per_unit``: a non-square pixel spacing would change angles)."""
    column_mm, row_mm = _mm_per_unit(view)
    landmarks = [(LEVEL_INDEX[lm.level], c * column_mm, r * row_mm)
                 for lm, (c, r) in zip(view.landmarks, _top_midpoints(view), strict=True)]  # fmt: skip
    return inverted_profile_errors(name, view.patient_orientation, landmarks, view.sd_mm)


def validate_payload(payload: Any, unscaled_views: tuple[str, ...] = ()) -> JobPayload:
    """Validate ``payload`` against the contract; raise ``InvalidInput`` listing every bad field.

    Numbers must be finite, levels known and unique per view, directors orthonormal and
    right-handed within 1e-3, ``px`` units need ``pixel_spacing``, and each view needs at least
    ``minimum_levels`` landmarked levels, any levels (``MIN_LEVELS_*``); ``options.profile`` must name a
    shipped profile (``profile_files``). A landmark has exactly
    one of ``point`` / ``corners`` (the error names the field: ``point`` when neither is given,
    ``corners`` when both are); corners need an upright view (rows H or F), pedicles the PA view
    with columns L or R. On an upright view the landmarks must run head to feet in level order;
    four corners must form a convex quadrilateral in the contract's order (``_corner_errors``); and
    consecutive landmarked levels must be as far apart as some spine's are (``_distance_errors``;
    for the views named in ``unscaled_views``, whose pixel spacing is a stand-in until the image's
    header is read, only the scale-free part); and a lateral view's thoracic and lumbar profiles must not
    both read inverted under its orientation (``_profile_errors``: a mirrored film; not judged on a view in
    ``unscaled_views``, whose stand-in spacing may not have the image's aspect).
    """
    if not isinstance(payload, dict):
        raise InvalidInput([FieldError((), "the payload must be a JSON object", "type_error")])
    try:
        model = JobPayload.model_validate(payload)
    except ValidationError as exc:
        raise InvalidInput(
            [
                FieldError(_clean_loc(tuple(e["loc"]), e["type"]), _message(e), e["type"])
                for e in exc.errors(include_url=False)
            ]
        ) from None
    exact = model.boundary is not None and not (model.boundary.T1.soft or model.boundary.L5.soft)
    errors = [] if is_profile(model.options.profile) else UnknownProfile(model.options.profile, list_profiles()).errors
    errors += _view_errors("pa", model.pa, exact) + _landmark_form_errors("pa", model.pa, payload.get("pa"))
    errors += _plane_errors("pa", model.pa)
    errors += _geometry_errors("pa", model.pa, "pa" not in unscaled_views)
    errors += _order_errors("pa", model.pa, payload.get("pa"), "pa" not in unscaled_views)
    errors += _corner_errors("pa", payload.get("pa")) + _pedicle_errors("pa", payload.get("pa"))
    if model.lateral is not None:
        errors += _view_errors("lateral", model.lateral, exact) + _plane_errors("lateral", model.lateral)
        errors += _geometry_errors("lateral", model.lateral, "lateral" not in unscaled_views)
        errors += _landmark_form_errors("lateral", model.lateral, payload.get("lateral"))
        errors += _order_errors("lateral", model.lateral, payload.get("lateral"), "lateral" not in unscaled_views)
        errors += _corner_errors("lateral", payload.get("lateral"))
    if not errors:  # distances need the spacing and well-formed landmarks
        for name, view in (("pa", model.pa), ("lateral", model.lateral)):
            if view is not None:
                errors += _across_errors(name, view)
                errors += _distance_errors(name, view, payload.get(name), name not in unscaled_views)
    if not errors and model.lateral is not None and "lateral" not in unscaled_views:
        errors += _profile_errors("lateral", model.lateral)
    if errors:
        raise InvalidInput(errors)
    return model
