"""The generic spine T1..L5 at rest: segment lengths, cross-sections, normal sagittal profile,
elastic profiles, and the rest model of the discrete Cosserat rod.

Frame and directors as in ``DESIGN.md`` (LPS mm; R = [d1 d2 d3] as columns). Segment j joins
vertebra j to vertebra j+1 (16 segments); its rest length Δs_j is the distance between the two
vertebral-body centres: half of each body height plus the disc between them.

Dimension tables (``VERTEBRA_TABLE``, ``DISC_HEIGHT_MM``)
--------------------------------------------------------
Vertebral body height H (mean of anterior and posterior heights), endplate width W and depth D
(means of the upper and lower endplates), in mm, after Panjabi et al., "Thoracic human vertebrae:
quantitative three-dimensional anatomy", Spine 1991;16(8):888–901 (T1–T12), and Panjabi et al.,
"Human lumbar vertebrae: quantitative three-dimensional anatomy", Spine 1992;17(3):299–306
(L1–L5), their tables of linear dimensions (VBHa/VBHp, EPWu/EPWl, EPDu/EPDl). The numbers were
entered from our reading of those tables and rounded to 0.5 mm; they were not re-checked against
the printed tables and may be off by about 1–2 mm at some levels.

Disc heights (mid-disc, mm): thoracic about 4–6.5 mm increasing caudally, after Kunkel et al.,
"Morphometric analysis of the relationships between intervertebral disc and vertebral body
heights: an anatomical and radiographic study of the human thoracic spine", J Anat
2011;219:375–387 (approximate, as recalled); T12–L1 and lumbar 7.5–11.5 mm after the radiographic
values of Tibrewal & Pearcy, Spine 1985;10:452–454 (approximate, as recalled).

Check against real spines (VerSe 2019/2020 dev split, 24 CT spines, vertebral-body centroids;
Sekuboyina et al., Med Image Anal 2021, CC BY-SA 4.0): mean inter-centroid distance per segment,
T1–T2 … L4–L5, mm:
    VerSe dev: 20.3 20.8 20.9 20.9 22.2 22.3 23.0 23.5 24.9 26.4 28.6 30.7 32.7 34.4 35.3 33.8
    this table: 19.3 20.3 20.8 21.8 22.3 23.3 23.8 24.3 25.5 27.0 28.8 31.5 34.5 36.3 37.5 37.8
Thoracic segments agree within about 1 mm; lumbar ones are 5–11 % longer here (VerSe patients
are older, scanned supine, with lower lumbar discs). ``length_scale`` absorbs a patient's size.

Normal sagittal profile
-----------------------
Thoracic kyphosis T4–T12 = 38° and lumbar lordosis L1–L5 = 46°: values of the order of the
means reported for healthy adolescents and young adults (e.g. Bernhardt & Bridwell, Spine
1989;14:717–721, T3–T12 kyphosis about 36°; Mac-Thiong et al., Eur Spine J 2007;16:227–234);
the exact pair 38°/46° is the project's choice, not a single study's table. The angle is
distributed over the discs with the relative weights ``KYPHOSIS_WEIGHTS`` and
``LORDOSIS_WEIGHTS``: kyphosis largest at mid-thorax (T5–T9), the thoracolumbar junction
neutral, lordosis growing caudally, as described by Bernhardt & Bridwell (1989); the weights
are ours, shaped after that description, not their numbers.
"""

from __future__ import annotations

import functools
import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.optimize import brentq

from .errors import UnknownProfile
from .frames import frames_from_centreline
from .levels import LEVELS, N_LEVELS
from .measures import kyphosis_lordosis_deg
from .profile_files import PROFILE_NAME, PROFILES_DIR, forget_found, list_profiles

FloatArray = npt.NDArray[np.float64]


# level: (body height H, endplate width W, endplate depth D), mm (sources in the module docstring)
VERTEBRA_TABLE: dict[str, tuple[float, float, float]] = {
    "T1": (14.5, 25.5, 15.5),
    "T2": (16.0, 26.0, 16.5),
    "T3": (16.5, 26.0, 17.5),
    "T4": (17.0, 26.5, 18.5),
    "T5": (17.5, 27.5, 20.0),
    "T6": (18.0, 28.5, 21.5),
    "T7": (18.5, 29.5, 23.0),
    "T8": (19.0, 30.5, 24.5),
    "T9": (19.5, 32.0, 25.5),
    "T10": (20.5, 34.0, 26.5),
    "T11": (21.5, 37.0, 27.5),
    "T12": (23.0, 39.5, 28.5),
    "L1": (25.0, 41.5, 29.5),
    "L2": (26.0, 43.5, 31.0),
    "L3": (26.5, 45.5, 32.5),
    "L4": (26.5, 47.5, 33.5),
    "L5": (26.0, 49.0, 34.0),
}

# disc below each level T1..L4 (T1–T2 … L4–L5), mid-disc height, mm (sources in the module docstring)
DISC_HEIGHT_MM: tuple[float, ...] = (
    4.0,
    4.0,
    4.0,
    4.5,
    4.5,
    5.0,
    5.0,
    5.0,
    5.5,
    6.0,
    6.5,  # T1–T2 … T11–T12
    7.5,  # T12–L1
    9.0,
    10.0,
    11.0,
    11.5,  # L1–L2 … L4–L5
)

NORMAL_KYPHOSIS_T4_T12_DEG = 38.0
NORMAL_LORDOSIS_L1_L5_DEG = 46.0

# Relative kyphotic angle of each disc T1–T2 … T11–T12 (then 0 at T12–L1), and relative lordotic
# angle of L1–L2 … L4–L5 (shape after Bernhardt & Bridwell 1989; see module docstring).
KYPHOSIS_WEIGHTS: tuple[float, ...] = (1, 2, 3, 4, 5, 5, 5, 5, 4, 3, 2)
LORDOSIS_WEIGHTS: tuple[float, ...] = (4, 7, 13, 20)

_I_T4, _I_T12, _I_L1 = LEVELS.index("T4"), LEVELS.index("T12"), LEVELS.index("L1")


# ---------------------------------------------------------------- geometry


def _table_column(k: int) -> FloatArray:
    """Column k of ``VERTEBRA_TABLE`` (0 height, 1 endplate width, 2 depth) over the levels (17,), mm."""
    return np.array([VERTEBRA_TABLE[lv][k] for lv in LEVELS])


_HEIGHT_SUM_MM = 0.5 * (_table_column(0)[:-1] + _table_column(0)[1:]) + np.asarray(DISC_HEIGHT_MM)
"""(H_j + H_{j+1})/2 + disc_j (16,), mm: the rest lengths at length scale 1 (``rest_segment_lengths``)."""
_WIDTH_SUM_MM = _table_column(1)[:-1] + _table_column(1)[1:]
"""w_j + w_{j+1} (16,), mm: endplate widths of each segment's two vertebrae (``segment_semi_axes``)."""
_DEPTH_SUM_MM = _table_column(2)[:-1] + _table_column(2)[1:]
"""d_j + d_{j+1} (16,), mm: endplate depths of each segment's two vertebrae (``segment_semi_axes``)."""
for _table in (_HEIGHT_SUM_MM, _WIDTH_SUM_MM, _DEPTH_SUM_MM):
    _table.setflags(write=False)


def rest_segment_lengths(length_scale: float = 1.0) -> FloatArray:
    """Rest lengths Δs_j = (H_j + H_{j+1})/2 + disc_j between consecutive vertebral-body centres,
    mm (16,), times ``length_scale``."""
    return length_scale * _HEIGHT_SUM_MM


def segment_semi_axes(length_scale: float = 1.0) -> tuple[FloatArray, FloatArray]:
    """Semi-axes (a along d1, b along d2) of each segment's elliptical section, mm (16,) each:
    half the mean endplate width and depth of its two vertebrae, times ``length_scale``."""
    return length_scale * 0.25 * _WIDTH_SUM_MM, length_scale * 0.25 * _DEPTH_SUM_MM


def section_properties(a: npt.ArrayLike, b: npt.ArrayLike) -> dict[str, FloatArray]:
    """Area and second moments of an ellipse with semi-axes a (along d1) and b (along d2), mm:
    A = πab (mm²), I1 = πab³/4 about d1, I2 = πa³b/4 about d2, J = πa³b³/(a² + b²) (mm⁴)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    # the shared factors πa, b³ and πa³ once each, in the order the formulas multiply them
    pi_a, b3 = np.pi * a, b**3
    pi_a3 = np.pi * a**3
    return {
        "A": pi_a * b,
        "I1": pi_a * b3 / 4.0,
        "I2": pi_a3 * b / 4.0,
        "J": pi_a3 * b3 / (a**2 + b**2),
    }


def sagittal_profile_deg(kyphosis_deg: float, lordosis_deg: float) -> FloatArray:
    """Sagittal inclination β_i of each vertebra's tangent (17,), degrees, with β_T1 = 0: β_{i+1} =
    β_i − Δ_i, Δ the disc angles from the weights, scaled so that Σ Δ over T4–T12 = kyphosis and
    −Σ Δ over L1–L5 = lordosis (β as in ``measures.sagittal_inclination_deg``)."""
    wk = np.zeros(N_LEVELS - 1)
    wk[: len(KYPHOSIS_WEIGHTS)] = KYPHOSIS_WEIGHTS
    wl = np.zeros(N_LEVELS - 1)
    wl[_I_L1 : _I_L1 + len(LORDOSIS_WEIGHTS)] = LORDOSIS_WEIGHTS
    disc = kyphosis_deg * wk / wk[_I_T4:_I_T12].sum() - lordosis_deg * wl / wl.sum()
    return np.concatenate([[0.0], -np.cumsum(disc)])


def centreline_from_angles(ds: npt.ArrayLike, frontal_deg: npt.ArrayLike, sagittal_deg: npt.ArrayLike) -> FloatArray:
    """Positions (17,3) from T1 at the origin, given the segment lengths ds (16,) mm and the
    projected tangent angles of each vertebra (17,) in degrees: frontal φ (toward +x going
    caudally) and sagittal β (toward +y going caudally).

    Chord j runs along u_j = (tan φ̄_j, tan β̄_j, −1)/|…| with φ̄_j, β̄_j the means over its two
    vertebrae, so its frontal and sagittal projections make exactly the angles φ̄_j and β̄_j with
    the caudal vertical; p_{j+1} = p_j + Δs_j u_j.
    """
    ds = np.asarray(ds, dtype=float)
    phi = np.radians(np.asarray(frontal_deg, dtype=float))
    beta = np.radians(np.asarray(sagittal_deg, dtype=float))
    pm, bm = 0.5 * (phi[:-1] + phi[1:]), 0.5 * (beta[:-1] + beta[1:])
    u = np.stack([np.tan(pm), np.tan(bm), -np.ones_like(pm)], axis=1)
    u /= np.linalg.norm(u, axis=1)[:, None]
    return np.concatenate([np.zeros((1, 3)), np.cumsum(ds[:, None] * u, axis=0)])


def balance_offset_deg(
    ds: npt.ArrayLike, frontal_deg: npt.ArrayLike, sagittal_deg: npt.ArrayLike, axis: int, target_mm: float = 0.0
) -> float:
    """Constant c (degrees) to add to the frontal (axis 0) or sagittal (axis 1) angles so that
    p_L5 − p_T1 along that axis equals ``target_mm`` (0: L5 straight below T1)."""
    angles = [np.asarray(frontal_deg, dtype=float), np.asarray(sagittal_deg, dtype=float)]

    def gap(c: float) -> float:
        shifted = [a + c if k == axis else a for k, a in enumerate(angles)]
        return float(centreline_from_angles(ds, *shifted)[-1, axis] - target_mm)

    shifted = angles[axis]
    return float(brentq(gap, -80.0 - shifted.min(), 80.0 - shifted.max(), xtol=1e-10))


# ---------------------------------------------------------------- elastic profiles


@dataclass(frozen=True)
class Profile:
    """Elastic and fitting constants of the rod.

    youngs_modulus_mpa Y and shear_modulus_mpa G (MPa = N/mm²); shear_coefficient k (Timoshenko,
    dimensionless); fit_weight_pa and fit_weight_lateral w (N/mm): the fitting energy of a view
    is w Σ_i |r_i|², r_i the landmark residual in patient mm, so w·r² is in N·mm like the rod's
    potential energy. stretch_factor (dimensionless) scales the stretch stiffness Y·A: a disc's
    effective axial modulus differs from its bending one, so the two are calibrated apart.
    rest_shape: ``None`` for the normal literature profile (kyphosis/lordosis of healthy controls),
    else a calibrated sagittal rest shape ``{"sagittal_inclination_deg": [17 values, T1 = 0],
    "length_fractions": [16 values summing to 1], "source": ...}``. provenance: where each value
    comes from. population_prior: ``None`` (every stiffness from Y, G and the sections), else the
    rod's prior calibrated on the population (``PopulationPrior``, written by ``spine bench prior``):
    it sets the bending, twist and shear stiffnesses so that the prior alone predicts the
    population, and the set-up priors of the fit; Y then acts only in the stretch stiffness
    stretch_factor·Y·A, and G nowhere.
    """

    name: str
    youngs_modulus_mpa: float
    shear_modulus_mpa: float
    shear_coefficient: float
    fit_weight_pa: float
    fit_weight_lateral: float
    provenance: dict[str, Any] = field(default_factory=dict)
    stretch_factor: float = 1.0
    rest_shape: dict[str, Any] | None = None
    population_prior: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        for key in ("youngs_modulus_mpa", "shear_modulus_mpa", "shear_coefficient", "fit_weight_pa"):
            value = getattr(self, key)
            if not (isinstance(value, int | float) and np.isfinite(value) and value > 0):
                raise ValueError(f"profile {self.name!r}: {key} must be a finite number > 0, got {value!r}")
        if not (isinstance(self.stretch_factor, int | float) and np.isfinite(self.stretch_factor)
                and self.stretch_factor > 0):
            raise ValueError(f"profile {self.name!r}: stretch_factor must be a finite number > 0")
        if self.rest_shape is not None:
            incl = np.asarray(self.rest_shape.get("sagittal_inclination_deg", []), dtype=float)
            frac = np.asarray(self.rest_shape.get("length_fractions", []), dtype=float)
            if incl.shape != (N_LEVELS,) or frac.shape != (N_LEVELS - 1,) or not np.all(frac > 0):
                raise ValueError(f"profile {self.name!r}: rest_shape needs 17 inclinations and 16 positive fractions")
        lateral = self.fit_weight_lateral
        if not (isinstance(lateral, int | float) and np.isfinite(lateral) and lateral >= 0):
            raise ValueError(f"profile {self.name!r}: fit_weight_lateral must be finite and >= 0, got {lateral!r}")


_PROFILE_KEYS = tuple(Profile.__dataclass_fields__)
_OPTIONAL_PROFILE_KEYS = ("stretch_factor", "rest_shape", "population_prior")


def profile_from_dict(data: dict[str, Any]) -> Profile:
    """A Profile from its JSON object; every key of the dataclass but the optional ones
    (stretch_factor, rest_shape, population_prior) is required, no other key allowed."""
    missing = [k for k in _PROFILE_KEYS if k not in data and k not in _OPTIONAL_PROFILE_KEYS]
    extra = [k for k in data if k not in _PROFILE_KEYS]
    if missing or extra:
        raise ValueError(f"profile keys: missing {missing}, unexpected {extra}")
    return Profile(**{k: data[k] for k in _PROFILE_KEYS if k in data})


def load_profile(name: str = "default") -> Profile:
    """The shipped profile ``spine_engine/profiles/<name>.json``; UnknownProfile if there is none.
    Read once per process (``save_profile`` forgets what was read): a profile already read costs
    no file-system call; a missing one is looked for again on every call (failures are not cached)."""
    if not PROFILE_NAME.fullmatch(name):
        raise UnknownProfile(name, list_profiles())
    try:
        return _read_profile(name)
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
        raise UnknownProfile(name, list_profiles()) from None


@functools.lru_cache(maxsize=16)
def _read_profile(name: str) -> Profile:
    with (PROFILES_DIR / f"{name}.json").open(encoding="utf-8") as fh:
        return profile_from_dict(json.load(fh))


def save_profile(profile: Profile, path: str | os.PathLike[str]) -> None:
    """Write ``profile`` as JSON (the keys ``load_profile`` reads, in dataclass order)."""
    text = json.dumps(asdict(profile), indent=2, ensure_ascii=False)
    Path(path).write_text(text + "\n", encoding="utf-8")
    _read_profile.cache_clear()
    forget_found()


# ---------------------------------------------------------------- rest model


@dataclass(frozen=True)
class RestModel:
    """The generic spine at rest, for one profile and size.

    levels: T1..L5; ds (16,) mm; positions (17,3) mm with T1 at the origin and L5 straight below it;
    rotations (17,3,3), directors as columns, from ``frames_from_centreline`` (no lateral curve,
    no axial rotation: d1 = +x everywhere); alpha (16,3) = (Y·I1, Y·I2, G·J) in N·mm², bending
    about d1, bending about d2, torsion; beta (16,3) = (k·G·A, k·G·A, Y·A) in N, shear along d1,
    shear along d2, stretch.
    """

    levels: tuple[str, ...]
    ds: FloatArray
    positions: FloatArray
    rotations: FloatArray
    alpha: FloatArray
    beta: FloatArray
    profile: Profile
    length_scale: float


_UNIT_SEGMENT_LENGTHS = rest_segment_lengths(1.0)
"""Rest lengths at length scale 1 (16,), mm (read-only)."""
_UNIT_SEGMENT_LENGTHS.setflags(write=False)


@functools.lru_cache(maxsize=1)
def _normal_profile_unit() -> tuple[FloatArray, FloatArray]:
    """Positions and rotations of the normal sagittal profile at length scale 1, whose kyphosis and
    lordosis, measured by ``measures.kyphosis_lordosis_deg`` on the discrete centreline, are exactly
    the targets: the prescribed angles are corrected by fixed-point iteration on the measured ones.
    Angles do not depend on a uniform length scale, so a scaled model scales these positions."""
    ds = rest_segment_lengths(1.0)
    target = np.array([NORMAL_KYPHOSIS_T4_T12_DEG, NORMAL_LORDOSIS_L1_L5_DEG])
    prescribed = target.copy()
    frontal = np.zeros(N_LEVELS)
    for _ in range(50):
        beta = sagittal_profile_deg(*prescribed)
        beta = beta + balance_offset_deg(ds, frontal, beta, axis=1)
        positions = centreline_from_angles(ds, frontal, beta)
        rotations = frames_from_centreline(positions)
        k4, _, lordosis = kyphosis_lordosis_deg(rotations)
        error = target - np.array([k4, lordosis])
        if np.max(np.abs(error)) < 1e-9:
            break
        prescribed += error
    positions.setflags(write=False)
    rotations.setflags(write=False)
    return positions, rotations


@functools.lru_cache(maxsize=8)
def _calibrated_shape_unit(
    inclination_deg: tuple[float, ...], fractions: tuple[float, ...]
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Segment lengths, positions and rotations of a calibrated sagittal rest shape at length
    scale 1: total length that of the literature table, L5 straight below T1 (balanced)."""
    ds = np.asarray(fractions) / np.sum(fractions) * rest_segment_lengths(1.0).sum()
    frontal = np.zeros(N_LEVELS)
    beta = np.asarray(inclination_deg, dtype=float)
    beta = beta + balance_offset_deg(ds, frontal, beta, axis=1)
    positions = centreline_from_angles(ds, frontal, beta)
    rotations = frames_from_centreline(positions)
    for arr in (ds, positions, rotations):
        arr.setflags(write=False)
    return ds, positions, rotations


RestShapeKey = tuple[tuple[float, ...], tuple[float, ...]] | None
"""What a profile's rest shape depends on, hashable: None for the normal sagittal profile, else the
calibrated shape's (17 inclinations in degrees, 16 length fractions)."""


def rest_shape_key(profile: Profile) -> RestShapeKey:
    """The ``RestShapeKey`` of ``profile`` (``Profile`` itself holds dicts and is not hashable)."""
    if profile.rest_shape is None:
        return None
    return tuple(profile.rest_shape["sagittal_inclination_deg"]), tuple(profile.rest_shape["length_fractions"])


def rest_shape_unit_of(key: RestShapeKey) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``rest_shape_unit`` of any profile whose ``rest_shape_key`` is ``key`` (the same read-only arrays)."""
    if key is None:
        return (_UNIT_SEGMENT_LENGTHS, *_normal_profile_unit())
    return _calibrated_shape_unit(*key)


def rest_shape_unit(profile: Profile) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Segment lengths (16,) mm, positions (17, 3) mm and rotations (17, 3, 3) of the profile's
    rest shape at length scale 1 (read-only, computed once per shape): the normal sagittal profile,
    or the profile's calibrated ``rest_shape``. ``rest_model(profile)`` has these positions."""
    return rest_shape_unit_of(rest_shape_key(profile))


def rest_model(profile: Profile, length_scale: float = 1.0) -> RestModel:
    """The rest model of the generic spine for ``profile``; ``length_scale`` multiplies every
    length (segment lengths, positions and section semi-axes, so A ∝ scale², I, J ∝ scale⁴)."""
    if not (np.isfinite(length_scale) and length_scale > 0):
        raise ValueError(f"length_scale must be finite and > 0, got {length_scale}")
    unit_ds, unit_positions, rotations = rest_shape_unit(profile)
    ds = rest_segment_lengths(length_scale) if profile.rest_shape is None else unit_ds * length_scale
    positions = unit_positions * length_scale
    sec = section_properties(*segment_semi_axes(length_scale))
    Y, G, k = profile.youngs_modulus_mpa, profile.shear_modulus_mpa, profile.shear_coefficient
    alpha = np.empty((len(ds), 3))  # columns as np.stack(..., axis=1) would lay them, without its wrapper
    alpha[:, 0], alpha[:, 1], alpha[:, 2] = Y * sec["I1"], Y * sec["I2"], G * sec["J"]
    beta = np.empty((len(ds), 3))
    beta[:, 0] = beta[:, 1] = k * G * sec["A"]
    beta[:, 2] = profile.stretch_factor * Y * sec["A"]
    prior = population_prior(profile)
    if prior is not None:
        alpha[:, 0] = prior.bending_stiffness(ds, prior.sagittal_sd_deg)
        alpha[:, 1] = prior.bending_stiffness(ds, prior.frontal_sd_deg)
        alpha[:, 2] = prior.bending_stiffness(ds, prior.twist_sd_deg)
        beta[:, :2] = 2.0 * prior.temperature_nmm / (ds[:, None] * prior.shear_sd**2)
    for arr in (ds, positions, alpha, beta):
        arr.setflags(write=False)
    return RestModel(LEVELS, ds, positions, rotations, alpha, beta, profile, float(length_scale))


@dataclass(frozen=True)
class PopulationPrior:
    """The rod's prior calibrated on a population (``Profile.population_prior``).

    Read as a prior at the fit's temperature τ (``temperature_nmm``, N·mm: the landmark weight w over
    the reference magnification squared, w·σ_ref²/s_ref², ``fit.uncertainty``), the rod's energy
    E_I = ½ Σ_i Δs_i α_i (u_i − u⁰_i)² makes each segment's bending angle θ_i = Δs_i u_i Gaussian with
    SD θ_sd,i when α_i = 2 τ Δs_i / θ_sd,i² (N·mm², θ in rad), and a shear v_k Gaussian with SD σ_k
    when β_k = 2 τ / (Δs σ_k²) (N). Per segment (16, T1–T2 … L4–L5):

    * ``sagittal_sd_deg``: bending about d1 (sagittal plane), VerSe dev's spread scaled so that the
      prior's kyphosis T4–T12 has the population's SD;
    * ``frontal_sd_deg``: bending about d2 (frontal plane), AASCE training's spread scaled so that the
      prior's major Cobb angle has the population's mean;
    * ``stretch_sd``: segment length relative to the patient-scaled rest length over the population
      (reported; the stretch stiffness stays the profile's Y·A: the PA film sets the patient's size,
      and holding each segment to it cost two-film accuracy, docs/engine.md);
    * ``shear_sd`` (16, 2): the chord's component across the vertebra's axis (v1, v2),
      β_k = 2τ/(Δs σ_k²);
    * ``twist_sd_deg``: twist about d3, α_3 as the bending ones.

    Set-up priors of a standing patient facing the detector, SDs in degrees: ``orientation_sd_deg``
    ``{"T1": [about d1, about d2, about d3], "L5": [...]}`` (d1: sagittal inclination, the lean;
    d2: frontal tilt; d3: rotation about the body's long axis, the spin about the vertical).
    ``measure_sd_deg``: the population SD of each measure a film may leave undetermined, the floor of
    its reported SD then (``reconstruction``): kyphosis T4–T12 and lordosis L1–L5 (VerSe dev), and
    ``major_cobb_deg``, the major Cobb angle's SD over the population the frontal prior was calibrated
    on (AASCE 2019 training, 18.4° in ``default``; a profile without it floors no Cobb SD).
    ``length_over_pa_projection``: the population's mean of
    L/P, L the T1–L5 polyline's length and P that of its projection on the frontal (PA) plane, which
    scales a patient's rest length from the PA film (``length_correction``); None in older profiles.
    ``provenance``: data, command and checks.
    """

    temperature_nmm: float
    sagittal_sd_deg: FloatArray
    frontal_sd_deg: FloatArray
    stretch_sd: FloatArray
    shear_sd: FloatArray
    twist_sd_deg: FloatArray
    orientation_sd_deg: dict[str, FloatArray]
    measure_sd_deg: dict[str, float]
    length_over_pa_projection: float | None = None

    def bending_stiffness(self, ds: FloatArray, sd_deg: FloatArray) -> FloatArray:
        """α_i = 2 τ Δs_i / θ_sd,i² (N·mm²) of segments ``ds`` (mm) for angle SDs ``sd_deg``."""
        return np.asarray(2.0 * self.temperature_nmm * ds / np.radians(sd_deg) ** 2)


_PARSED_PRIORS: dict[int, tuple[dict[str, Any], PopulationPrior]] = {}
"""``population_prior``'s parses, keyed by the id of the profile's dict (kept alive beside them, so
an id is never reused while its entry stands): a loaded profile is parsed once, not per job."""


def population_prior(profile: Profile) -> PopulationPrior | None:
    """The profile's ``population_prior`` as arrays (None when it has none)."""
    data = profile.population_prior
    if data is None:
        return None
    hit = _PARSED_PRIORS.get(id(data))
    if hit is not None and hit[0] is data:
        return hit[1]
    parsed = _parse_population_prior(profile.name, data)
    if len(_PARSED_PRIORS) >= 32:
        _PARSED_PRIORS.clear()
    _PARSED_PRIORS[id(data)] = (data, parsed)
    return parsed


def _parse_population_prior(name: str, data: dict[str, Any]) -> PopulationPrior:
    keys = ("sagittal_sd_deg", "frontal_sd_deg", "stretch_sd", "twist_sd_deg")
    sd = {k: np.asarray(data[k], dtype=float) for k in keys}
    shear = np.asarray(data["shear_sd"], dtype=float).T
    if any(v.shape != (N_LEVELS - 1,) or not np.all(v > 0) for v in sd.values()) or shear.shape != (N_LEVELS - 1, 2):
        raise ValueError(f"profile {name!r}: population_prior needs 16 positive SDs per segment for each plane")
    orientation = {k: np.asarray(v, dtype=float) for k, v in data["orientation_sd_deg"].items()}
    measure_sd = {k: float(v) for k, v in data["measure_sd_deg"].items()}
    return PopulationPrior(
        float(data["temperature_nmm"]), sd["sagittal_sd_deg"], sd["frontal_sd_deg"], sd["stretch_sd"], shear,
        sd["twist_sd_deg"], orientation, measure_sd,
        float(data["length_over_pa_projection"]) if "length_over_pa_projection" in data else None,
    )


def length_correction(profile: Profile) -> float:
    """Factor on a rest length scaled from the PA film, dimensionless: c = E[L/P] / (L₀/P₀), with E[L/P]
    the population's mean ratio of the T1–L5 length to its PA projection's
    (``PopulationPrior.length_over_pa_projection``) and L₀/P₀ the rest shape's; 1 without it.

    The rest shape is the population's mean shape, and a mean shape is straighter than the spines it
    averages (E[1/cos β] > 1/cos E[β]): scaled only so that its PA projection is as long as a
    patient's, it would be about 1 % shorter than the patient on VerSe dev (L/P 1.038 against the rest
    shape's 1.027), and the fit would make that up by a larger magnification and flatter sagittal
    curves."""
    prior = population_prior(profile)
    if prior is None or prior.length_over_pa_projection is None:
        return 1.0
    return prior.length_over_pa_projection / _rest_length_over_pa_projection(rest_shape_key(profile))


@functools.lru_cache(maxsize=8)
def _rest_length_over_pa_projection(key: RestShapeKey) -> float:
    positions = rest_shape_unit_of(key)[1]
    return length_over_pa_projection(positions)


def length_over_pa_projection(positions: FloatArray) -> float:
    """L/P of a centreline (N, 3) mm, LPS: its polyline length over that of its projection on the
    frontal plane (x, z), the plane of a PA film."""
    length = float(np.sum(np.linalg.norm(np.diff(positions, axis=0), axis=1)))
    frontal = np.asarray(positions)[:, [0, 2]]
    return length / float(np.sum(np.linalg.norm(np.diff(frontal, axis=0), axis=1)))


def typical_bending_energy_nmm(profile: Profile, cobb_deg: float = 40.0, segments: int = 6) -> float:
    """Bending energy of one mid-thoracic segment (T7–T8) of a typical scoliotic curve, N·mm:
    ½ (Y·I2) θ²/Δs for a lateral bend θ = cobb/segments spread evenly over ``segments`` segments.
    It sets the scale of the fit weight: w·(0.2 mm)² ≈ this energy (``profiles/default.json``)."""
    j = LEVELS.index("T7")
    a, b = segment_semi_axes()
    i2 = section_properties(a[j], b[j])["I2"]
    theta = np.radians(cobb_deg / segments)
    return float(0.5 * profile.youngs_modulus_mpa * i2 * theta**2 / rest_segment_lengths()[j])
