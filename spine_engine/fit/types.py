"""Data types of the fit: one ``FloatArray``, poses, views, rod parameters, outputs.

Conventions (``docs/engine.md``): positions in mm (DICOM LPS), rotations R = [d1 d2 d3] with the
directors as columns, image points (column, row) in detector mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..rotations import cross

FloatArray = NDArray[np.float64]
"""The one float array type of the engine's numerics."""
IntArray = NDArray[np.intp]


class Pose(NamedTuple):
    """A vertebra's pose: position (3,) in mm (LPS) and rotation (3, 3) with the directors as columns."""

    position: FloatArray
    rotation: FloatArray


class State(NamedTuple):
    """A configuration: positions (N, 3), rotations (N, 3, 3) and each view's camera parameters."""

    r: FloatArray
    R: FloatArray
    cameras: tuple[FloatArray, ...]


def as_pose(pose: Any, name: str = "pose") -> Pose:
    """The one pose helper: a ``Pose`` of float copies from a (position, rotation) pair, a ``Pose``, or a
    payload ``models.Pose`` (whose ``directors`` are rows [d1, d2, d3], so R = directorsᵀ)."""
    if hasattr(pose, "directors"):
        r = np.array(pose.position, dtype=float)
        R = np.array(pose.directors, dtype=float).T
    else:
        r = np.array(pose[0], dtype=float)
        R = np.array(pose[1], dtype=float)
    if r.shape != (3,) or R.shape != (3, 3):
        raise ValueError(f"{name} must be (position (3,), rotation (3, 3)), got {r.shape}, {R.shape}")
    return Pose(r, R)


def nearest_rotation(R: ArrayLike) -> FloatArray:
    """Nearest rotation to R (polar decomposition): directors valid within 1e-3 become exact."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=float))
    return np.asarray(U @ Vt)


class PosePrior(NamedTuple):
    """A soft pose: vertebra number ``vertebra`` is held near ``pose`` with SDs (Gaussian).

    Rows ρ = √(κ/2)·(r − r̄)/σ_r and √(κ/2)·vee(log(R̄ᵀR))/σ_θ (κ: ``Solution.energy_unit``), σ_θ one
    SD for every axis or three, about the mean pose's own directors d1, d2, d3 (rad)."""

    vertebra: int
    pose: Pose
    position_sd_mm: float
    rotation_sd_rad: float | FloatArray


FILM_TURN_PRIOR_SD_DEG = 2.0
"""SD of the Gaussian prior on a film's in-plane turn ψ when it is estimated, degrees (a film
is turned in its plane by a small angle; not fitted to the simulated films, docs/engine.md)."""
CENTRAL_RAY_PRIOR_SD_MM = 50.0
"""SD of the Gaussian prior on where the central ray meets the detector when a perspective film's
header gives SID and SOD but neither the central ray nor the image size, per image axis, detector
mm, around the landmarks' centre. In a standing full-spine series the patient's spine is centred on
the image receptor and the central ray on the receptor's centre (Bontrager & Lampignano, Textbook
of Radiographic Positioning and Related Anatomy, scoliosis series: "centre IR to CR", the
midsagittal plane to the CR); 50 mm per axis is our allowance for off-centring (a modelling
choice, not a measured spread)."""
DEPTH_PRIOR_SD_MM = 30.0
"""SD of the Gaussian that holds the spine's mid-plane at SOD on a perspective film whose
central-ray point o is estimated, mm (docs/engine.md)."""


@dataclass(frozen=True)
class Camera:
    """The projection of one view (``fit.cameras``), with which of its parameters the fit estimates.

    weak perspective, parameters [s, T_c, T_r, ψ]:  p = s·Rot(ψ)·(e_c·r, e_r·r) + T;
    perspective (pinhole), parameters [c_c, c_r, o_x, o_y, o_z, ψ]:
        p = c + m(r)·Rot(ψ)·(e_c·(r − o), e_r·(r − o)),  m(r) = SID / (SOD + b·(r − o)),
    with b the beam direction (source → detector; ``beam``), c the central ray's foot on the
    detector (detector mm) and o the point of the central ray at SOD from the source (patient mm).
    Rot(ψ) = [[cos ψ, −sin ψ], [sin ψ, cos ψ]] turns the film in its plane (rad).
    """

    kind: str
    """"weak" or "perspective"."""
    values: FloatArray
    """Initial (or given) parameter values, in the order of the docstring."""
    free: NDArray[np.bool_]
    """Which parameters the fit estimates."""
    sid_mm: float = 0.0
    """Source–detector distance (perspective only), mm."""
    sod_mm: float = 0.0
    """Source to the spine's mid-plane (perspective only), mm."""
    scale_prior: tuple[float, float] | None = None
    """(mean, SD) of a Gaussian prior on s when s is free (weak perspective)."""
    rotation_prior_sd_rad: float = np.radians(FILM_TURN_PRIOR_SD_DEG)
    """SD of the Gaussian prior on ψ when ψ is free ("a small in-plane rotation")."""
    depth_prior_sd_mm: float = DEPTH_PRIOR_SD_MM
    """Perspective with o free: SD of b·(r_mid − o), the mid-spine vertebra's distance from the plane at SOD."""
    depth_prior_mean_mm: float = 0.0
    """Perspective with o free: the mean of b·(r_mid − o), mm: how far along the beam the mid-spine
    vertebra lies from the spine's mid-plane, which is the plane at SOD (DESIGN.md: SOD runs "to the
    spine's mid-plane")."""
    beam: FloatArray | None = None
    """Perspective: unit beam direction b (source → detector), LPS; None: e_c × e_r."""
    central_ray_prior: tuple[FloatArray, float] | None = None
    """Perspective with c free: (mean (2,), SD) of a Gaussian prior on the central ray's foot c,
    detector mm (``CENTRAL_RAY_PRIOR_SD_MM``)."""
    depth_from_prior: bool = False
    """Perspective: the spine's distance from the source is known only from the depth prior (its SOD
    was assumed, ``clinical.pinhole_geometry``), as a weak view's magnification from ``scale_prior``."""

    def beam_direction(self, e_c: ArrayLike, e_r: ArrayLike) -> FloatArray:
        """b: ``beam`` or e_c × e_r."""
        if self.beam is not None:
            return np.asarray(self.beam, dtype=float)
        return cross(np.asarray(e_c, dtype=float), np.asarray(e_r, dtype=float))

    @property
    def names(self) -> tuple[str, ...]:
        return ("s", "T_c", "T_r", "psi") if self.kind == "weak" else ("c_c", "c_r", "o_x", "o_y", "o_z", "psi")

    @property
    def reference_scale(self) -> float:
        """s₀: the scale that converts detector mm to patient mm in the residual rows (fixed per fit)."""
        return float(self.values[0]) if self.kind == "weak" else self.sid_mm / self.sod_mm


def weak_camera(scale: float, translation: ArrayLike, free: bool = False, **kw: Any) -> Camera:
    """A weak-perspective camera; ``free``: s, T and ψ all estimated (ψ starts at 0)."""
    t = np.asarray(translation, dtype=float)
    mask = np.array([free, free, free, free])
    return Camera("weak", np.array([scale, t[0], t[1], 0.0]), mask, **kw)


@dataclass(frozen=True)
class ViewData:
    """One radiograph, with its landmarks already converted to detector mm."""

    name: str
    """View name, "pa" or "lateral"."""
    indices: np.ndarray
    """(k,) int: vertebra index 0..N−1 of each landmark."""
    points: np.ndarray
    """(k, 2) image points (column, row), detector mm."""
    e_c: np.ndarray
    """(3,) patient-space unit vector of the image column direction."""
    e_r: np.ndarray
    """(3,) patient-space unit vector of the image row direction."""
    scale: float
    """Weak-perspective magnification s (dimensionless): the reference s₀ of the residual rows."""
    translation: np.ndarray
    """(2,) weak-perspective translation T, detector mm (initial value when the camera is estimated)."""
    weight: float
    """Fitting weight w, N/mm."""
    landmark_sd_mm: float = 1.0
    """σ, the landmarks' SD per image coordinate, detector mm (``weight`` holds it already); the default
    is the payload's, ``models.LANDMARK_SD_MM_DEFAULT``."""
    offset_indices: np.ndarray | None = None
    """(q,) int: vertebra index of each offset-point observation (optional)."""
    offset_vectors: np.ndarray | None = None
    """(q, 3) the point in the vertebra's body frame, o = (o1, o2, o3) along (d1, d2, d3), mm."""
    offset_columns: np.ndarray | None = None
    """(q,) image column of each point, detector mm (only the column, across the spine, is fitted)."""
    tilt_indices: np.ndarray | None = None
    """(m,) int: vertebra index of each tilt observation (optional)."""
    tilt_directions: np.ndarray | None = None
    """(m, 2) observed image direction (column, row) of the vertebra's transverse axis; any length > 0."""
    tilt_weights: np.ndarray | None = None
    """(m,) weight w_m of each tilt observation, N·mm/rad²."""
    tilt_director: np.ndarray | None = None
    """(3,) body-frame director e whose projection the tilts observe (e.g. (1, 0, 0) = d1 on PA)."""
    camera: Camera | None = None
    """The view's projection; None: the weak perspective (scale, translation) above, fixed."""

    @property
    def n_offsets(self) -> int:
        return 0 if self.offset_indices is None else len(self.offset_indices)

    @property
    def n_tilts(self) -> int:
        return 0 if self.tilt_indices is None else len(self.tilt_indices)

    def get_camera(self) -> Camera:
        """The view's camera: ``camera``, or the fixed weak perspective (scale, translation)."""
        return self.camera if self.camera is not None else weak_camera(self.scale, self.translation)


@dataclass(frozen=True)
class RodParameters:
    """Rest shape and stiffness of the rod; N−1 segments."""

    ds: np.ndarray
    """(N−1,) rest lengths Δs, mm."""
    u0: np.ndarray
    """(N−1, 3) rest angular strains, rad/mm."""
    v0: np.ndarray
    """(N−1, 3) rest linear strains (dimensionless)."""
    alpha: np.ndarray
    """(N−1, 3) bending (α1, α2) and twisting (α3) stiffness, N·mm²."""
    beta: np.ndarray
    """(N−1, 3) shear (β1, β2) and axial (β3) stiffness, N."""


class ParameterLayout(NamedTuple):
    """Where each unknown sits in the parameter vector (columns of ``Solution.jacobian``).

    Vertebra j's position increment δr_j (mm) is at columns ``position[j]`` and its rotation
    increment δθ_j (rad, body frame: R_j exp(hat δθ_j)) at ``rotation[j]``; −1 for a vertebra held
    fixed (an exact boundary). The vertebra columns come first, 6 per free vertebra in level order,
    so that their normal matrix is banded (half-bandwidth 11); then the estimated projection
    parameters: ``views[name][param]`` (names in ``Camera``; s dimensionless, T, c in detector mm,
    o in patient mm, ψ in rad)."""

    position: IntArray
    """(N, 3) columns of δr_j, −1 when fixed."""
    rotation: IntArray
    """(N, 3) columns of δθ_j, −1 when fixed."""
    n_vertebra_params: int
    """6 × the number of free vertebrae: the banded part."""
    views: dict[str, dict[str, int]]
    """Per view, the column of each estimated projection parameter."""
    n_params: int


class Solution(NamedTuple):
    """What the solver returns: the optimum and what a Laplace approximation needs there.

    E = ‖ρ‖² (N·mm) and E = κ·(−log p(x | landmarks)) + const with κ = ``energy_unit`` (N·mm) when
    the landmarks' SDs are the views' ``landmark_sd_mm``: ρ is already weighted (whitened), so the
    weights are ``weights`` = 1 per row and H = JᵀJ is the Gauss–Newton Hessian of E/2; the
    Laplace covariance of the parameters is cov ≈ (κ/2)·(JᵀJ)⁻¹ (the rod's energy and every prior,
    soft pose and gauge rows are in ρ, so no separate prior Hessian is needed). Columns of J follow
    ``layout``; rows: 6 per segment (rod), 2 per landmark, then offset points, tilts, pose priors,
    gauge and projection priors (``row_kinds``).
    """

    positions: FloatArray
    """(N, 3) mm."""
    rotations: FloatArray
    """(N, 3, 3), directors as columns."""
    cameras: dict[str, FloatArray]
    """Per view, the camera parameters at the optimum (all of them, estimated or not)."""
    x: FloatArray
    """The estimated parameters at the optimum in ``layout`` order: zeros for the vertebra increments
    (the optimum is the chart's origin) and the projection parameters' values."""
    residuals: FloatArray
    """ρ at the optimum (n_rows,)."""
    jacobian: FloatArray
    """∂ρ/∂x at the optimum, dense (n_rows, n_params)."""
    weights: FloatArray
    """(n_rows,) ones: the rows are already whitened (kept for a weighted-least-squares reading)."""
    row_kinds: tuple[str, ...]
    """Kind of each row: "rod", "landmark:<view>", "offset:<view>", "tilt:<view>", "pose", "gauge", "camera"."""
    layout: ParameterLayout
    energy_unit: float
    """κ in N·mm (see above)."""
    output: FitOutput


@dataclass(frozen=True)
class FitOutput:
    """Result of ``fit``."""

    positions: np.ndarray
    """(N, 3) vertebra positions, mm (LPS)."""
    rotations: np.ndarray
    """(N, 3, 3) rotations, directors as columns."""
    u: np.ndarray
    """(N−1, 3) angular strains, rad/mm."""
    v: np.ndarray
    """(N−1, 3) linear strains."""
    energy_fit: float
    """E_f, N·mm."""
    energy_internal: float
    """E_I, N·mm."""
    iterations: int
    """Accepted (Newton / Levenberg–Marquardt) steps."""
    converged: bool
    """Whether a convergence criterion of ``solver.solve`` was met."""
    residuals_mm: dict[str, np.ndarray]
    """Per view name, (k,) distance between landmark and projected vertebra in patient mm (detector mm / s₀)."""
    offset_residuals_mm: dict[str, np.ndarray] = field(default_factory=dict)
    """Per view name with offset points, (q,) signed column residual, patient mm."""
    tilt_residuals_deg: dict[str, np.ndarray] = field(default_factory=dict)
    """Per view name with tilts, (m,) signed angle α from the observed to the model's axis, degrees."""
    cameras: dict[str, np.ndarray] = field(default_factory=dict)
    """Per view name, its camera parameters at the optimum (``Camera``)."""
    point_source: dict[str, PointSourceReading] = field(default_factory=dict)
    """Per view whose projection the payload did not state, with two films: the point source the films
    show (``fit.unstated_projection``)."""


class PointSourceReading(NamedTuple):
    """How far one weak-perspective film comes from a point source, as the two films read it
    (``fit.unstated_projection``)."""

    eta_per_mm: float
    """η̂ = 1/SOD (1/mm), its sign the side of the source along e_c × e_r; 0: a parallel beam."""
    sd_per_mm: float
    """η̂'s posterior SD (1/mm)."""
    stepped: bool
    """Whether the fit moved the spine toward the point source the films show."""


class PointRows(NamedTuple):
    """The non-rod rows of one configuration: each touches one vertebra (``vertebra``; −1: none)."""

    rho: FloatArray
    """(k,) values."""
    vertebra: np.ndarray
    """(k,) vertebra of each row (−1 when it touches none)."""
    Jv: FloatArray
    """(k, 6) ∂ρ/∂[δr_j, δθ_j]."""
    Jb: FloatArray
    """(k, P) ∂ρ/∂(estimated camera parameters)."""
    second: FloatArray | None
    """(k, 3, 3) ρ ∇²_θθ ρ of each row (offsets and tilts; zero elsewhere), when asked for."""
