"""The simulated scoliosis series of ``spine bench clinic``: films and cases.

A known spine (``Truth``) is filmed by a PA and a lateral radiograph of the superior endplate
midpoints (the rod's nodes) with Gaussian landmark noise (SD ``noise_mm`` per coordinate, detector
mm, seeded; the same noise draw serves every case of one spine). Geometry, in the spirit of a
full-spine series (``SID_MM``, ``PA_SOD_MM``): the PA's magnification at the spine's mid-plane is
SID/SOD = 1800/1600 = 1.125; the lateral is 5–10 % more magnified (drawn), its film turned in its
plane by 0.5–2° (drawn sign and size) and both films offset (drawn). The central ray meets the
patient within ``CENTRAL_RAY_SPREAD_MM`` of the spine's centroid (drawn). PA beam posterior →
anterior (−y), lateral beam right → left (+x, the patient's left side at the detector).

``CASES`` are what the clinic sends of such a series (``build_payload``): (a) uncalibrated PA +
full lateral, weak perspective, nothing given; (b) the same with the lateral from T4 down; (c)
perspective films (pinhole: magnification SID/d with d the source distance of each point) with
``acquisition`` giving SID, SOD and the central ray; (d) the same films without their geometry, stated
as point-source films (``acquisition.projection_model`` "perspective", as the DICOM layer sends a CR
film without SID);
(e) the PA film of (a) only; (f) the paper's case: T1 and L5 given from the truth, both views' weak
perspective given, films not turned; (g) the films of (c) with SID and SOD but no central ray (a DX
header), the ray farther from the spine (``RAY_OFFSET_SD_MM``); (h) the films of (d) without
``projection_model``, as a client that does not say they come from a point source sends them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from spine_engine.frames import frames_from_centreline
from spine_engine.levels import LEVELS, N_LEVELS
from spine_engine.measures import compute_measures
from spine_engine.models import (
    LATERAL_ORIENTATION,
    PA_ORIENTATION,
    Acquisition,
    JobPayload,
    LateralView,
    Measures,
    PAView,
)
from spine_engine.projection import image_axes

FloatArray = npt.NDArray[np.float64]

SID_MM = 1800.0
"""Source–detector distance of the simulated films, mm: the usual full-spine distance of about
1.8 m (72 inches)."""
PA_SOD_MM = 1600.0
"""Source to the spine's mid-plane on the PA film, mm (the mid-plane 20 cm before the detector); PA
magnification at that plane SID/SOD = 1.125."""
LATERAL_EXTRA_MAGNIFICATION = (1.05, 1.10)
"""The lateral film's magnification over the PA's, drawn uniformly: 5–10 % more (the spine's mid-plane
lies farther from the lateral's detector)."""
LATERAL_TURN_DEG = (0.5, 2.0)
"""Size of the lateral film's in-plane rotation, drawn uniformly with a random sign ("slightly
rotated"; a modelling choice)."""
CENTRAL_RAY_SPREAD_MM = 20.0
"""SD of the central ray's in-plane distance from the spine's centroid, per axis, mm ("near the
spine's middle"; a modelling choice)."""
RAY_OFFSET_SD_MM = 40.0
"""Case (g): SD per axis of the central ray's extra distance from the spine, mm, so that it lies up to
about 80 mm (2 SD) from the spine (the brief of the DX-header case)."""
FILM_OFFSET_MM = ((150.0, 250.0), (350.0, 550.0))
"""Range of the image (column, row) of the central ray, detector mm: where the spine's middle
lands on a 35 × 90 cm film (drawn uniformly; any offset is equivalent for the engine)."""

PA_BEAM = np.array([0.0, -1.0, 0.0])
"""PA film: the beam runs posterior → anterior (LPS −y)."""
LATERAL_BEAM = np.array([1.0, 0.0, 0.0])
"""Lateral film: the beam runs from the patient's right to left (LPS +x)."""


@dataclass(frozen=True)
class Case:
    """One clinical setting of the benchmark."""

    key: str
    title: str
    lateral_from: int | None = 0
    """First level index on the lateral film (None: no lateral)."""
    perspective: bool = False
    """Films made by a point source (pinhole) rather than weak perspective."""
    acquisition: bool = False
    """The views' ``acquisition`` (SID, SOD, central ray) is in the payload."""
    boundary: bool = False
    """T1 and L5 poses are given from the truth (the paper's setting)."""
    calibrated: bool = False
    """Each view's weak perspective ``projection`` is given and the lateral film is not turned."""
    central_ray: bool = True
    """With ``acquisition``: whether it gives the central ray (a DX header usually gives SID and SOD only)."""
    ray_offset_sd_mm: float = 0.0
    """SD per image axis of an extra offset of the central ray from the spine, mm (patient plane),
    drawn per spine apart from the series' own draws (``ray_offset``)."""
    point_source: bool = False
    """The views state ``acquisition.projection_model`` "perspective" (a film read from DICOM)."""


CASES: dict[str, Case] = {
    c.key: c
    for c in (
        Case("a", "PA + full lateral, uncalibrated"),
        Case("b", "PA + lateral T4-L5, uncalibrated", lateral_from=3),
        Case("c", "perspective PA + lateral, geometry given", perspective=True, acquisition=True),
        Case("d", "perspective PA + lateral, geometry unknown", perspective=True, point_source=True),
        Case("e", "PA only, uncalibrated", lateral_from=None),
        Case("f", "paper: T1/L5 given, calibrated PA + lateral", boundary=True, calibrated=True),
        Case("g", "perspective PA + lateral, SID/SOD without central ray, ray ~40 mm off", perspective=True,
             acquisition=True, central_ray=False, ray_offset_sd_mm=RAY_OFFSET_SD_MM),
        Case("h", "perspective PA + lateral, geometry unknown, not said to be a point source", perspective=True),
    )
}


@dataclass(frozen=True)
class Truth:
    """A known spine: positions (17, 3) mm LPS and rotations (17, 3, 3), directors as columns."""

    spine_id: str
    positions: FloatArray
    rotations: FloatArray
    axial_rotation_known: bool = True
    """False where the rotations are the centreline's frames only (VerSe gives centroids): their axial
    rotation is a convention, not a measurement, and is not compared."""


def centreline_measures(positions: npt.ArrayLike) -> Measures:
    """The measures of a spine's positions (17, 3) on the frames their centreline puts on them
    (``frames.frames_from_centreline``): how the benches measure a truth, which has no other frames
    (VerSe gives centroids), and a result "computed the same way"."""
    p = np.asarray(positions, dtype=float)
    return compute_measures(p, frames_from_centreline(p))


@dataclass(frozen=True)
class Film:
    """The geometry of one simulated radiograph (all lengths mm)."""

    orientation: tuple[str, str]
    beam: FloatArray
    """Unit vector of the beam, source → detector, LPS."""
    sod_mm: float
    """Source to the plane through the spine's centroid normal to the beam."""
    principal_point: FloatArray
    """(3,) where the central ray crosses that plane, patient mm."""
    central_ray: FloatArray
    """(2,) image (column, row) of the central ray, detector mm."""
    turn_deg: float
    """In-plane rotation of the film, degrees."""
    sid_mm: float = SID_MM

    @property
    def magnification(self) -> float:
        """Magnification at the mid-plane, SID/SOD."""
        return self.sid_mm / self.sod_mm

    def image(self, points: FloatArray, perspective: bool) -> FloatArray:
        """Image (column, row) in detector mm of points (k, 3).

        With q = (e_c·(r − c), e_r·(r − c)) the in-plane coordinates from the principal point c:
        p = Rot(γ) m q + p_c with m = SID / (SOD + b·(r − c)) (pinhole; b the beam) or the
        constant SID/SOD (weak perspective), γ the film's turn and p_c the central ray's image.
        """
        e_c, e_r = image_axes(self.orientation)
        rel = np.asarray(points, dtype=float) - self.principal_point
        q = np.stack((rel @ e_c, rel @ e_r), axis=-1)
        m = self.sid_mm / (self.sod_mm + rel @ self.beam) if perspective else np.full(len(rel), self.magnification)
        g = np.radians(self.turn_deg)
        rot = np.array([[np.cos(g), -np.sin(g)], [np.sin(g), np.cos(g)]])
        return np.asarray((m[:, None] * q) @ rot.T + self.central_ray)

    def weak_projection(self) -> tuple[float, tuple[float, float]]:
        """(scale s, translation T) of this film as the engine's weak perspective p = s E r + T
        (valid when the film is not turned): T = p_c − s E c."""
        e_c, e_r = image_axes(self.orientation)
        s = self.magnification
        t = self.central_ray - s * np.array([self.principal_point @ e_c, self.principal_point @ e_r])
        return s, (float(t[0]), float(t[1]))


@dataclass(frozen=True)
class Series:
    """A simulated scoliosis series of one spine: both films and the landmark noise."""

    truth: Truth
    pa: Film
    lateral: Film
    pa_noise: FloatArray
    """(17, 2) landmark noise of the PA film, detector mm."""
    lateral_noise: FloatArray
    """(17, 2) landmark noise of the lateral film, detector mm."""
    noise_mm: float


def seed_of(spine_id: str) -> int:
    """A spine's own seed, drawn with the run's seed so that each spine's draws are its own."""
    return sum((i + 1) * ord(ch) for i, ch in enumerate(spine_id))


def simulate_series(truth: Truth, noise_mm: float, seed: int, sid_mm: float = SID_MM) -> Series:
    """Draw the series geometry and noise of one spine (module docstring), deterministic for
    (seed, spine id); ``sid_mm``: both films taken at this SID, the PA's spine mid-plane
    SID − SOD = 200 mm before its detector as at ``SID_MM`` (the draws do not depend on it)."""
    rng = np.random.default_rng([seed, seed_of(truth.spine_id)])
    centre = truth.positions.mean(axis=0)
    pa_sod = sid_mm - (SID_MM - PA_SOD_MM)
    films = []
    for orientation, beam, sod in (
        (PA_ORIENTATION, PA_BEAM, pa_sod),
        (LATERAL_ORIENTATION, LATERAL_BEAM, None),
    ):
        e_c, e_r = image_axes(orientation)
        if sod is None:
            ratio = rng.uniform(*LATERAL_EXTRA_MAGNIFICATION)
            sod = sid_mm / (sid_mm / pa_sod * ratio)
            turn = rng.uniform(*LATERAL_TURN_DEG) * rng.choice([-1.0, 1.0])
        else:
            turn = 0.0
        offset = rng.normal(0.0, CENTRAL_RAY_SPREAD_MM, 2)
        ray = np.array([rng.uniform(*FILM_OFFSET_MM[0]), rng.uniform(*FILM_OFFSET_MM[1])])
        principal = centre + offset[0] * e_c + offset[1] * e_r
        films.append(Film(orientation, beam, float(sod), principal, ray, float(turn), sid_mm))
    pa_noise = rng.normal(0.0, noise_mm, (N_LEVELS, 2)) if noise_mm > 0 else np.zeros((N_LEVELS, 2))
    lateral_noise = rng.normal(0.0, noise_mm, (N_LEVELS, 2)) if noise_mm > 0 else np.zeros((N_LEVELS, 2))
    return Series(truth, films[0], films[1], pa_noise, lateral_noise, noise_mm)


def supports(field_name: str, view: type[PAView] | type[LateralView] | type[Acquisition] = PAView) -> bool:
    """Whether this engine's payload model has ``field_name`` on a view or its acquisition (the bench
    sends only what the engine knows)."""
    return field_name in view.model_fields


def ray_offset(series: Series, film: Film, case: Case) -> Film:
    """``film`` with its central ray moved by a drawn offset of SD ``case.ray_offset_sd_mm`` per image
    axis (seeded by the spine and the film's beam, apart from ``simulate_series``'s draws)."""
    if case.ray_offset_sd_mm <= 0.0:
        return film
    rng = np.random.default_rng([seed_of(series.truth.spine_id), int(abs(film.beam[0])), 40])
    e_c, e_r = image_axes(film.orientation)
    shift = rng.normal(0.0, case.ray_offset_sd_mm, 2)
    moved = film.principal_point + shift[0] * e_c + shift[1] * e_r
    return Film(film.orientation, film.beam, film.sod_mm, moved, film.central_ray, film.turn_deg, film.sid_mm)


def _view_payload(series: Series, film: Film, noise: FloatArray, levels: list[int], case: Case) -> dict[str, Any]:
    film = ray_offset(series, film, case)
    untilted = Film(film.orientation, film.beam, film.sod_mm, film.principal_point, film.central_ray, 0.0)
    used = untilted if case.calibrated else film
    points = used.image(series.truth.positions[levels], case.perspective) + noise[levels]
    view: dict[str, Any] = {
        "units": "mm",
        "patient_orientation": list(film.orientation),
        "landmarks": [
            {"level": LEVELS[i], "point": [float(p[0]), float(p[1])]} for i, p in zip(levels, points, strict=True)
        ],
    }
    if supports("landmark_sd_mm") and series.noise_mm > 0:
        view["landmark_sd_mm"] = series.noise_mm
    if case.calibrated:
        s, t = used.weak_projection()
        view["projection"] = {"scale": s, "translation": list(t)}
    if case.acquisition:
        view["acquisition"] = {
            "distance_source_to_detector_mm": film.sid_mm,
            "distance_source_to_patient_mm": film.sod_mm,
        }
        if case.central_ray:
            view["acquisition"]["central_ray"] = [float(film.central_ray[0]), float(film.central_ray[1])]
    if case.point_source and supports("projection_model", Acquisition):
        view.setdefault("acquisition", {})["projection_model"] = "perspective"
    return view


def build_payload(series: Series, case: Case) -> JobPayload:
    """The ``JobPayload`` a clinic would send for this series in this case (validated by the
    public model: a field this engine does not know yet fails here, and the case is reported as
    refused)."""
    payload: dict[str, Any] = {
        "pa": _view_payload(series, series.pa, series.pa_noise, list(range(N_LEVELS)), case),
    }
    if case.lateral_from is not None:
        levels = list(range(case.lateral_from, N_LEVELS))
        payload["lateral"] = _view_payload(series, series.lateral, series.lateral_noise, levels, case)
    if case.boundary:
        t = series.truth
        payload["boundary"] = {
            lv: {"position": t.positions[i].tolist(), "directors": t.rotations[i].T.tolist()}
            for lv, i in (("T1", 0), ("L5", N_LEVELS - 1))
        }
    return JobPayload.model_validate(payload)
