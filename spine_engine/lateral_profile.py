"""A lateral film whose sagittal profile reads inverted in both regions: its orientation is mirrored.

A lateral radiograph shows the spine's depth (y) against its height (z). Its ``patient_orientation``
names which image direction runs toward the patient's anterior (DICOM PS3.3 C.7.6.1.1.1, Patient
Orientation (0020,0020)). A film displayed mirrored, or sent as ["A", "F"] when the patient's anterior
lies toward the other side of the image, turns every depth into its negative: the engine then reads a
kyphotic thoracic spine as lordotic and a lordotic lumbar spine as kyphotic, both films still agree on
every height (the PA sees no depth), and the fit has nothing to object to. Only what is known of people
tells the two readings apart.

What is known of people (angles between endplates on standing lateral radiographs, Cobb's method):

- normal spines: a wide range of kyphosis T3–T12, a straight thoracolumbar junction, and a lordosis
  that usually starts at L1–L2 and grows at each level caudally (Bernhardt & Bridwell, "Segmental
  analysis of the sagittal plane alignment of the normal thoracic and lumbar spines and thoracolumbar
  junction", Spine 1989;14(7):717–721: lateral radiographs of 102 clinically and radiographically normal
  subjects, Cobb angles T3–T12, T10–T12, T12–L2 and L1–L5 and each segment T1–T2 to L5–S1);
- adolescent idiopathic scoliosis flattens the thoracic kyphosis, not the lumbar lordosis: on standing
  biplanar (EOS) radiographs of 458 AIS patients and 69 controls, kyphosis T4–T12 27.1 ± 18.8° against
  37.7 ± 15.1° and lordosis L1–L5 46.4 ± 13.2° against 46.0 ± 9.1° (mean ± SD; Scoliosis Spinal Disord
  2018;13, doi:10.1186/s13013-018-0156-0, Table 2). A lordotic thoracic spine (T4–T12 < 0) is 1.4 SD
  below the AIS mean: hypokyphosis reaches it. A kyphotic lumbar spine (L1–L5 < 0) is 3.5 SD below the
  AIS mean and 5 SD below the controls'; the two together lie further out still.

So the rule reads the two regions' signs, not their sizes: a sign is the same in the engine's measures
(tangents of the centreline, docs/measures.md) and in the cited endplate angles, whose magnitudes differ
(VerSe dev reads L1–L5 23.1 ± 9.3° on the centreline). A lateral film is refused when, under its stated
orientation, its T4–T12 profile is lordotic AND its T12–L5 profile kyphotic, each by more than
``PROFILE_NOISE_SDS`` SDs of what its landmark noise allows: the mirrored reading is then kyphotic and
lordotic, the signs of every population cited. A single inverted region (thoracic lordosis in AIS, a flat
or kyphotic lumbar spine in the elderly) is never refused.

The check runs on the landmarks alone, before the fit, in pure Python (no numpy: the validation stays
light, as ``validation`` is).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from .errors import FieldError
from .levels import LEVEL_INDEX, LEVELS
from .models import PATIENT_AXES

THORACIC_WINDOW = ("T4", "T12")
"""Levels whose landmarks read the thoracic profile (the engine's kyphosis T4–T12)."""
LUMBAR_WINDOW = ("T12", "L5")
"""Levels whose landmarks read the lumbar profile: L1–L5 and T12 above it, so that the tangent at L1 has
a landmark on either side."""
THORACIC_REACH = ("T6", "T11")
"""The thoracic window is read only when its landmarks reach at least from this high to this low (the
film may hide T4 and T5 behind the shoulders): a shorter run reads a part of the curve only (a lordotic
T9–T12 segment is common in AIS: T9–T12 0.9 ± 10° in 115 patients' Lenke 3 curves against 7.9 ± 5° in
116 healthy adolescents, "Thoracic sagittal plane variations between patients with thoracic adolescent
idiopathic scoliosis and healthy adolescents", PubMed 26821145, standing lateral radiographs), and no judgement
is made."""
LUMBAR_REACH = ("L1", "L5")
"""The lumbar window is read only when its landmarks reach from L1 (or T12) down to L5: lordosis grows
caudally (Bernhardt & Bridwell 1989) and is largest at L4–L5, so a run ending at L4 may read flat."""
MIN_POINTS = 4
"""Fewest landmarks a window needs: three fix the quadratic, a fourth leaves its residual something to
average."""
PROFILE_NOISE_SDS = 3.0
"""Landmark noise allowed for, in SDs of each region's angle (as ``validation.NOISE_SDS``)."""
CHECK_NAME = "lateral_profile_inverted"
"""The reason code of the refusal (``FieldError.type``)."""


@dataclass(frozen=True)
class RegionReading:
    """One region's sagittal angle read from a lateral film's landmarks.

    ``angle_deg`` = β_upper − β_lower, β = −atan(dy/dz) the inclination of the caudal tangent from the
    caudal vertical (positive when the spine runs posteriorly going down, as
    ``measures.sagittal_inclination_deg``): positive when the region is convex posteriorly (kyphotic),
    the engine's kyphosis T4–T12; the lordosis L1–L5 is its negative. ``sd_deg`` is its SD from the
    landmarks' noise; ``upper`` and ``lower`` the levels it runs between."""

    angle_deg: float
    sd_deg: float
    upper: str
    lower: str


def _solve3(a: list[list[float]], b: list[float]) -> list[float] | None:
    """x with a·x = b for a 3 × 3 matrix (Gaussian elimination with partial pivoting), None if singular."""
    m = [[*row, rhs] for row, rhs in zip(a, b, strict=True)]
    for col in range(3):
        pivot = max(range(col, 3), key=lambda r: abs(m[r][col]))
        if abs(m[pivot][col]) < 1e-12:
            return None
        m[col], m[pivot] = m[pivot], m[col]
        for r in range(col + 1, 3):
            f = m[r][col] / m[col][col]
            m[r] = [x - f * y for x, y in zip(m[r], m[col], strict=True)]
    x = [0.0, 0.0, 0.0]
    for r in (2, 1, 0):
        x[r] = (m[r][3] - sum(m[r][k] * x[k] for k in range(r + 1, 3))) / m[r][r]
    return x


def region_reading(
    points: Sequence[tuple[int, float, float]], window: tuple[str, str], reach: tuple[str, str], sd_mm: float
) -> RegionReading | None:
    """The sagittal angle of the landmarks ``points`` (level index, depth y, height z; film mm along the
    patient's +y and +z) within ``window``, or None when they do not reach ``reach`` or number fewer than
    ``MIN_POINTS``.

    Least squares y(z) = a + b t + c t², t = (z − z̄)/100 mm, through the window's landmarks; the slope
    y'(z) = (b + 2 c t)/100 at the window's highest (t_u) and lowest (t_l) landmarks gives
        angle = β_u − β_l = atan y'(t_l) − atan y'(t_u),
    and its SD from the noise: g = ∂angle/∂(a, b, c) = (0, w_l − w_u, 2 (t_l w_l − t_u w_u))/100 with
    w = 1/(1 + y'²), Var = σ_y² gᵀ (XᵀX)⁻¹ g (radians), σ_y = σ √(1 + max y'²) the landmark SD σ with a
    height error's share δz·y' added. A quadratic smooths the profile: on VerSe dev's noise-free lateral
    films it reads kyphosis 12° below to 7° above the centreline's T4–T12 and lordosis 0.6–1.8 times its
    L1–L5, every reading of the sign of the measure (``spine bench lateral-mirror``, ``population``); only
    the sign is judged.
    """
    lo, hi = LEVEL_INDEX[window[0]], LEVEL_INDEX[window[1]]
    inside = sorted((p for p in points if lo <= p[0] <= hi), key=lambda p: p[0])
    if len(inside) < MIN_POINTS or inside[0][0] > LEVEL_INDEX[reach[0]] or inside[-1][0] < LEVEL_INDEX[reach[1]]:
        return None
    z_mean = sum(p[2] for p in inside) / len(inside)
    ts = [(p[2] - z_mean) / 100.0 for p in inside]
    ys = [p[1] for p in inside]
    t2s = [t * t for t in ts]
    power = [float(len(ts)), sum(ts), sum(t2s), sum(t * t2 for t, t2 in zip(ts, t2s, strict=True)),
             sum(t2 * t2 for t2 in t2s)]  # Σ tᵏ, k = 0…4  # fmt: skip
    xtx = [[power[i + j] for j in range(3)] for i in range(3)]
    rhs = [sum(ys), sum(y * t for t, y in zip(ts, ys, strict=True)), sum(y * t2 for t2, y in zip(t2s, ys, strict=True))]
    coef = _solve3(xtx, rhs)
    if coef is None:
        return None
    _, b, c = coef

    def slope(t: float) -> float:
        return (b + 2.0 * c * t) / 100.0

    t_u, t_l = ts[0], ts[-1]
    s_u, s_l = slope(t_u), slope(t_l)
    angle = math.atan(s_l) - math.atan(s_u)
    w_u, w_l = 1.0 / (1.0 + s_u * s_u), 1.0 / (1.0 + s_l * s_l)
    g = [0.0, (w_l - w_u) / 100.0, 2.0 * (t_l * w_l - t_u * w_u) / 100.0]
    x = _solve3(xtx, g)  # (XᵀX)⁻¹ g
    if x is None:
        return None
    variance = sum(gi * xi for gi, xi in zip(g, x, strict=True))
    sigma_y = sd_mm * math.sqrt(1.0 + max(slope(t) ** 2 for t in ts))
    return RegionReading(
        math.degrees(angle),
        math.degrees(sigma_y * math.sqrt(max(variance, 0.0))),
        LEVELS[inside[0][0]],
        LEVELS[inside[-1][0]],
    )


def sagittal_points(
    orientation: tuple[str, str], landmarks: Sequence[tuple[int, float, float]]
) -> list[tuple[int, float, float]]:
    """(level index, y, z) of lateral landmarks given as (level index, column, row) in film mm: with
    e_c, e_r the patient-space unit vectors ``orientation`` names (``models.PATIENT_AXES``), y = c e_c,y + r e_r,y and
    z = c e_c,z + r e_r,z (a weak perspective's scale and translation, and a turn of the film in its
    plane, change no angle difference)."""
    column, row = orientation
    return [
        (level,
         c * PATIENT_AXES[column][1] + r * PATIENT_AXES[row][1],
         c * PATIENT_AXES[column][2] + r * PATIENT_AXES[row][2])
        for level, c, r in landmarks
    ]  # fmt: skip


def profile_readings(
    orientation: tuple[str, str], landmarks: Sequence[tuple[int, float, float]], sd_mm: float
) -> tuple[RegionReading | None, RegionReading | None]:
    """(thoracic, lumbar) readings of a lateral view under ``orientation`` (``region_reading``)."""
    points = sagittal_points(orientation, landmarks)
    return (
        region_reading(points, THORACIC_WINDOW, THORACIC_REACH, sd_mm),
        region_reading(points, LUMBAR_WINDOW, LUMBAR_REACH, sd_mm),
    )


def is_inverted(thoracic: RegionReading | None, lumbar: RegionReading | None) -> bool:
    """Whether both regions read inverted beyond the noise: kyphosis κ = thoracic.angle_deg and lordosis
    λ = −lumbar.angle_deg with κ + n·SD_κ < 0 and λ + n·SD_λ < 0, n = ``PROFILE_NOISE_SDS``."""
    if thoracic is None or lumbar is None:
        return False
    kyphosis, lordosis = thoracic.angle_deg, -lumbar.angle_deg
    return (kyphosis + PROFILE_NOISE_SDS * thoracic.sd_deg < 0.0
            and lordosis + PROFILE_NOISE_SDS * lumbar.sd_deg < 0.0)  # fmt: skip


def inverted_profile_errors(
    name: str, orientation: tuple[str, str], landmarks: Sequence[tuple[int, float, float]], sd_mm: float
) -> list[FieldError]:
    """A ``lateral_profile_inverted`` error at ``<name>.patient_orientation`` when the view's thoracic and
    lumbar profiles both read inverted beyond the noise (``is_inverted``), else none. ``landmarks``:
    (level index, column, row) in film mm (top endplate midpoints); ``sd_mm`` the view's landmark SD."""
    points = sagittal_points(orientation, landmarks)
    thoracic = region_reading(points, THORACIC_WINDOW, THORACIC_REACH, sd_mm)
    if thoracic is None or thoracic.angle_deg >= 0.0:  # kyphotic: the lumbar region cannot make it inverted
        return []
    lumbar = region_reading(points, LUMBAR_WINDOW, LUMBAR_REACH, sd_mm)
    if not is_inverted(thoracic, lumbar):
        return []
    assert thoracic is not None and lumbar is not None
    column, row = orientation
    depth = column if PATIENT_AXES[column][1] else row
    other = "P" if depth == "A" else "A"
    return [
        FieldError(
            (name, "patient_orientation"),
            f"under the stated orientation {[column, row]} the {name} film's landmarks read a lordotic thoracic "
            f"spine ({thoracic.upper}–{thoracic.lower} {thoracic.angle_deg:.0f}° ± {thoracic.sd_deg:.0f}° of "
            f"kyphosis) and a kyphotic lumbar spine ({lumbar.upper}–{lumbar.lower} {-lumbar.angle_deg:.0f}° ± "
            f"{lumbar.sd_deg:.0f}° of lordosis): both inverted, which no normal or scoliotic spine is, and exactly "
            f"what a film mirrored left to right reads. Check the image's display and which side the patient's "
            f"anterior is on: with the direction toward the anterior labelled {other!r} instead of {depth!r} the "
            "profile reads kyphotic and lordotic",
            CHECK_NAME,
        )
    ]
