"""Clinical landmark forms on a radiograph: four vertebral corners, pedicle centres, tilts.

Pure kernels on arrays. Image vectors are (column, row) in detector mm; a view's column and row
directions are the patient-space (LPS) unit vectors e_c, e_r of ``projection.image_axes``.
Directors as in ``DESIGN.md``: d1 ≈ patient left, d2 ≈ anterior, d3 caudal.

Corners (the AASCE 2019 form) are given per vertebra in the order top-left, top-right,
bottom-left, bottom-right, named as they appear in the image ("left" = smaller column, "top" =
smaller row). They give

* the **superior endplate midpoint** (the paper's landmark, fed to E_f as a point): the mean of
  the two corners on the cranial side of the image (the top pair when the rows run toward the
  feet, the bottom pair when they run toward the head);
* the **transverse axis** of the vertebra: the vector from the midpoint of its left edge
  (mean of top-left and bottom-left) to the midpoint of its right edge (mean of top-right and
  bottom-right), the line the AASCE 2019 Cobb angles were measured with; on a PA view
  (["L", "F"]) it points toward +column = patient left ≈ d1;
* the two **endplate lines** (top-left → top-right and bottom-left → bottom-right) for the
  endplate-based Cobb angle;
* the **inferior endplate midpoint**, whose image column is fitted as a point fixed in the
  vertebra at H (the body height of ``anatomy.VERTEBRA_TABLE``, scaled to the patient) along d3
  from the node: it tells the frontal direction of the body's axis d3, so that a tilt of the
  transverse axis is not explained by an axial rotation instead.

Pedicle centres are fixed offsets in the vertebra's own frame (``PEDICLE_TABLE``); only their
image column, the coordinate across the spine, is fitted (``fit.ViewData``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .anatomy import VERTEBRA_TABLE
from .levels import LEVELS

FloatArray = npt.NDArray[np.float64]

_X = np.array([1.0, 0.0, 0.0])
_Y = np.array([0.0, 1.0, 0.0])
_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class CornerGeometry:
    """What four corners per vertebra say, as image points and vectors (detector mm), (k, 2) each."""

    superior_midpoint: FloatArray
    inferior_midpoint: FloatArray
    transverse: FloatArray
    superior_endplate: FloatArray
    inferior_endplate: FloatArray


def corner_geometry(corners: npt.ArrayLike, e_r: npt.ArrayLike) -> CornerGeometry:
    """Endplate midpoints, transverse axis and endplate lines of vertebrae given by corners.

    corners (k, 4, 2): top-left, top-right, bottom-left, bottom-right, image (column, row) in
    detector mm; e_r (3,): the row direction. With rows toward the feet (e_r·z < 0) the top pair is
    the superior endplate: midpoint (TL + TR)/2, superior line TR − TL, inferior line BR − BL,
    inferior midpoint (BL + BR)/2; with rows toward the head the bottom pair is. The transverse
    axis is (TR + BR)/2 − (TL + BL)/2.
    Raises ValueError when the rows are horizontal (the image is not upright: no "top" endplate).
    """
    c = np.asarray(corners, dtype=float)
    if c.ndim != 3 or c.shape[1:] != (4, 2):
        raise ValueError(f"corners must have shape (k, 4, 2), got {c.shape}")
    down = float(np.asarray(e_r, dtype=float) @ _Z)
    if down == 0.0:
        raise ValueError("corners need an upright image: the row direction must be head (H) or feet (F)")
    tl, tr, bl, br = c[:, 0], c[:, 1], c[:, 2], c[:, 3]
    (sl, sr), (il, ir) = ((tl, tr), (bl, br)) if down < 0 else ((bl, br), (tl, tr))
    return CornerGeometry(
        superior_midpoint=0.5 * (sl + sr),
        inferior_midpoint=0.5 * (il + ir),
        transverse=0.5 * (tr + br) - 0.5 * (tl + bl),
        superior_endplate=sr - sl,
        inferior_endplate=ir - il,
    )


def transverse_director(e_c: npt.ArrayLike, e_r: npt.ArrayLike | None = None) -> FloatArray:
    """Body-frame director e (3,) whose projection a view's left–right image axis shows, signed so
    that R e ≈ e_c (e_r on a PA turned a quarter) for an upright vertebra facing forward.

    e_c = ±x (PA or AP view): e = ±(1, 0, 0), i.e. ±d1; e_c = ±y (lateral view): d2 ≈ −y, so
    e = ∓(0, 1, 0); e_c = ±z and e_r = ±x (a PA turned a quarter, its rows left–right): e = ±d1 along
    e_r. Raises ValueError for any other view whose columns run head–feet.
    """
    ec = np.asarray(e_c, dtype=float)
    if abs(float(ec @ _X)) == 1.0:
        return np.array([float(ec @ _X), 0.0, 0.0])
    if abs(float(ec @ _Y)) == 1.0:
        return np.array([0.0, -float(ec @ _Y), 0.0])
    sign = None if e_r is None else frontal_sign(ec, e_r)
    if sign is not None:  # a PA turned a quarter: its rows run left–right
        return np.array([sign, 0.0, 0.0])
    raise ValueError("the column direction must be horizontal (L, R, A or P) for tilts and pedicles")


def frontal_tilt_deg_of_image_vectors(vectors: npt.ArrayLike, e_c: npt.ArrayLike, e_r: npt.ArrayLike) -> FloatArray:
    """Frontal tilt θ (degrees) of image vectors on a frontal (PA or AP) view, in the sense of
    ``measures.frontal_tilt_deg``: the vector goes to patient space as v = v_c e_c + v_r e_r,
    turned toward patient left (v ← −v when e_c = −x), and θ = atan2(v_z, v_x).

    vectors (..., 2) detector mm (their length and a uniform magnification do not matter).
    Raises ValueError unless the view is frontal (``_toward_left``).
    """
    ec, er = np.asarray(e_c, dtype=float), np.asarray(e_r, dtype=float)
    v = np.asarray(vectors, dtype=float)
    v3 = _toward_left(ec, er) * (v[..., :1] * ec + v[..., 1:2] * er)
    return np.degrees(np.arctan2(v3[..., 2], v3[..., 0]))


def frontal_sign(e_c: npt.ArrayLike, e_r: npt.ArrayLike) -> float | None:
    """±1: the sign that turns an image vector along the image axis running left–right in the patient
    toward the patient's left (+x): e_c·x on a frontal view shown upright (columns L or R, rows H or F),
    e_r·x on one turned a quarter (rows L or R, columns H or F); None on any other view (not frontal)."""
    ec, er = np.asarray(e_c, dtype=float), np.asarray(e_r, dtype=float)
    if abs(float(ec @ _X)) == 1.0 and abs(float(er @ _Z)) == 1.0:
        return float(ec @ _X)
    if abs(float(er @ _X)) == 1.0 and abs(float(ec @ _Z)) == 1.0:
        return float(er @ _X)
    return None


def _toward_left(ec: FloatArray, er: FloatArray) -> float:
    """``frontal_sign``; raises ValueError on a view that is not frontal."""
    sign = frontal_sign(ec, er)
    if sign is None:
        raise ValueError("frontal tilts need a frontal view: one image axis L or R, the other H or F")
    return sign


def image_vectors_of_frontal_tilt(tilt_deg: npt.ArrayLike, e_c: npt.ArrayLike, e_r: npt.ArrayLike) -> FloatArray:
    """Unit image vectors (..., 2) of frontal tilts θ: the inverse of
    ``frontal_tilt_deg_of_image_vectors``; the patient direction ±(cos θ, 0, sin θ) projected."""
    ec, er = np.asarray(e_c, dtype=float), np.asarray(e_r, dtype=float)
    t = np.radians(np.asarray(tilt_deg, dtype=float))
    d = _toward_left(ec, er) * np.stack([np.cos(t), np.zeros_like(t), np.sin(t)], axis=-1)
    return np.stack([d @ ec, d @ er], axis=-1)


def chord_angles_deg(points: npt.ArrayLike, e_c: npt.ArrayLike, e_r: npt.ArrayLike) -> FloatArray:
    """Frontal angle φ (degrees) of each chord between consecutive image points (k, 2) → (k−1,):
    the chord in patient space Δ = Δ_c e_c + Δ_r e_r and φ = atan2(Δ_x, −Δ_z), positive when the
    spine runs toward the patient's left going caudally. For an upright vertebra perpendicular to
    the chord, its frontal tilt equals φ."""
    p = np.asarray(points, dtype=float)
    d = np.diff(p, axis=0)
    ec, er = np.asarray(e_c, dtype=float), np.asarray(e_r, dtype=float)
    d3 = d[:, :1] * ec + d[:, 1:2] * er
    return np.degrees(np.arctan2(d3[:, 0], -d3[:, 2]))


def tilt_weight(level_indices: npt.ArrayLike, point_weight: float) -> FloatArray:
    """Weight w_t (N·mm/rad²) of a vertebra's tilt observation, from its endplate width W (mm,
    ``anatomy.VERTEBRA_TABLE``, Panjabi et al. 1991/1992) and the view's point weight w (N/mm):

        w_t = w · W² / 2

    the cost of turning a segment of length W about its midpoint against two point landmarks
    at its ends (each end moves by W/2 · δ: 2 · w (W δ / 2)² = w W²/2 · δ²). A tilt off by
    1° then costs as much as its edge midpoints off by W/2 · 1° ≈ 0.25 mm at T7."""
    widths = np.array([VERTEBRA_TABLE[LEVELS[int(i)]][1] for i in np.atleast_1d(level_indices)])
    return float(point_weight) * widths**2 / 2.0


# ---------------------------------------------------------------- pedicles

# level: (spinal canal width SCW = interpedicular distance between the medial pedicle walls,
#         transverse pedicle width PDW), mm.
# SCW after Panjabi et al., Spine 1991;16(8):888–901 (T1–T12) and Spine 1992;17(3):299–306
# (L1–L5), their tables of spinal canal dimensions; PDW after Zindrick et al., "Analysis of the
# morphometric characteristics of the thoracic and lumbar pedicles", Spine 1987;12(2):160–166
# (transverse pedicle width per level). Entered from our reading of those tables, rounded to
# 0.5 mm (SCW) / 0.1 mm (PDW), not re-checked against the printed tables: expect errors of
# about 1–2 mm at some levels (the same caveat as ``anatomy.VERTEBRA_TABLE``).
PEDICLE_WIDTHS_MM: dict[str, tuple[float, float]] = {
    "T1": (22.5, 7.9),
    "T2": (18.0, 7.0),
    "T3": (16.5, 5.6),
    "T4": (16.0, 4.7),
    "T5": (16.0, 4.5),
    "T6": (16.0, 5.2),
    "T7": (16.5, 5.3),
    "T8": (16.5, 5.9),
    "T9": (17.0, 6.1),
    "T10": (17.5, 6.3),
    "T11": (19.0, 7.8),
    "T12": (21.5, 7.1),
    "L1": (22.5, 8.7),
    "L2": (23.0, 8.9),
    "L3": (23.5, 10.3),
    "L4": (24.0, 12.9),
    "L5": (26.5, 18.0),
}

PEDICLE_BEHIND_BODY_MM = 5.0
"""Distance from the posterior wall of the vertebral body to the centre of the pedicle's
isthmus, mm: about half the sagittal length of the pedicle between body and lamina (our
estimate of 8–12 mm for that length, consistent with pedicle lengths of about 16 mm measured
along the oblique pedicle axis at T1, Kim et al., J Korean Neurosurg Soc 2009;46:181–188)."""

PEDICLE_DROP_FRACTION = 1.0 / 3.0
"""Height of the pedicle centre below the superior endplate, as a fraction of the body height H:
the pedicles join the upper half of the posterior vertebral body (Gray's Anatomy, 41st ed., the
vertebral arch); one third is our estimate, not a measured value."""


def pedicle_offsets_mm(level_index: int, length_scale: float = 1.0) -> tuple[float, float, float]:
    """Body-frame offset (o1, o2, o3) in mm of the patient-left pedicle centre from the vertebra's
    node (the superior endplate midpoint, the point that projects onto the landmark):

        o1 = +(SCW + PDW)/2   (half the distance between the pedicle centres, along d1)
        o2 = −(D/2 + 5 mm)    (posterior, along −d2: half the endplate depth D, then
                               ``PEDICLE_BEHIND_BODY_MM`` behind the posterior wall)
        o3 = +H/3             (caudal, along d3: ``PEDICLE_DROP_FRACTION`` of the body height)

    The patient-right pedicle has −o1. SCW, PDW from ``PEDICLE_WIDTHS_MM``; D, H from
    ``anatomy.VERTEBRA_TABLE``. Every length is multiplied by ``length_scale``."""
    level = LEVELS[level_index]
    scw, pdw = PEDICLE_WIDTHS_MM[level]
    height, _, depth = VERTEBRA_TABLE[level]
    return (
        length_scale * 0.5 * (scw + pdw),
        -length_scale * (0.5 * depth + PEDICLE_BEHIND_BODY_MM),
        length_scale * PEDICLE_DROP_FRACTION * height,
    )


def inferior_midpoint_offsets(level_indices: npt.ArrayLike, length_scale: float = 1.0) -> FloatArray:
    """Body-frame offsets (k, 3) of the inferior endplate midpoint from the node (the superior
    one): (0, 0, H) along d3, H the body height of ``anatomy.VERTEBRA_TABLE`` × ``length_scale``."""
    heights = np.array([VERTEBRA_TABLE[LEVELS[int(i)]][0] for i in np.atleast_1d(level_indices)])
    out = np.zeros((len(heights), 3))
    out[:, 2] = length_scale * heights
    return out


def pedicle_offsets_in_image_order(
    level_indices: npt.ArrayLike, e_c: npt.ArrayLike, length_scale: float = 1.0
) -> FloatArray:
    """Offsets (2k, 3) of the pedicles of each level, image-left then image-right per level.

    On a view whose column runs toward the patient's left (e_c = +x, PA ["L", "F"]) the
    image-left pedicle is the patient-right one (o1 < 0); with e_c = −x (AP) it is the
    patient-left one. Raises ValueError unless e_c = ±x."""
    ec = np.asarray(e_c, dtype=float)
    sign = float(ec @ _X)
    if abs(sign) != 1.0:
        raise ValueError("pedicles need a frontal view whose columns run toward L or R")
    out = []
    for i in np.atleast_1d(level_indices):
        o1, o2, o3 = pedicle_offsets_mm(int(i), length_scale)
        out.append((-sign * o1, o2, o3))
        out.append((sign * o1, o2, o3))
    return np.array(out, dtype=float).reshape(-1, 3)
