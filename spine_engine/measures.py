"""Clinical measures of a spine from its vertebra positions and directors (``docs/measures.md``).

Inputs: positions (17,3) mm and rotations (17,3,3) with the directors as columns [d1 d2 d3], in
DICOM LPS (+x patient left, +y posterior, +z superior), levels T1..L5 in order.
Every angle here is in degrees.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Literal, cast

import numpy as np
import numpy.typing as npt

from .frames import axial_rotation_deg, centreline_tangents
from .levels import LEVEL_INDEX, LEVELS, N_LEVELS, Level
from .models import AasceMajorAngle, CobbCurve, LargestCobbAngle, LenkeCurve, LenkeInputs, Measures

FloatArray = npt.NDArray[np.float64]

TILT_HYSTERESIS_DEG = 5.0
"""A reversal of the tilt sequence smaller than this does not end a curve. Chosen at the size of
the intra-observer error of manual Cobb measurement, about ±5° (Morrissy et al., J Bone Joint
Surg Am 1990;72:320–327, report a 95 % confidence interval of roughly this size; value rounded)."""


def frontal_tilt_deg(rotations: npt.ArrayLike) -> FloatArray:
    """Frontal tilt θ_i = atan2(d1_z, d1_x) of each vertebra: the angle of d1 projected on the
    frontal (x, z) plane from patient left, positive when d1 rises toward the left (17,), degrees.

    An endplate's tilt is that of a line, so θ is taken in [−90°, 90°) (θ − 180° when d1 points to
    the patient's right, a vertebra turned 90° or more about its axis): a Cobb angle, a difference
    of two tilts, is then below 180°, as between any two lines of the film."""
    R = np.asarray(rotations, dtype=float)
    d1 = R[..., :, 0]
    theta = np.degrees(np.arctan2(d1[..., 2], d1[..., 0]))
    return np.asarray((theta + 90.0) % 180.0 - 90.0)


def sagittal_inclination_deg(rotations: npt.ArrayLike) -> FloatArray:
    """Sagittal inclination β_i = atan2(d3_y, −d3_z) of the caudal tangent d3 projected on the
    sagittal (y, z) plane, from the caudal vertical, positive when the spine runs posteriorly
    going down (17,)."""
    return _inclination_deg(np.asarray(rotations, dtype=float)[..., :, 2])


def _inclination_deg(caudal: FloatArray) -> FloatArray:
    """β = atan2(t_y, −t_z) of caudal directions t (..., 3), degrees."""
    return np.degrees(np.arctan2(caudal[..., 1], -caudal[..., 2]))


def kyphosis_lordosis_deg(rotations: npt.ArrayLike) -> tuple[float, float, float]:
    """(kyphosis T4–T12, kyphosis T5–T12, lordosis L1–L5), degrees.

    Kyphosis = β_T4 − β_T12 (resp. β_T5 − β_T12), positive when convex posteriorly;
    lordosis = β_L5 − β_L1, positive when convex anteriorly (β: ``sagittal_inclination_deg``).
    """
    return _kyphosis_lordosis(sagittal_inclination_deg(rotations))


def sagittal_inclinations(
    positions: npt.ArrayLike, rotations: npt.ArrayLike, observed: npt.ArrayLike | None = None
) -> FloatArray:
    """β (17,) the sagittal measures read: the director's (``sagittal_inclination_deg``) where
    ``observed`` (17,) bool, the vertebrae whose sagittal tilt a lateral view's corners observed or
    the boundary gave, and elsewhere the tangent's, of the frames ``frames_from_centreline`` builds
    on the positions.

    Without lateral corners no film sees a director's sagittal tilt: its departure from the tangent
    is the rod's shear and bending prior alone, which pulls it toward the rest shape (on synthetic
    spines with lordosis 30–65°, 9–10° of lordosis with both films). The tangent is what the
    landmarks determine, and what the reported SDs are of (``fit.uncertainty``)."""
    beta = _inclination_deg(centreline_tangents(np.asarray(positions, dtype=float)))
    if observed is None:
        return beta
    return np.where(np.asarray(observed, dtype=bool), sagittal_inclination_deg(rotations), beta)


def _kyphosis_lordosis(beta: FloatArray) -> tuple[float, float, float]:
    i = LEVEL_INDEX
    return (
        float(beta[i["T4"]] - beta[i["T12"]]),
        float(beta[i["T5"]] - beta[i["T12"]]),
        float(beta[i["L5"]] - beta[i["L1"]]),
    )


def tilt_turning_points(tilt_deg: npt.ArrayLike, hysteresis_deg: float = TILT_HYSTERESIS_DEG) -> list[int]:
    """Indices of the local extremes of a tilt sequence, with hysteresis ("zig-zag" filter).

    A running extreme becomes a turning point once the sequence has moved back from it by at least
    ``hysteresis_deg``. The first point is the extreme before the first such move; the last is the
    extreme of the final run. Returns [] when the whole range is below the hysteresis.
    """
    t = np.asarray(tilt_deg, dtype=float)
    h = float(hysteresis_deg)
    lo = hi = 0
    trend = 0
    points: list[int] = []
    ext = 0
    for i in range(1, len(t)):
        if trend == 0:
            if t[i] > t[hi]:
                hi = i
            if t[i] < t[lo]:
                lo = i
            if t[hi] - t[lo] >= max(h, 1e-12):
                up = lo < hi
                points.append(lo if up else hi)
                trend, ext = (1, hi) if up else (-1, lo)
        elif trend == 1:
            if t[i] >= t[ext]:
                ext = i
            elif t[ext] - t[i] >= h:
                points.append(ext)
                trend, ext = -1, i
        else:
            if t[i] <= t[ext]:
                ext = i
            elif t[i] - t[ext] >= h:
                points.append(ext)
                trend, ext = 1, i
    if trend != 0:
        points.append(ext)
    return points


@dataclass(frozen=True)
class FrontalCurve:
    """A frontal curve between two end vertebrae (indices into T1..L5)."""

    upper: int
    lower: int
    apex: int
    angle_deg: float
    convexity: Literal["left", "right"]
    apical_disc: bool = False
    """The apex is the disc between ``apex`` and ``apex + 1`` (a curve of one segment, ``_apex``)."""


def _apex(
    positions: FloatArray, upper: int, lower: int, tilt: FloatArray
) -> tuple[int, Literal["left", "right"], bool]:
    """The curve's apex, its side and whether it is a disc: (apex, convexity, apical_disc).

    SRS: the apex of a curve is its most laterally deviated vertebra (apical vertebra) or disc (apical
    disc) (Scoliosis Research Society, Revised Glossary of Terms, "apical vertebra", "apical disc";
    Stokes, Spine 1994;19:236–248). SRS measures the deviation from the vertical axis through the
    sacrum, which the model (T1–L5) does not have; here it is taken from the chord of the end
    vertebrae's centres in the frontal (x, z) plane: signed distance δ_i = (p_i − p_U)·n with
    n = (−c_z, c_x) the normal of the unit chord c = (p_L − p_U)/|…| that points toward +x for a chord
    running caudally (δ > 0: patient left). The convexity is the tilts', which define the curve (its ends
    and its angle): right when the tilt rises caudally (θ_L > θ_U), left when it falls (``docs/measures.md``;
    from δ only for a curve of 0°). The apex is the vertebra strictly between the ends deviated most toward
    the convexity (largest δ for a left curve, largest −δ for a right one): where the positions and the
    tilts come from different sources (corners, the fitted centreline), a short curve of 10–15°, a few mm
    off its chord, cannot then be read as convex to the side its tilts deny (with 1 mm of noise on the
    positions of 60 synthetic spines, 1 curve in 142 was, before). If no vertebra lies on the convex side
    of the chord, the apex is the middle vertebra. When two neighbouring vertebrae share the largest
    deviation (equal to 1e-9 mm), the apex lies between them: the disc between them, which lies on the
    curved spine between them and so is deviated more than either, is the apical disc (SRS: the disc
    most deviated); a run of more than two equally deviated vertebrae has its apex at the run's middle,
    a vertebra or a disc. A disc is named by its upper vertebra with ``apical_disc`` True (the
    contract's apex is a vertebra). A curve of one segment (lower = upper + 1) has no vertebra between
    its end vertebrae, both on the chord: its apex is the disc between them.
    """
    xz = positions[:, [0, 2]]
    chord = xz[lower] - xz[upper]
    length = math.sqrt(float(chord @ chord))  # |chord|, as np.linalg.norm computes it
    inner = np.arange(upper + 1, lower)
    # The curve is its tilts' (its ends and angle are): the tilt rising caudally means convex right.
    by_tilt: Literal["left", "right", ""] = (
        "right" if tilt[lower] > tilt[upper] else "left" if tilt[lower] < tilt[upper] else ""
    )
    if length > 0 and len(inner):
        c = chord / length
        n = np.array([-c[1], c[0]])
        if n[0] < 0:
            n = -n
        dist = (xz[inner] - xz[upper]) @ n
        side_sign = {"left": 1.0, "right": -1.0}  # a curve of 0° (no side by tilt): its most deviated one's
        toward = side_sign[by_tilt] if by_tilt else float(np.sign(dist[np.argmax(np.abs(dist))]) or 1.0)
        deviation = toward * dist  # deviation toward the convexity, mm
        k = int(np.argmax(deviation))
        if deviation[k] > 1e-9:
            side: Literal["left", "right"] = "left" if toward > 0 else "right"
            tied = np.flatnonzero(deviation[k] - deviation <= 1e-9)
            if len(tied) > 1 and tied[-1] - tied[0] == len(tied) - 1:  # a run of equally deviated vertebrae
                middle = int(tied[0] + tied[-1])  # twice the run's middle, in steps of half a level
                return int(inner[middle // 2]), side, middle % 2 == 1
            return int(inner[k]), side, False
    convexity: Literal["left", "right"] = by_tilt or "left"
    if not len(inner):
        return upper, convexity, True
    return int(inner[len(inner) // 2]), convexity, False


def frontal_curves(
    positions: npt.ArrayLike,
    rotations: npt.ArrayLike,
    min_cobb_deg: float = 10.0,
    hysteresis_deg: float = TILT_HYSTERESIS_DEG,
) -> list[FrontalCurve]:
    """Frontal Cobb curves, top to bottom: consecutive turning points of the frontal tilt sequence
    are the end vertebrae; Cobb = |θ_upper − θ_lower|; curves below ``min_cobb_deg`` are dropped."""
    p = np.asarray(positions, dtype=float)
    tilt = frontal_tilt_deg(rotations)
    turning = tilt_turning_points(tilt, hysteresis_deg)
    curves = []
    for upper, lower in itertools.pairwise(turning):
        angle = float(abs(tilt[upper] - tilt[lower]))
        if angle < min_cobb_deg:
            continue
        apex, convexity, disc = _apex(p, upper, lower, tilt)
        curves.append(FrontalCurve(upper, lower, apex, angle, convexity, disc))
    return curves


def most_tilted_pair(tilt_deg: npt.ArrayLike) -> tuple[int, int, float] | None:
    """(upper, lower, angle): the two vertebrae most tilted relative to each other, the pair i < j
    with the largest |θ_i − θ_j| (first pair in row-major order on a tie, as the AASCE 2019
    script's argmax), and that angle, max θ − min θ (degrees). A flat sequence (all tilts equal) has
    its largest angle, 0°, between its first and last vertebrae. None for fewer than two tilts."""
    t = np.asarray(tilt_deg, dtype=float)
    n = len(t)
    if n < 2:
        return None
    diff = np.abs(t[:, None] - t[None, :])
    if float(diff.max()) <= 0.0:
        return 0, n - 1, 0.0
    upper, lower = sorted(divmod(int(np.argmax(diff)), n))
    return upper, lower, float(diff[upper, lower])


CURVE_REVERSAL_DEG = 10.0
"""A reversal of the frontal tilt of this much or more between two vertebrae of a curve is a curve of
the other convexity, which splits it (``major_first_curves``, 3): the Scoliosis Research Society calls
a lateral curvature of 10° Cobb or more scoliosis (SRS Revised Glossary of Terms, "scoliosis"). It does
not depend on the reporting threshold ``min_cobb_deg``, so the curves and the major angle do not
either (a split piece below that threshold is not reported but still separates its neighbours)."""


def major_first_curves(
    tilt_deg: npt.ArrayLike, min_cobb_deg: float = 10.0, reversal_deg: float = CURVE_REVERSAL_DEG
) -> list[tuple[int, int, float]]:
    """Frontal curves (upper, lower, Cobb angle in degrees) of a tilt sequence, top to bottom.

    1. The **major curve** ends at the two most tilted vertebrae relative to each other: the pair
       i < j with the largest |θ_i − θ_j| (first pair in row-major order on a tie, as the AASCE
       2019 script's argmax). Its Cobb angle is max θ − min θ.
    2. Going up from its upper end U, the next curve ends at the vertebra above U most tilted
       relative to U (the nearest on a tie), and so on to T1; going down from its lower end
       likewise to L5. Each such curve is no larger than the one it joins, and the curves
       alternate in direction.
    3. **A curve turns one way only**: a curve of 1–2 whose tilt turns back, between two of its
       vertebrae, by ``reversal_deg`` (``CURVE_REVERSAL_DEG``, 10°) or more holds a curve of the
       other convexity that is itself scoliotic (Cobb 1948: a curve's end vertebrae are its most
       tilted ones, where the tilt turns back; SRS: a lateral curvature of 10° or more). It is split
       there (``_split_reversals``): its largest reversal, from the vertebra a to the vertebra b
       (a < b), becomes a curve a–b of its own and the pieces on either side end at a and at b;
       each piece is split again the same way. A smaller reversal (a wiggle) never splits a curve.
       The major curve is then the largest of the curves, no longer always the most tilted pair
       (``most_tilted_pair``, which the AASCE 2019 script reads).
    4. Curves below ``min_cobb_deg`` are dropped (they still separate their neighbours).
    A flat sequence (all tilts equal) has no curve.
    """
    t = np.asarray(tilt_deg, dtype=float)
    n = len(t)
    largest = most_tilted_pair(t)
    if largest is None or largest[2] <= 0.0:
        return []
    upper, lower, _ = largest
    ends = [upper, lower]
    end = upper
    while end > 0:
        above = np.abs(t[:end] - t[end])
        end = end - 1 - int(np.argmax(above[::-1]))
        ends.insert(0, end)
    end = lower
    while end < n - 1:
        below = np.abs(t[end + 1 :] - t[end])
        end = end + 1 + int(np.argmax(below))
        ends.append(end)
    split = [e for u, l in itertools.pairwise(ends) for e in _split_reversals(t, u, l, reversal_deg)[:-1]]
    curves = [(u, l, float(abs(t[l] - t[u]))) for u, l in itertools.pairwise([*split, ends[-1]])]
    return [c for c in curves if c[2] >= min_cobb_deg]


def _split_reversals(t: FloatArray, upper: int, lower: int, min_reversal_deg: float) -> list[int]:
    """End vertebrae [upper, …, lower] of the curve upper–lower once split at every reversal of its tilt
    of ``min_reversal_deg`` or more (``major_first_curves``, 3), degrees.

    The curve's ends are the extremes of its tilts (``major_first_curves`` picks them so); its direction
    is s = sign(θ_lower − θ_upper). Its largest reversal is the pair a < b inside it with the largest
    s·(θ_a − θ_b) > 0: b the first vertebra farthest below the running extreme max_{i ≤ b} s·θ_i, a
    the first vertebra at that extreme. When it reaches ``min_reversal_deg`` (and is > 0), a is the
    extreme of upper..b and b that of a..lower, so upper–a, a–b and b–lower are curves with their
    ends at their extremes, split again in turn; else the curve stays whole."""
    s = 1.0 if t[lower] >= t[upper] else -1.0
    run = s * t[upper : lower + 1]
    drop = np.maximum.accumulate(run) - run  # s·(θ_a − θ_b) from the running extreme a above b
    b = int(np.argmax(drop))
    if drop[b] <= 0.0 or drop[b] < min_reversal_deg:
        return [upper, lower]
    a, b = upper + int(np.argmax(run[: b + 1])), upper + b
    return [
        *_split_reversals(t, upper, a, min_reversal_deg)[:-1],
        *_split_reversals(t, a, b, min_reversal_deg)[:-1],
        *_split_reversals(t, b, lower, min_reversal_deg),
    ]


def aasce_major_angle(tilt_deg: npt.ArrayLike) -> tuple[float, int, int]:
    """The major angle of the AASCE 2019 challenge's Cobb script and its vertebrae (upper, lower).

    The script takes each vertebra's vector from the midpoint of its left edge to the midpoint of
    its right edge, the angle A_ij = arccos(clip(cos ∠(v_i, v_j), 0, 1)) between every two, and
    the largest (row of the largest row maximum, then its first column). With the vectors' frontal
    tilts θ, cos ∠(v_i, v_j) = cos(θ_i − θ_j). Degrees; at most 90° (the clip).
    """
    t = np.radians(np.asarray(tilt_deg, dtype=float))
    angles = np.arccos(np.clip(np.cos(t[:, None] - t[None, :]), 0.0, 1.0))
    row = int(np.argmax(angles.max(axis=1)))
    col = int(np.argmax(angles[row]))
    return float(np.degrees(angles[row, col])), min(row, col), max(row, col)


def _plane_tilt_deg(R: FloatArray, phi_deg: npt.ArrayLike) -> FloatArray:
    """Tilt of a vertebra's endplate director in the vertical plane of azimuth φ, degrees, per φ.

    The plane has horizontal direction h = cos φ e_x − sin φ e_y (patient left turned toward
    anterior). The director is the direction of the endplate plane (span of d1, d2) closest to h,
    w = h − (h·d3) d3: for a vertebra without axial rotation it is d1 at φ = 0 (so Cobb(0) is the
    frontal Cobb angle) and close to cos φ d1 + sin φ d2 in general. Its tilt in the plane is
    atan2(w·z, w·h).
    """
    phi = np.radians(np.asarray(phi_deg, dtype=float))
    return _plane_tilt_cs_deg(R, np.cos(phi), np.sin(phi))


def _plane_tilt_cs_deg(R: FloatArray, c: FloatArray, s: FloatArray) -> FloatArray:
    """``_plane_tilt_deg`` from cos φ and sin φ, in closed form: with a = h·d3 = c d3x − s d3y,
    w·z = −a d3z (h has no z) and w·h = |h|² − a² (no 3-vectors per φ: this runs on the grids of
    ``plane_of_max_curvature``)."""
    return _plane_tilts_deg(R[None, :, 2], c, s, c * c + s * s)[0]


def _plane_tilts_deg(d3: FloatArray, c: FloatArray, s: FloatArray, h2: FloatArray) -> FloatArray:
    """``_plane_tilt_cs_deg`` of several vertebrae at once: d3 (k, 3) their caudal directors,
    c, s (m,) cos φ and sin φ of the grid, h2 = c² + s² (m,); returns (k, m) degrees."""
    a = c * d3[:, 0:1] - s * d3[:, 1:2]
    return np.degrees(np.arctan2(-a * d3[:, 2:3], h2 - a * a))


def _plane_cobb_deg(R_upper: FloatArray, R_lower: FloatArray, phi_deg: npt.ArrayLike) -> FloatArray:
    phi = np.radians(np.asarray(phi_deg, dtype=float))
    c, s = np.cos(phi), np.sin(phi)
    return _plane_cobb_cs_deg(np.stack((R_upper[:, 2], R_lower[:, 2])), c, s, c * c + s * s)


def _plane_cobb_cs_deg(d3: FloatArray, c: FloatArray, s: FloatArray, h2: FloatArray) -> FloatArray:
    """Cobb(φ) = |tilt_U(φ) − tilt_L(φ)| wrapped to [0°, 180°] on a grid given by c = cos φ,
    s = sin φ and h2 = c² + s² (m,); d3 (2, 3): the caudal directors of the upper and lower end."""
    tilt = _plane_tilts_deg(d3, c, s, h2)
    return np.abs((tilt[0] - tilt[1] + 180.0) % 360.0 - 180.0)


def _trig_grid(grid: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """cos φ, sin φ and cos² φ + sin² φ of a grid of φ in degrees."""
    phi = np.radians(grid)
    c, s = np.cos(phi), np.sin(phi)
    return c, s, c * c + s * s


_MAX_CURVATURE_OFFSETS = tuple(
    np.arange(-step, step + fine / 2, fine) for step, fine in ((90.0, 1.0), (1.0, 1e-2), (1e-2, 1e-4))
)
"""Offsets (degrees) of the three grids of ``plane_of_max_curvature`` around the best point so far:
±90° by 1°, ±1° by 0.01°, ±0.01° by 1e-4°."""
_MAX_CURVATURE_FIRST_TRIG = _trig_grid(90.0 + _MAX_CURVATURE_OFFSETS[0])
"""``_trig_grid`` of the first grid (0°–180°, around 90°), the same for every curve."""
for _array in (*_MAX_CURVATURE_OFFSETS, *_MAX_CURVATURE_FIRST_TRIG):
    _array.setflags(write=False)


def plane_of_max_curvature(R_upper: npt.ArrayLike, R_lower: npt.ArrayLike) -> tuple[float, float]:
    """(φ*, Cobb(φ*)), degrees: the azimuth φ* ∈ [0°, 180°) of the vertical plane in which the Cobb
    angle between the two end vertebrae is largest, and that angle.

    Cobb(φ) = |tilt_U(φ) − tilt_L(φ)| with the endplate tilts of ``_plane_tilt_deg``; φ = 0° is the
    frontal plane (Cobb(0) is the frontal Cobb angle when the end vertebrae have no axial
    rotation), φ = 90° the sagittal plane. It turns with the spine: rotating the whole spine by −α
    about +z moves φ* by +α. A 1° grid, then two finer grids around the best point (0.01°, then
    1e-4°), all vectorised (both end vertebrae at once; the first grid's trigonometry precomputed).
    """
    d3 = np.stack((np.asarray(R_upper, dtype=float)[:, 2], np.asarray(R_lower, dtype=float)[:, 2]))
    best = 90.0
    for level, offsets in enumerate(_MAX_CURVATURE_OFFSETS):
        grid = best + offsets
        c, s, h2 = _MAX_CURVATURE_FIRST_TRIG if level == 0 else _trig_grid(grid)
        values = _plane_cobb_cs_deg(d3, c, s, h2)
        k = int(np.argmax(values))
        best, value = float(grid[k]), float(values[k])
    phi = best % 180.0
    if phi > 180.0 - 1e-3:
        phi = 0.0
    return phi, value


LENKE_REGIONS: dict[str, tuple[str, str]] = {
    "proximal_thoracic": ("T2", "T5"),
    "main_thoracic": ("T6", "T11"),
    "thoracolumbar_lumbar": ("T12", "L4"),
}
"""Apex levels of each Lenke region (Lenke et al., J Bone Joint Surg Am 2001;83:1169–1181:
proximal thoracic apex T3–T5, main thoracic T6 to the T11–T12 disc, thoracolumbar T12–L1,
lumbar L1–L2 disc to L4; apexes here are vertebrae, so T2 joins the proximal region and T12
starts the thoracolumbar/lumbar one)."""
LENKE_STRUCTURAL_COBB_DEG = 25.0
"""Lenke 2001: a minor curve is structural when its side-bending Cobb angle is ≥ 25°."""
LENKE_STRUCTURAL_KYPHOSIS_DEG = 20.0
"""Lenke 2001: ... or when its regional kyphosis (T2–T5, or T10–L2) is ≥ +20°."""
LENKE_MODIFIER_DEG = (10.0, 40.0)
"""Lenke 2001 sagittal thoracic modifier on T5–T12 kyphosis: '-' below 10°, 'N' 10–40°, '+' above."""


def lenke_modifier(t5_t12_kyphosis_deg: float) -> Literal["-", "N", "+"]:
    """Lenke's sagittal thoracic modifier of a T5–T12 kyphosis (``LENKE_MODIFIER_DEG``)."""
    lo, hi = LENKE_MODIFIER_DEG
    return "-" if t5_t12_kyphosis_deg < lo else ("+" if t5_t12_kyphosis_deg > hi else "N")


def _normal_below(x: float, mean: float, sd: float) -> float:
    """P(X < x) for X ~ N(mean, sd²): ½(1 + erf((x − mean) / (sd √2)))."""
    return 0.5 * (1.0 + math.erf((x - mean) / (sd * math.sqrt(2.0))))


def lenke_with_kyphoses(lenke: LenkeInputs, t2_t5: float, t5_t12: float, t10_l2: float) -> LenkeInputs:
    """``lenke`` with its regional kyphoses (degrees) replaced, and what they decide (each curve's
    ``structural_by_kyphosis``, the sagittal modifier) decided again."""
    curves = [
        c.model_copy(update={"structural_by_kyphosis": (t2_t5 if c.region == "proximal_thoracic" else t10_l2)
                             >= LENKE_STRUCTURAL_KYPHOSIS_DEG})
        for c in lenke.curves
    ]
    return lenke.model_copy(update={
        "curves": curves, "t2_t5_kyphosis_deg": t2_t5, "t5_t12_kyphosis_deg": t5_t12, "t10_l2_kyphosis_deg": t10_l2,
        "sagittal_thoracic_modifier": lenke_modifier(t5_t12),
    })


def lenke_probabilities(lenke: LenkeInputs) -> LenkeInputs:
    """``lenke`` with the probabilities of its sagittal criteria under N(k, SD²) of the kyphosis k each
    is read from: a curve's regional kyphosis ≥ 20° (P(k ≥ 20°), whatever ``structural_by_kyphosis``
    decided) and the sagittal modifier given (P(k < 10°), P(10° ≤ k ≤ 40°) or P(k > 40°)); None where
    that SD is None."""
    def structural(value: float, sd: float | None) -> float | None:
        if sd is None or not sd > 0.0:
            return None
        return 1.0 - _normal_below(LENKE_STRUCTURAL_KYPHOSIS_DEG, value, sd)

    curves = [
        c.model_copy(update={"structural_by_kyphosis_probability": structural(
            *((lenke.t2_t5_kyphosis_deg, lenke.t2_t5_kyphosis_sd_deg) if c.region == "proximal_thoracic"
              else (lenke.t10_l2_kyphosis_deg, lenke.t10_l2_kyphosis_sd_deg)))})
        for c in lenke.curves
    ]
    modifier = None
    sd = lenke.t5_t12_kyphosis_sd_deg
    if sd is not None and sd > 0.0:
        lo, hi = (_normal_below(b, lenke.t5_t12_kyphosis_deg, sd) for b in LENKE_MODIFIER_DEG)
        modifier = {"-": lo, "N": hi - lo, "+": 1.0 - hi}[lenke.sagittal_thoracic_modifier]
    return lenke.model_copy(update={"curves": curves, "sagittal_thoracic_modifier_probability": modifier})


def lenke_inputs(cobb: list[CobbCurve], beta: FloatArray) -> LenkeInputs:
    """The Lenke classification inputs a reconstruction supports (model estimates); ``beta``: the
    sagittal inclinations (``sagittal_inclinations``)."""
    t2_t5, t5_t12, t10_l2 = (
        float(beta[LEVEL_INDEX[upper]] - beta[LEVEL_INDEX[lower]])  # regional kyphosis (+: convex posteriorly)
        for upper, lower in (("T2", "T5"), ("T5", "T12"), ("T10", "L2"))
    )
    curves = []
    for region, (first, last) in LENKE_REGIONS.items():
        inside = [c for c in cobb if LEVEL_INDEX[first] <= LEVEL_INDEX[c.apex] <= LEVEL_INDEX[last]]
        if not inside:
            continue
        c = max(inside, key=lambda c: c.angle_deg)
        kyphosis = t2_t5 if region == "proximal_thoracic" else t10_l2
        curves.append(
            LenkeCurve(
                region=region,
                upper=c.upper,
                lower=c.lower,
                apex=c.apex,
                angle_deg=c.angle_deg,
                major=c.major,
                structural_by_magnitude=c.major or c.angle_deg >= LENKE_STRUCTURAL_COBB_DEG,
                structural_by_kyphosis=kyphosis >= LENKE_STRUCTURAL_KYPHOSIS_DEG,
            )
        )
    return LenkeInputs(
        curves=curves,
        t2_t5_kyphosis_deg=t2_t5,
        t5_t12_kyphosis_deg=t5_t12,
        t10_l2_kyphosis_deg=t10_l2,
        sagittal_thoracic_modifier=lenke_modifier(t5_t12),
        not_supported=["side_bending_cobb", "lumbar_modifier_csvl"],
    )


def frontal_tilts(
    rotations: npt.ArrayLike, observed_tilt_deg: npt.ArrayLike | None = None
) -> tuple[FloatArray, FloatArray]:
    """Tilt of each vertebra for the Cobb measure (17,) and a mask of those observed (17,) bool:
    the observed tilt (from corners) where finite, else the model's ``frontal_tilt_deg``, made
    continuous along the spine (``continuous_tilts``)."""
    model = frontal_tilt_deg(rotations)
    if observed_tilt_deg is None:
        return continuous_tilts(model), np.zeros(len(model), dtype=bool)
    observed = np.asarray(observed_tilt_deg, dtype=float)
    mask = np.isfinite(observed)
    return continuous_tilts(np.where(mask, observed, model)), mask


def continuous_tilts(tilt_deg: npt.ArrayLike) -> FloatArray:
    """Tilts (degrees) of lines, each known up to 180°, made continuous from T1 to L5: each is moved
    by a multiple of 180° to lie within 90° of the one above it (``np.unwrap``, period 180°), then all
    by one multiple of 180° so that their median lies in [−90°, 90°).

    A tilt is that of a line, so ``frontal_tilt_deg`` reads it in [−90°, 90°): a vertebra tilted 100°
    (the lower end of a severe curve, 130° say, whose upper end is tilted −30°, as in a collapsing
    neuromuscular curve) reads −80°, and a Cobb angle across it, a difference of two tilts, would be
    50° instead of 130°. Two neighbouring vertebrae are never 90° apart in the frontal plane (a
    segment turns a few degrees, at most about 20° in a severe curve), so the continuous sequence is
    the spine's. A sequence in [−90°, 90°) whose neighbours are all within 90° is returned unchanged."""
    t = np.asarray(tilt_deg, dtype=float)
    if t.size == 0:
        return t.copy()
    lo, hi = float(t.min()), float(t.max())
    if lo >= -90.0 and hi < 90.0 and hi - lo < 90.0:
        return t.copy()  # every neighbour within 90°: what the lines below return, without their cost
    t = np.unwrap(t, period=180.0)
    return np.asarray(t - 180.0 * np.floor((float(np.median(t)) + 90.0) / 180.0))


TiltSource = Literal["model", "mixed", "corners"]
_TILT_SOURCES: tuple[TiltSource, TiltSource, TiltSource] = ("model", "mixed", "corners")


def _tilt_source(observed: npt.NDArray[np.generic], upper: int, lower: int) -> TiltSource:
    """Where the tilts of two end vertebrae come from: corners for neither ("model"), one ("mixed") or both."""
    return _TILT_SOURCES[int(observed[upper]) + int(observed[lower])]


def compute_measures(
    positions: npt.ArrayLike,
    rotations: npt.ArrayLike,
    min_cobb_deg: float = 10.0,
    *,
    observed_tilt_deg: npt.ArrayLike | None = None,
    observed_endplate_tilt_deg: npt.ArrayLike | None = None,
    observed_sagittal: npt.ArrayLike | None = None,
) -> Measures:
    """Frontal Cobb curves with their 3D descriptors, kyphosis, lordosis and Lenke inputs.

    positions (17,3) mm and rotations (17,3,3) (directors as columns), T1..L5. The curves come
    from the frontal tilts (``major_first_curves``): ``observed_tilt_deg`` (17,), the tilts of the
    corner lines where finite, else the model's d1. Exactly one curve is ``major`` (the largest)
    when any curve reaches ``min_cobb_deg``; ``largest_cobb`` is that major curve, or without one the
    largest angle (``most_tilted_pair``) whatever its size. ``observed_endplate_tilt_deg`` (17, 2): the superior
    and inferior endplate tilts from corners where finite, else the vertebra's tilt (the model has
    one frame per vertebra: both endplates are perpendicular to d3). With observed tilts on all 17
    levels ``aasce2019`` holds the AASCE script's major angle. Kyphosis, lordosis and the Lenke
    kyphosis values read ``sagittal_inclinations``: the centreline's tangent, or the director where
    ``observed_sagittal`` (17,) says a lateral view's corners observed it. Definitions:
    ``docs/measures.md``.
    """
    p = np.asarray(positions, dtype=float)
    R = np.asarray(rotations, dtype=float)
    if p.shape != (N_LEVELS, 3) or R.shape != (N_LEVELS, 3, 3):
        raise ValueError(f"expected positions (17,3) and rotations (17,3,3), got {p.shape} and {R.shape}")
    if not (np.isfinite(p).all() and np.isfinite(R).all()):
        raise ValueError("positions and rotations must be finite")
    tilt, observed = frontal_tilts(R, observed_tilt_deg)
    endplates = tilt[:, None].repeat(2, axis=1)  # (17, 2): both endplates at the vertebra's tilt
    if observed_endplate_tilt_deg is not None:
        given = np.asarray(observed_endplate_tilt_deg, dtype=float).reshape(N_LEVELS, 2)
        endplates = np.where(np.isfinite(given), given, endplates)
    found = major_first_curves(tilt, min_cobb_deg)
    major = int(np.argmax([angle for _, _, angle in found])) if found else -1
    psi = axial_rotation_deg(R)
    cobb = []
    for k, (upper, lower, angle) in enumerate(found):
        apex, convexity, disc = _apex(p, upper, lower, tilt)
        phi, max_angle = plane_of_max_curvature(R[upper], R[lower])
        cobb.append(
            CobbCurve(
                upper=cast(Level, LEVELS[upper]),
                lower=cast(Level, LEVELS[lower]),
                apex=cast(Level, LEVELS[apex]),
                angle_deg=angle,
                major=k == major,
                convexity=convexity,
                apical_disc=disc,
                apex_axial_rotation_deg=float(psi[apex]),
                plane_of_max_curvature_deg=phi,
                max_curvature_deg=max_angle,
                endplate_angle_deg=float(abs(endplates[upper, 0] - endplates[lower, 1])),
                tilt_source=_tilt_source(observed, upper, lower),
            )
        )
    largest = None
    # the major curve when one is reported (the most tilted pair, unless a reversal of the threshold
    # or more inside it split it: ``major_first_curves``, 3); else the most tilted pair, below it
    pair = found[major] if found else most_tilted_pair(tilt)
    if pair is not None:
        largest = LargestCobbAngle(
            upper=cast(Level, LEVELS[pair[0]]),
            lower=cast(Level, LEVELS[pair[1]]),
            angle_deg=pair[2],
            tilt_source=_tilt_source(observed, pair[0], pair[1]),
            reported_as_curve=bool(found),
        )
    aasce = None
    if observed.all():
        angle, upper, lower = aasce_major_angle(tilt)
        aasce = AasceMajorAngle(angle_deg=angle, upper=cast(Level, LEVELS[upper]), lower=cast(Level, LEVELS[lower]))
    beta = sagittal_inclinations(p, R, observed_sagittal)
    k4, k5, lordosis = _kyphosis_lordosis(beta)
    return Measures(
        cobb=cobb,
        largest_cobb=largest,
        thoracic_kyphosis_t4_t12_deg=k4,
        thoracic_kyphosis_t5_t12_deg=k5,
        lumbar_lordosis_l1_l5_deg=lordosis,
        aasce2019=aasce,
        lenke=lenke_inputs(cobb, beta),
    )
