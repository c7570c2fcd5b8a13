"""Offset-point and tilt rows (``ViewData``): observations that touch one vertebra's pose.

* an offset point (pedicle centre, inferior endplate midpoint) o fixed in vertebra j (body frame,
  mm), one row: the image column of √w (P(r_j + R_j o) − c)/s₀ with P the view's camera:
      ∂ρ/∂δr_j = g,  ∂ρ/∂δθ_j = o × (R_jᵀ g),  g = √w/s₀ ∂P_col/∂r,
      ∇²_θθ ρ = ½(ω oᵀ + o ωᵀ) − (ω·o) I with ω = R_jᵀ g (exact for a weak perspective, whose g is
      constant; the perspective's curvature in r is left out: a Gauss–Newton term);
* a tilt, one row ρ = √w_m α (rad · √(N·mm)), α = atan2(ĉ × a, ĉ·a) the signed angle from the
  observed unit direction ĉ to the projected director a = E R_j e (E = [e_c; e_r]):
      ∂a/∂δθ_j = A with rows e × (R_jᵀ E_k), k = column, row;  ∂α/∂a = a⊥/|a|², a⊥ = (−a_row, a_col);
      ∂ρ/∂δθ_j = √w_m Aᵀ a⊥/|a|²;
      ∇²_θθ ρ = √w_m (Aᵀ H_a A + ½(ω eᵀ + e ωᵀ) − (ω·e) I), ω = R_jᵀ Eᵀ a⊥/|a|², and H_a the
      Hessian of atan2(a_row, a_col): [[2xy, y² − x²], [y² − x², −2xy]]/|a|⁴, (x, y) = a.
  The observed direction is taken in the film's frame (its in-plane rotation ψ, a degree or two, is
  not applied to tilts).
(With a right perturbation R exp(hat δθ), ∂(R exp(hat δθ) b)/∂δθ = −R hat(b) and the second
derivative of cᵀR exp(hat δθ) b is ½(ω bᵀ + b ωᵀ) − (ω·b) I with ω = Rᵀc.)
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numba import njit

from ..rotations import vector_norms
from .cameras import project
from .types import Camera, FloatArray, IntArray, PointRows, State, ViewData


def _shape(a: np.ndarray | None) -> tuple[int, ...]:
    return () if a is None else tuple(np.shape(a))


def rotational(omega: FloatArray, b: FloatArray) -> FloatArray:
    """½(ω bᵀ + b ωᵀ) − (ω·b) I per row: the second derivative of cᵀR exp(hat δθ) b (ω = Rᵀc)."""
    outer = omega[:, :, None] * b[:, None, :]
    return 0.5 * (outer + np.swapaxes(outer, 1, 2)) - np.einsum("ij,ij->i", omega, b)[:, None, None] * np.eye(3)


@njit(cache=True)
def _tilt_kernel(
    R: FloatArray, idx: IntArray, E: FloatArray, e: FloatArray, c: FloatArray, sw: FloatArray, second_order: bool
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(ρ (m,), ∂ρ/∂(δr, δθ) (m, 6), ∇²_θθ ρ·ρ (m, 3, 3), zero unless ``second_order``) of the tilt rows
    (module docstring), tilt by tilt (the small arrays' numpy calls cost more than their arithmetic):
    W_k = R_jᵀ E_k, A_k = e × W_k, a_k = W_k·e, g = a⊥/|a|², ∂ρ/∂δθ = √w Σ_k g_k A_k, ρ = √w α."""
    m = idx.shape[0]
    rho = np.empty(m)
    Jv = np.zeros((m, 6))
    S = np.zeros((m, 3, 3))
    W = np.empty((2, 3))
    A = np.empty((2, 3))
    om = np.empty(3)
    for n in range(m):
        j = idx[n]
        for k in range(2):
            for i in range(3):
                W[k, i] = R[j, 0, i] * E[n, k, 0] + R[j, 1, i] * E[n, k, 1] + R[j, 2, i] * E[n, k, 2]
            A[k, 0] = e[n, 1] * W[k, 2] - e[n, 2] * W[k, 1]
            A[k, 1] = e[n, 2] * W[k, 0] - e[n, 0] * W[k, 2]
            A[k, 2] = e[n, 0] * W[k, 1] - e[n, 1] * W[k, 0]
        x = W[0, 0] * e[n, 0] + W[0, 1] * e[n, 1] + W[0, 2] * e[n, 2]
        y = W[1, 0] * e[n, 0] + W[1, 1] * e[n, 1] + W[1, 2] * e[n, 2]
        r2 = x * x + y * y
        g0, g1 = -y / r2, x / r2
        rho[n] = sw[n] * math.atan2(c[n, 0] * y - c[n, 1] * x, c[n, 0] * x + c[n, 1] * y)
        for i in range(3):
            Jv[n, 3 + i] = sw[n] * (A[0, i] * g0 + A[1, i] * g1)
        if second_order:
            r4 = r2 * r2
            h00 = 2.0 * x * y / r4
            h01 = (y * y - x * x) / r4
            scale = rho[n] * sw[n]
            for i in range(3):
                om[i] = W[0, i] * g0 + W[1, i] * g1
            om_e = om[0] * e[n, 0] + om[1] * e[n, 1] + om[2] * e[n, 2]
            for i in range(3):
                for l in range(3):
                    ha = A[0, i] * (h00 * A[0, l] + h01 * A[1, l]) + A[1, i] * (h01 * A[0, l] - h00 * A[1, l])
                    rot = 0.5 * (om[i] * e[n, l] + e[n, i] * om[l]) - (om_e if i == l else 0.0)
                    S[n, i, l] = scale * (ha + rot)
    return rho, Jv, S


class PoseRows:
    """The offset-point and tilt observations of every view, stacked (module docstring)."""

    @staticmethod
    def check_view(view: ViewData, n: int) -> None:
        """Raise ValueError when the view's optional observations have inconsistent shapes."""
        if view.n_offsets:
            q = view.n_offsets
            pi = np.asarray(view.offset_indices)
            if pi.ndim != 1 or _shape(view.offset_vectors) != (q, 3) or _shape(view.offset_columns) != (q,):
                raise ValueError(f"view {view.name!r}: offset indices (q,), vectors (q, 3) and columns (q,) expected")
            if pi.min() < 0 or pi.max() >= n:
                raise ValueError(f"view {view.name!r}: offset indices must lie in 0..{n - 1}")
        if view.n_tilts:
            m = view.n_tilts
            ti = np.asarray(view.tilt_indices)
            if ti.ndim != 1 or _shape(view.tilt_directions) != (m, 2) or _shape(view.tilt_weights) != (m,):
                raise ValueError(f"view {view.name!r}: tilt indices (m,), directions (m, 2) and weights (m,) expected")
            if ti.min() < 0 or ti.max() >= n:
                raise ValueError(f"view {view.name!r}: tilt indices must lie in 0..{n - 1}")
            if _shape(view.tilt_director) != (3,):
                raise ValueError(f"view {view.name!r}: tilts need a tilt_director (3,)")
            if (vector_norms(np.asarray(view.tilt_directions, dtype=float)) <= 0.0).any():
                raise ValueError(f"view {view.name!r}: tilt directions must be non-zero")
            if (~(np.asarray(view.tilt_weights, dtype=float) >= 0.0)).any():
                raise ValueError(f"view {view.name!r}: tilt weights must be non-negative")

    def __init__(self, views: Sequence[ViewData]):
        self.views = tuple(views)
        self.offset_slices: dict[str, slice] = {}
        self.tilt_slices: dict[str, slice] = {}
        t_idx, t_e, t_E, t_c, t_sw = [], [], [], [], []
        q0 = m0 = 0
        for view in self.views:
            if view.n_offsets:
                self.offset_slices[view.name] = slice(q0, q0 + view.n_offsets)
                q0 += view.n_offsets
            if view.n_tilts:
                m = view.n_tilts
                E = np.array((view.e_c, view.e_r), dtype=float)
                d = np.asarray(view.tilt_directions, dtype=float)
                t_idx.append(np.asarray(view.tilt_indices, dtype=np.intp))
                t_e.append(np.repeat(np.asarray(view.tilt_director, dtype=float)[None], m, axis=0))
                t_E.append(np.repeat(E[None], m, axis=0))
                t_c.append(d / vector_norms(d)[:, None])
                t_sw.append(np.sqrt(np.asarray(view.tilt_weights, dtype=float)))
                self.tilt_slices[view.name] = slice(m0, m0 + m)
                m0 += m
        self.n_offsets = q0
        self.n_tilts = m0
        self._tilt_idx = np.concatenate(t_idx) if t_idx else np.zeros(0, dtype=np.intp)
        self._tilt_e = np.concatenate(t_e) if t_e else np.zeros((0, 3))
        self._tilt_E = np.concatenate(t_E) if t_E else np.zeros((0, 2, 3))
        self._tilt_c = np.concatenate(t_c) if t_c else np.zeros((0, 2))
        self._tilt_sw = np.concatenate(t_sw) if t_sw else np.zeros(0)

    @property
    def tilt_indices(self) -> np.ndarray:
        """(m,) vertebra of each tilt row, all views stacked."""
        return self._tilt_idx

    # ------------------------------------------------------------------ offsets

    @staticmethod
    def _offset_view(k: int, view: ViewData, state: State, cam: Camera) -> tuple:
        j = np.asarray(view.offset_indices, dtype=int)
        o = np.asarray(view.offset_vectors, dtype=float)
        Rj = state.R[j]
        X = state.r[j] + (Rj @ o[:, :, None])[:, :, 0]
        pr = project(cam, state.cameras[k], X, view.e_c, view.e_r)
        c = np.sqrt(float(view.weight)) / cam.reference_scale
        diff = pr.points[:, 0] - np.asarray(view.offset_columns, dtype=float)
        return cam, j, o, Rj, pr, c, diff

    def offset_rows(
        self,
        state: State,
        cameras: Sequence[Camera],
        border_columns: Sequence[IntArray],
        n_border: int,
        second_order: bool,
    ) -> PointRows | None:
        """Rows, Jacobians (and θθ second-order terms) of the offset points (module docstring);
        ``border_columns[k]``: the border columns (0..``n_border``) of camera k's free parameters."""
        if not self.n_offsets:
            return None
        rho_l, idx_l, Jv_l, Jb_l, S_l = [], [], [], [], []
        for k, view in enumerate(self.views):
            if not view.n_offsets:
                continue
            cam, j, o, Rj, pr, c, diff = self._offset_view(k, view, state, cameras[k])
            g = c * pr.d_r[:, 0, :]
            omega = np.einsum("nji,nj->ni", Rj, g)
            rho = c * diff
            Jv = np.concatenate((g, np.cross(o, omega)), axis=1)
            Jb = np.zeros((len(j), n_border))
            if len(border_columns[k]):
                Jb[:, border_columns[k]] = c * pr.d_params[:, 0, cam.free]
            rho_l.append(rho)
            idx_l.append(j)
            Jv_l.append(Jv)
            Jb_l.append(Jb)
            if second_order:
                S_l.append(rho[:, None, None] * rotational(omega, o))
        return PointRows(
            np.concatenate(rho_l),
            np.concatenate(idx_l),
            np.concatenate(Jv_l),
            np.concatenate(Jb_l),
            np.concatenate(S_l) if second_order else None,
        )

    # ------------------------------------------------------------------ tilts

    def _tilt_angles(self, R: FloatArray) -> FloatArray:
        """α (m,), radians: each tilt's signed angle from the observed direction to the projected director."""
        return _tilt_kernel(np.ascontiguousarray(R, dtype=float), self._tilt_idx, self._tilt_E, self._tilt_e,
                            self._tilt_c, np.ones(self.n_tilts), False)[0]  # fmt: skip

    def tilt_rows(self, state: State, n_border: int, second_order: bool) -> PointRows | None:
        """Rows, Jacobians (and θθ second-order terms) of the tilts (module docstring)."""
        m = self.n_tilts
        if not m:
            return None
        R = np.ascontiguousarray(state.R, dtype=float)
        rho, Jv, S = _tilt_kernel(R, self._tilt_idx, self._tilt_E, self._tilt_e, self._tilt_c, self._tilt_sw,
                                  second_order)  # fmt: skip
        return PointRows(rho, self._tilt_idx, Jv, np.zeros((m, n_border)), S if second_order else None)

    # ------------------------------------------------------------------ report

    def unweighted(
        self, state: State, cameras: Sequence[Camera]
    ) -> tuple[dict[str, FloatArray], dict[str, FloatArray]]:
        """Per view, the offset points' signed column residuals (patient mm: detector mm / s₀) and the
        tilts' signed angles (degrees); unweighted, so a zero weight does not hide them."""
        offsets: dict[str, FloatArray] = {}
        for k, view in enumerate(self.views):
            if view.n_offsets:
                cam, *_, diff = self._offset_view(k, view, state, cameras[k])
                offsets[view.name] = diff / cam.reference_scale
        tilt = np.degrees(self._tilt_angles(state.R)) if self.n_tilts else np.zeros(0)
        tilts = {name: tilt[sl].copy() for name, sl in self.tilt_slices.items()}
        return offsets, tilts
