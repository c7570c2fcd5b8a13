"""The registration problem: the residual vector ρ of a configuration, its Jacobian and normal equations.

E = ‖ρ‖² (N·mm), with rows in this order (``RegistrationProblem.row_kinds``):

* rod: 6 per segment, E_I (``rod_rows``);
* landmarks: 2 per landmark, √w (P(r_j) − p)/s₀ with P the view's camera (``cameras``), p the
  landmark (detector mm) and s₀ the view's reference scale (so the rows are in patient mm ·√(N/mm));
* offset points (pedicle centres, inferior endplate midpoints), one row each, the column of
  √w (P(r_j + R_j o) − c)/s₀ (``pose_rows``);
* tilts, one row each, √w_m α (``pose_rows``);
* pose priors (soft boundary, the gauge): 6 rows each, √(κ/2) (r_j − r̄)/σ_r and
  √(κ/2) vee(log(R̄ᵀR_j))/σ_θ;
* camera priors: √(κ/2)(s − s̄)/σ_s on an estimated weak-perspective scale, √(κ/2) ψ/σ_ψ on an
  estimated film rotation, √(κ/2)(b·(r_mid − o) − d̄)/σ_d on an estimated perspective centre's depth
  (d̄: ``Camera.depth_prior_mean_mm``).

Unknowns (``ParameterLayout``): vertebra j's δr_j (mm) and δθ_j (rad) — r_j + δr_j,
R_j exp(hat δθ_j) — for the free vertebrae (all 17 without an exact boundary, else 1..N−2), then
the estimated camera parameters (added). Every non-rod row touches at most one vertebra, so the
vertebra block of JᵀJ stays banded (half-bandwidth 11) and the camera parameters form its border
(``banded.solve_bordered``).
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from ..rotations import exp_so3, log_so3
from .banded import KD, BorderedSystem, band_to_dense
from .cameras import NO_BEAM, landmark_rows_kernel, project
from .pose_rows import PoseRows
from .rod_rows import RodCache, RodRows, jr_inverse
from .types import (
    Camera,
    FitOutput,
    FloatArray,
    ParameterLayout,
    PointRows,
    Pose,
    PosePrior,
    RodParameters,
    State,
    ViewData,
    as_pose,
)


@njit(cache=True)
def _assemble_normal(
    H: FloatArray, g_rod: FloatArray, S_rod: FloatArray, Jv: FloatArray, rho: FloatArray, Jb: FloatArray,
    second: FloatArray, vertebra: np.ndarray, second_order: bool,
    ab: FloatArray, ab_2: FloatArray, g_ext: FloatArray, B_ext: FloatArray,
) -> None:
    """Add every row's share to the normal equations over the extended unknowns (6 per vertebra, fixed
    ends included), in upper band storage ab[KD + i − j, j] (``banded``):

    * segment i (columns 6i … 6i + 11): the upper triangle of J_iᵀJ_i (``H``, N−1 × 78 in
      ``np.triu_indices(12)`` order) into ab, J_iᵀρ_i (``g_rod``) into g_ext and, when
      ``second_order``, its Σρ∇²ρ (``S_rod``, same order) into ab_2;
    * non-rod row k at vertebra j = vertebra[k] ≥ 0 (columns 6j … 6j + 5): J_kᵀJ_k (upper) into ab,
      J_k ρ_k into g_ext, J_kᵀ Jb_k into the border B_ext (6N × P) and, when ``second_order``, the upper
      triangle of its θθ term ``second[k]`` into ab_2; rows with j < 0 touch no vertebra.
    """
    kd = ab.shape[0] - 1
    for i in range(H.shape[0]):
        c0 = 6 * i
        k = 0
        for a in range(12):
            g_ext[c0 + a] += g_rod[i, a]
            for b in range(a, 12):
                ab[kd + a - b, c0 + b] += H[i, k]
                if second_order:
                    ab_2[kd + a - b, c0 + b] += S_rod[i, k]
                k += 1
    P = Jb.shape[1]
    for k in range(len(rho)):
        j = vertebra[k]
        if j < 0:
            continue
        c0 = 6 * j
        for a in range(6):
            ja = Jv[k, a]
            g_ext[c0 + a] += ja * rho[k]
            for b in range(a, 6):
                ab[kd + a - b, c0 + b] += ja * Jv[k, b]
            for p in range(P):
                B_ext[c0 + a, p] += ja * Jb[k, p]
        if second_order:
            for a in range(3):
                for b in range(a, 3):
                    ab_2[kd + a - b, c0 + 3 + b] += second[k, a, b]


_NO_SECOND = np.zeros((0, 3, 3))
"""Stand-in for absent second-order terms (the assembly kernel takes arrays only)."""


def _check_view(view: ViewData, n: int) -> None:
    idx = np.asarray(view.indices)
    pts = np.asarray(view.points)
    if idx.ndim != 1 or pts.shape != (len(idx), 2):
        raise ValueError(f"view {view.name!r}: indices (k,) and points (k, 2) expected, got {idx.shape}, {pts.shape}")
    if len(idx) and (idx.min() < 0 or idx.max() >= n):
        raise ValueError(f"view {view.name!r}: landmark indices must lie in 0..{n - 1}")
    if not view.scale > 0.0:
        raise ValueError(f"view {view.name!r}: scale must be positive, got {view.scale}")
    if not view.weight >= 0.0:
        raise ValueError(f"view {view.name!r}: weight must be non-negative, got {view.weight}")
    PoseRows.check_view(view, n)


def _projection_args(
    view: ViewData, camera: Camera, beam: FloatArray
) -> tuple[FloatArray, FloatArray, float, float, bool]:
    """``landmark_rows_kernel``'s constant arguments of a view: E = [e_c; e_r] (2, 3), the beam b, SID
    and SOD (mm) and whether the camera is a point source (a weak-perspective one: b, SID, SOD unused)."""
    E = np.array((view.e_c, view.e_r), dtype=float)
    if camera.kind == "weak":
        return E, NO_BEAM, 1.0, 1.0, False
    return E, np.ascontiguousarray(beam, dtype=float), float(camera.sid_mm), float(camera.sod_mm), True


@njit(cache=True)
def _pose_prior_rows_kernel(
    r: FloatArray, idx: np.ndarray, mean_r: FloatArray, a: FloatArray, b: FloatArray, phi: FloatArray,
    Jr_inv: FloatArray, rho: FloatArray, Jv: FloatArray, start: int,
) -> None:
    """The pose priors' rows written in place from row ``start``, six per prior i (vertebra idx[i]):
    ρ = a_i (r − r̄_i) and b_i ⊙ φ_i (φ_i = log(R̄_iᵀR)); ∂ρ/∂r = a_i I and ∂ρ/∂θ = diag(b_i) J_r⁻¹(φ_i)
    into Jv (zero on entry)."""
    for i in range(idx.shape[0]):
        row = start + 6 * i
        for j in range(3):
            rho[row + j] = a[i] * (r[idx[i], j] - mean_r[i, j])
            rho[row + 3 + j] = b[i, j] * phi[i, j]
            Jv[row + j, j] = a[i]
            for col in range(3):
                Jv[row + 3 + j, 3 + col] = b[i, j] * Jr_inv[i, j, col]


def _pose_prior_arrays(
    priors: Sequence[PosePrior], energy_unit: float
) -> tuple[np.ndarray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """The pose priors as arrays (k priors): vertebrae (k,), mean positions (k, 3), mean rotations
    transposed (k, 3, 3), a = √(κ/2)/σ_r (k,) and b = √(κ/2)/σ_θ (k, 3) per axis."""
    half_k = np.sqrt(0.5 * energy_unit)
    idx = np.array([p.vertebra for p in priors], dtype=np.intp)
    mean_r = np.array([p.pose.position for p in priors], dtype=float).reshape(-1, 3)
    mean_RT = np.array([p.pose.rotation.T for p in priors], dtype=float).reshape(-1, 3, 3)
    a = half_k / np.array([p.position_sd_mm for p in priors], dtype=float)
    b = half_k / np.array([np.broadcast_to(np.asarray(p.rotation_sd_rad, dtype=float), (3,)) for p in priors],
                          dtype=float).reshape(-1, 3)  # fmt: skip
    return idx, mean_r, mean_RT, a, b


class RegistrationProblem:
    """Residual vector ρ, its analytic Jacobian and the normal equations, for fixed data (module docstring).

    ``top`` and ``bottom`` given: T1 and L5 are held exactly (the paper). Both None: all N vertebrae are
    free; ``pose_priors`` then hold soft poses and the gauge. ``energy_unit`` κ (N·mm) converts the
    priors' −log densities into energy; default: 2 w σ²/s₀² of the first view with σ = 1 mm.
    """

    def __init__(
        self,
        params: RodParameters,
        views: Sequence[ViewData],
        top: Pose | tuple[ArrayLike, ArrayLike] | None,
        bottom: Pose | tuple[ArrayLike, ArrayLike] | None,
        pose_priors: Sequence[PosePrior] = (),
        energy_unit: float | None = None,
        depth_reference: int | None = None,
    ):
        self.rod = RodRows(params)
        n = self.rod.n
        if (top is None) != (bottom is None):
            raise ValueError("give both top and bottom (exact ends) or neither (all vertebrae free)")
        self.n = n
        self.fixed_ends = top is not None
        self.top = as_pose(top, "top") if top is not None else None
        self.bottom = as_pose(bottom, "bottom") if bottom is not None else None
        self.params = params
        self.ds = self.rod.ds
        self.j0, self.j1 = (1, n - 1) if self.fixed_ends else (0, n)
        self.m = self.j1 - self.j0
        self.n_vertebra_params = 6 * self.m
        first = views[0] if views else None
        self.energy_unit = (
            float(energy_unit)
            if energy_unit is not None
            else (2.0 * first.weight / first.scale**2 if first is not None and first.weight > 0 else 1.0)
        )
        self.pose_priors = tuple(pose_priors)
        self._pose_prior_arrays = _pose_prior_arrays(self.pose_priors, self.energy_unit)
        self.depth_reference = (n - 1) // 2 if depth_reference is None else depth_reference
        self._set_views(views)

    def with_views(self, views: Sequence[ViewData]) -> RegistrationProblem:
        """The same problem (rod, ends, pose priors, energy unit κ) on other views: the same films with
        other cameras, e.g. a parameter held in one and estimated in the other."""
        other = copy.copy(self)
        other._set_views(views)
        return other

    def _set_views(self, views: Sequence[ViewData]) -> None:
        """The views, their cameras and every row and column that depends on them."""
        n = self.n
        for view in views:
            _check_view(view, n)
        names = [view.name for view in views]
        if len(set(names)) != len(names):
            raise ValueError(f"view names must be distinct, got {names}")
        self.views = tuple(views)

        # Cameras and the border's columns.
        self.cameras: tuple[Camera, ...] = tuple(view.get_camera() for view in self.views)
        col = self.n_vertebra_params
        self._cam_cols: list[np.ndarray] = []
        view_cols: dict[str, dict[str, int]] = {}
        for view, cam in zip(self.views, self.cameras, strict=True):
            free = np.flatnonzero(cam.free)
            cols = np.arange(col, col + len(free))
            self._cam_cols.append(cols)
            view_cols[view.name] = {cam.names[k]: int(c) for k, c in zip(free, cols, strict=True)}
            col += len(free)
        self.n_border = col - self.n_vertebra_params
        self._cam_free = [np.flatnonzero(cam.free) for cam in self.cameras]
        """Each camera's estimated parameters (positions in its ``values``)."""
        self._cam_border = [cols - self.n_vertebra_params for cols in self._cam_cols]
        """Their columns in the border (0..n_border−1)."""
        self.n_params = col
        position = np.full((n, 3), -1, dtype=np.intp)
        rotation = np.full((n, 3), -1, dtype=np.intp)
        first_cols = 6 * np.arange(self.m)[:, None]
        position[self.j0 : self.j1] = first_cols + np.arange(3)
        rotation[self.j0 : self.j1] = first_cols + 3 + np.arange(3)
        self.layout = ParameterLayout(position, rotation, self.n_vertebra_params, view_cols, self.n_params)

        # Rows.
        self.obs = PoseRows(self.views)
        kinds: list[str] = ["rod"] * (6 * (n - 1))
        self._lm_slices: dict[str, slice] = {}
        start = 0
        for view in self.views:
            k = len(view.indices)
            kinds += [f"landmark:{view.name}"] * (2 * k)
            self._lm_slices[view.name] = slice(start, start + k)
            start += k
        self.n_landmarks = start
        self._lm_constants = [
            (
                np.ascontiguousarray(view.indices, dtype=np.intp),
                np.ascontiguousarray(view.points, dtype=float),
                np.sqrt(float(view.weight)) / cam.reference_scale,
            )
            for view, cam in zip(self.views, self.cameras, strict=True)
        ]
        self._lm_rows_index = [np.repeat(idx, 2) for idx, _, _ in self._lm_constants]
        kinds += [f"offset:{name}" for name, sl in self.obs.offset_slices.items() for _ in range(sl.stop - sl.start)]
        kinds += [f"tilt:{name}" for name, sl in self.obs.tilt_slices.items() for _ in range(sl.stop - sl.start)]
        kinds += ["pose"] * (6 * len(self.pose_priors))
        self._camera_prior_rows = self._camera_priors()
        self._beams = [cam.beam_direction(v.e_c, v.e_r) for v, cam in zip(self.views, self.cameras, strict=True)]
        """Each view's beam direction b (perspective depth rows)."""
        self._projection_args = [_projection_args(v, cam, beam) for v, cam, beam in
                                 zip(self.views, self.cameras, self._beams, strict=True)]  # fmt: skip
        """Each view's constant arguments of ``landmark_rows_kernel``: E, b, SID, SOD, perspective."""
        self._camera_prior_sd = np.array([sd for *_, sd in self._camera_prior_rows], dtype=float)
        self._camera_prior_mean = np.array([mean for _, _, mean, _ in self._camera_prior_rows], dtype=float)
        first_value = np.cumsum([0] + [len(cam.values) for cam in self.cameras])
        self._camera_prior_value = np.array([first_value[k] + max(p, 0) for k, p, _, _ in self._camera_prior_rows],
                                            dtype=np.intp)  # fmt: skip
        """Each camera prior row's parameter in the cameras' values laid end to end (a depth row: a stand-in)."""
        self._camera_prior_depth = [(i, k) for i, (k, p, _, _) in enumerate(self._camera_prior_rows) if p < 0]
        """(row, view) of each depth row b·(r_mid − o), whose value is computed."""
        self._camera_prior_Jv, self._camera_prior_Jb = self._camera_prior_jacobians()
        self._point_vertebra = self._point_rows_vertebra()
        kinds += ["camera"] * len(self._camera_prior_rows)
        self.row_kinds = tuple(kinds)
        self.n_residuals = len(kinds)
        self.n_fit = 2 * self.n_landmarks
        """Number of landmark rows (2 per landmark)."""
        self.n_offsets = self.obs.n_offsets
        self.n_tilts = self.obs.n_tilts
        self.n_data_rows = self.n_fit + self.n_offsets + self.n_tilts
        self._n_ext = 6 * n
        self._vslice = slice(6 * self.j0, 6 * self.j1)

    # ------------------------------------------------------------------ configuration

    def initial_state(self, positions: ArrayLike, rotations: ArrayLike) -> State:
        """A ``State`` from positions and rotations (ends reset to top and bottom when exact) and the
        cameras' initial values."""
        r = np.array(positions, dtype=float)
        R = np.array(rotations, dtype=float)
        if r.shape != (self.n, 3) or R.shape != (self.n, 3, 3):
            raise ValueError(
                f"expected positions ({self.n}, 3) and rotations ({self.n}, 3, 3), got {r.shape}, {R.shape}"
            )
        if self.top is not None and self.bottom is not None:
            r[0], R[0] = self.top
            r[-1], R[-1] = self.bottom
        return State(r, R, tuple(np.array(cam.values, dtype=float) for cam in self.cameras))

    def with_boundary(self, positions: ArrayLike, rotations: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Copies of (positions, rotations), with vertebrae 0 and N−1 set to top and bottom when exact."""
        state = self.initial_state(positions, rotations)
        return state.r, state.R

    def retract(
        self, positions: FloatArray, rotations: FloatArray, delta: ArrayLike
    ) -> tuple[FloatArray, FloatArray]:
        """(positions, rotations) moved by the vertebra part of ``delta`` (copies; cameras unchanged)."""
        cams = tuple(np.array(cam.values, dtype=float) for cam in self.cameras)
        h = np.zeros(self.n_params)
        h[: self.n_vertebra_params] = np.asarray(delta, dtype=float)[: self.n_vertebra_params]
        moved = self.step(State(np.asarray(positions, dtype=float), np.asarray(rotations, dtype=float), cams), h)
        return moved.r, moved.R

    def step(self, state: State, delta: ArrayLike) -> State:
        """New configuration r_j + δr_j, R_j exp(hat δθ_j) for the free vertebrae, cameras + their steps."""
        h = np.asarray(delta, dtype=float)
        d = h[: self.n_vertebra_params].reshape(self.m, 6)
        r = state.r.copy()
        R = state.R.copy()
        r[self.j0 : self.j1] += d[:, :3]
        R[self.j0 : self.j1] = state.R[self.j0 : self.j1] @ exp_so3(d[:, 3:])
        cams = []
        for free, values, cols in zip(self._cam_free, state.cameras, self._cam_cols, strict=True):
            if len(cols):
                values = values.copy()
                values[free] += h[cols]
            cams.append(values)
        return State(r, R, tuple(cams))

    # ------------------------------------------------------------------ rows

    def _camera_priors(self) -> list[tuple[int, int, float, float]]:
        """(view number, parameter, mean, SD) of each Gaussian prior on an estimated camera parameter
        (s, ψ, the central ray's foot c); parameter −1 is the perspective depth row b·(r_mid − o)."""
        rows: list[tuple[int, int, float, float]] = []
        for k, cam in enumerate(self.cameras):
            if cam.kind == "weak" and cam.free[0] and cam.scale_prior is not None:
                rows.append((k, 0, cam.scale_prior[0], cam.scale_prior[1]))
            if cam.free[-1]:
                rows.append((k, len(cam.values) - 1, 0.0, cam.rotation_prior_sd_rad))
            if cam.kind == "perspective" and cam.free[2:5].any():
                rows.append((k, -1, cam.depth_prior_mean_mm, cam.depth_prior_sd_mm))
            if cam.kind == "perspective" and cam.central_ray_prior is not None:
                mean, sd = cam.central_ray_prior
                rows += [(k, p, float(mean[p]), sd) for p in (0, 1) if cam.free[p]]
        return rows

    def point_rows(self, state: State, second_order: bool = False) -> PointRows:
        """All non-rod rows with their Jacobians (module docstring), written into arrays of the final size."""
        r, R, cams = state
        n_rows = len(self._point_vertebra)
        rho_all = np.empty(n_rows)
        Jv_all = np.zeros((n_rows, 6))
        Jb_all = np.zeros((n_rows, self.n_border))
        second = np.zeros((n_rows, 3, 3)) if second_order else None
        start = 0
        # landmarks
        for k, (idx, points, c) in enumerate(self._lm_constants):
            if not len(idx):
                continue
            E, beam, sid, sod, perspective = self._projection_args[k]
            landmark_rows_kernel(r, idx, points, c, E, np.ascontiguousarray(cams[k], dtype=float), beam, sid, sod,
                                 perspective, self._cam_free[k], self._cam_border[k], rho_all, Jv_all, Jb_all, start)
            start += 2 * len(idx)
        offsets = self.obs.offset_rows(state, self.cameras, self._cam_border, self.n_border, second_order)
        for part in (offsets, self.obs.tilt_rows(state, self.n_border, second_order)):
            if part is not None:
                rows = slice(start, start + len(part.rho))
                rho_all[rows] = part.rho
                Jv_all[rows] = part.Jv
                Jb_all[rows] = part.Jb
                if second is not None:
                    assert part.second is not None
                    second[rows] = part.second
                start = rows.stop
        # pose priors, all at once: rows (r − r̄)·a and b·log(R̄ᵀR) per prior
        if self.pose_priors:
            idx, mean_r, mean_RT, a, b = self._pose_prior_arrays
            phi = log_so3(mean_RT @ R[idx])
            _pose_prior_rows_kernel(r, idx, mean_r, a, b, phi, jr_inverse(phi), rho_all, Jv_all, start)
            start += 6 * len(idx)
        # camera priors: their Jacobians are constant (``_camera_prior_jacobians``), their ρ are not
        if self._camera_prior_rows:
            half_k = np.sqrt(0.5 * self.energy_unit)
            stop = start + len(self._camera_prior_rows)
            Jv_all[start:stop], Jb_all[start:stop] = self._camera_prior_Jv, self._camera_prior_Jb
            values = np.concatenate(cams)[self._camera_prior_value]
            for i, k in self._camera_prior_depth:
                values[i] = float(self._beams[k] @ (r[self.depth_reference] - cams[k][2:5]))
            rho_all[start:stop] = half_k * (values - self._camera_prior_mean) / self._camera_prior_sd
        return PointRows(rho_all, self._point_vertebra, Jv_all, Jb_all, second)

    def _camera_prior_jacobians(self) -> tuple[FloatArray, FloatArray]:
        """(Jv, Jb) of the camera prior rows, constant: √(κ/2)/σ on the parameter's column, and for a
        depth row √(κ/2) b/σ on the reference vertebra's position and −√(κ/2) b/σ on the source's."""
        half_k = np.sqrt(0.5 * self.energy_unit)
        Jv = np.zeros((len(self._camera_prior_rows), 6))
        Jb = np.zeros((len(self._camera_prior_rows), self.n_border))
        for i, (k, p, _, sd) in enumerate(self._camera_prior_rows):
            cols = dict(zip(self._cam_free[k].tolist(), self._cam_border[k].tolist(), strict=True))
            if p >= 0:
                Jb[i, cols[p]] = half_k / sd
                continue
            Jv[i, :3] = half_k * self._beams[k] / sd
            for axis in range(3):
                if (2 + axis) in cols:
                    Jb[i, cols[2 + axis]] = -half_k * self._beams[k][axis] / sd
        return Jv, Jb

    def _point_rows_vertebra(self) -> np.ndarray:
        """The vertebra of each non-rod row (−1: none), in ``point_rows`` order; fixed for the problem."""
        parts = [np.repeat(idx, 2) for idx, _, _ in self._lm_constants]
        parts += [np.asarray(v.offset_indices, dtype=np.intp) for v in self.views if v.n_offsets]
        parts.append(np.asarray(self.obs.tilt_indices, dtype=np.intp))
        parts += [np.full(6, prior.vertebra, dtype=np.intp) for prior in self.pose_priors]
        depth = self.depth_reference
        parts += [np.array([-1 if p >= 0 else depth], dtype=np.intp) for _, p, _, _ in self._camera_prior_rows]
        vertebra = np.concatenate(parts) if parts else np.zeros(0, dtype=np.intp)
        vertebra.flags.writeable = False
        return vertebra

    def evaluate(self, state: State, second_order: bool = False) -> tuple[FloatArray, RodCache, PointRows]:
        """ρ (layout in the module docstring), the rod cache and the non-rod rows (with Jacobians and,
        when ``second_order``, their θθ second-order terms)."""
        out = np.empty(self.n_residuals)
        cache = self.rod.evaluate(state.r, state.R, out)
        rows = self.point_rows(state, second_order)
        out[6 * (self.n - 1) :] = rows.rho
        return out, cache, rows

    # ------------------------------------------------------------------ derivatives

    def normal_equations(
        self, state: State, res: FloatArray, cache: RodCache, second_order: bool, rows: PointRows | None = None
    ) -> tuple[BorderedSystem, FloatArray | None, FloatArray]:
        """Gauss–Newton normal matrix JᵀJ (bordered), the band of Σ_k ρ_k ∇²ρ_k over the vertebrae (when
        ``second_order``, else None) and the gradient Jᵀρ, over the unknowns. ``rows``: the non-rod rows
        of ``state`` when already evaluated (with their second-order terms when ``second_order``)."""
        ns = self.n - 1
        rod = self.rod.normal_blocks(cache, res[: 6 * ns].reshape(ns, 6), second_order)
        if rows is None or (second_order and rows.second is None):
            rows = self.point_rows(state, second_order)
        P = self.n_border
        ab_gn = np.zeros((KD + 1, self._n_ext))
        ab_2 = np.zeros((KD + 1, self._n_ext)) if second_order else None
        g_ext = np.zeros(self._n_ext)
        B_ext = np.zeros((self._n_ext, P))
        _assemble_normal(
            rod.H, rod.g, rod.S if rod.S is not None else rod.H, rows.Jv, rows.rho, rows.Jb,
            rows.second if rows.second is not None else _NO_SECOND, rows.vertebra, second_order,
            ab_gn, ab_gn if ab_2 is None else ab_2, g_ext, B_ext,
        )
        C = rows.Jb.T @ rows.Jb
        g = np.concatenate((g_ext[self._vslice], rows.Jb.T @ rows.rho))
        system = BorderedSystem(ab_gn[:, self._vslice], B_ext[self._vslice], C)
        return system, (None if ab_2 is None else ab_2[:, self._vslice]), g

    def jacobian_state(self, state: State, evaluated: tuple[RodCache, PointRows] | None = None) -> FloatArray:
        """Analytic Jacobian ∂ρ/∂x at ``state``, dense (n_residuals, n_params); columns as ``layout``.
        ``evaluated``: the rod cache and non-rod rows of ``state`` when already evaluated."""
        cache, rows = self.evaluate(state)[1:] if evaluated is None else evaluated
        J_loc = self.rod.local_jacobian(cache).J
        ns = self.n - 1
        J = np.zeros((self.n_residuals, self._n_ext + self.n_border))
        seg = np.arange(ns)
        J[(6 * seg[:, None, None] + np.arange(6)[None, :, None]), (6 * seg[:, None, None] + np.arange(12))] = J_loc
        start = 6 * ns
        k = np.flatnonzero(rows.vertebra >= 0)
        J[(start + k)[:, None], 6 * rows.vertebra[k][:, None] + np.arange(6)] = rows.Jv[k]
        J[start:, self._n_ext :] = rows.Jb
        return np.concatenate((J[:, self._vslice], J[:, self._n_ext :]), axis=1)

    # ------------------------------------------------------------------ public conveniences

    def residuals(self, positions: ArrayLike, rotations: ArrayLike) -> FloatArray:
        """Residual vector ρ of a configuration (cameras at their initial values); E = ‖ρ‖² in N·mm."""
        return self.evaluate(self.initial_state(positions, rotations))[0]

    def jacobian(self, positions: ArrayLike, rotations: ArrayLike) -> FloatArray:
        """Analytic Jacobian ∂ρ/∂x, dense, cameras at their initial values (columns as ``layout``)."""
        return self.jacobian_state(self.initial_state(positions, rotations))

    def gradient_and_hessian(
        self, positions: ArrayLike, rotations: ArrayLike, second_order: bool = True
    ) -> tuple[FloatArray, FloatArray]:
        """(Jᵀρ, JᵀJ + Σ_k ρ_k ∇²ρ_k), dense; ½ the gradient and Hessian of E(retract(x, δ)) at δ = 0
        (camera rows Gauss–Newton). Without ``second_order`` the matrix is the Gauss–Newton JᵀJ."""
        state = self.initial_state(positions, rotations)
        res, cache, _ = self.evaluate(state)
        system, ab_2, g = self.normal_equations(state, res, cache, second_order)
        H = system.dense()
        if ab_2 is not None:
            H[: self.n_vertebra_params, : self.n_vertebra_params] += band_to_dense(ab_2)
        return g, H

    def energy(self, positions: ArrayLike, rotations: ArrayLike) -> float:
        """E = ‖ρ‖², N·mm."""
        res = self.residuals(positions, rotations)
        return float(res @ res)

    def output(self, state: State, res: FloatArray, cache: RodCache, iterations: int, converged: bool) -> FitOutput:
        """The ``FitOutput`` of a configuration: strains, energies, unweighted residuals per view."""
        ns = self.n - 1
        u, v = self.rod.strains(cache)
        rod = res[: 6 * ns]
        data = res[6 * ns : 6 * ns + self.n_data_rows]
        distances: dict[str, FloatArray] = {}
        for k, (view, cam) in enumerate(zip(self.views, self.cameras, strict=True)):
            idx = np.asarray(view.indices, dtype=int)
            pr = project(cam, state.cameras[k], state.r[idx], view.e_c, view.e_r)
            diff = (pr.points - np.asarray(view.points, dtype=float)) / cam.reference_scale
            distances[view.name] = np.sqrt(np.einsum("ij,ij->i", diff, diff))
        offsets, tilts = self.obs.unweighted(state, self.cameras)
        return FitOutput(
            positions=state.r,
            rotations=state.R,
            u=u,
            v=v,
            energy_fit=float(data @ data),
            energy_internal=float(rod @ rod),
            iterations=iterations,
            converged=converged,
            residuals_mm=distances,
            offset_residuals_mm=offsets,
            tilt_residuals_deg=tilts,
            cameras={view.name: values for view, values in zip(self.views, state.cameras, strict=True)},
        )
