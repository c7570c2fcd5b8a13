"""Synthetic scoliotic spines, built geometrically, for tests and experiments.

No energy minimiser is involved, so a registration tested on these spines is not tested on its
own assumptions. A spine is drawn from its projected tangent angles at the 17 vertebrae:

- frontal angle φ_i: monotone (PCHIP) interpolation, in arc length, of knot values at T1, at the
  end vertebrae and apex of each structural curve, and at L5. Between two end vertebrae φ rises
  (convex right) or falls (convex left) by the curve's amplitude; T1 and L5 keep a fraction of
  the neighbouring end vertebra's tilt, which makes the compensatory curves. These fractions and
  the common offset of the curve knots are solved for coronal balance (x_L5 − x_T1 = a drawn
  few mm), within ranges that keep every end vertebra a tilt extreme;
- sagittal angle β_i: the normal profile of ``anatomy.sagittal_profile_deg`` with the drawn
  kyphosis and lordosis, offset for sagittal balance;
- positions from ``anatomy.centreline_from_angles``, directors from ``frames_from_centreline``
  with an axial rotation toward the convexity of every curve, proportional to the frontal
  deviation from the curve's chord (zero at the end vertebrae, r·Cobb at the apex).

The amplitudes are then corrected by a damped fixed-point iteration on the spine's own measures
(``measures.frontal_curves``, ``measures.kyphosis_lordosis_deg``) until the frontal Cobb angle of
each structural curve, the kyphosis T4–T12 and the lordosis L1–L5 equal their targets within
0.05° (the best iterate is kept; over 1,200 seeds the largest Cobb error left was 0.8°): a
geometric rescaling, not a mechanical model. The measured end vertebrae and apex can differ by a
level or two from the designed knots (the discrete tangent smooths sharp short curves, and axial
rotation tilts the projected d1 of sagittally inclined vertebrae); ``SyntheticSpine.ends`` and
``apexes`` hold the measured ones.

Numbers drawn (uniformly) and their sources:

- curve types by apex level, SRS / Lenke et al., J Bone Joint Surg Am 2001;83:1169–1181:
  thoracic apex T2 to the T11–T12 disc, thoracolumbar T12–L1, lumbar L1–L2 disc to L4. End
  vertebrae are chosen at levels typical of each type (``CURVE_LEVELS``; our choice);
- convexity: right for 85 % of thoracic curves and left for 65 % of thoracolumbar and lumbar ones,
  a modelling choice reflecting the usual right-thoracic predominance in adolescent idiopathic
  scoliosis (not a prevalence taken from a table); double curves are thoracic and lumbar on
  opposite sides;
- frontal Cobb 10°–80° (the lumbar curve of a double curve 0.6–1.2 times the thoracic one);
- apical axial rotation r·Cobb with r in 0.2–0.5 toward the convexity: apical rotation grows with
  the Cobb angle and is of the order of a few tenths of it in moderate curves (Aaro & Dahlborn,
  Spine 1981;6:460–467; Perdriolle & Vidal, Spine 1985;10:785–791; Stokes, Bigalow & Moreland,
  Spine 1986;11:213–218); the ratio range is a modelling choice, not a fitted regression;
- kyphosis T4–T12 20°–60° and lordosis L1–L5 30°–65°: the range of healthy and scoliotic
  subjects around the normal profile of ``anatomy`` (same sources);
- segment lengths: the ``anatomy`` table ×(1 ± 10 %) per level × an overall size 0.85–1.15;
- balance: x_L5 − x_T1 within ±10 mm and y_L5 − y_T1 within ±20 mm, modelling choices well inside
  the usual clinical thresholds (coronal 20 mm; sagittal vertical axis 50 mm, Glassman et al.,
  Spine 2005;30:2024–2029);
- compensation (tilt kept at T1 / L5) drawn in 0–0.5 and solved in −0.6–0.7, knot offset at
  25–75 % (10–90 % if needed for balance) of its admissible range, apex knot at 40–60 % of the
  curve's tilt change: modelling choices.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from scipy.interpolate import PchipInterpolator
from scipy.optimize import brentq

from .anatomy import balance_offset_deg, centreline_from_angles, rest_segment_lengths, sagittal_profile_deg
from .frames import frames_from_centreline
from .levels import LEVEL_INDEX, LEVELS, N_LEVELS
from .measures import FrontalCurve, frontal_curves, frontal_tilt_deg, kyphosis_lordosis_deg, tilt_turning_points

FloatArray = npt.NDArray[np.float64]

KINDS: tuple[str, ...] = ("thoracic", "thoracolumbar", "lumbar", "double")

# (upper end, apex, lower end) level choices of each single-curve type
CURVE_LEVELS: dict[str, tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]]] = {
    "thoracic": (("T4", "T5", "T6"), ("T7", "T8", "T9"), ("T11", "T12", "L1")),
    "thoracolumbar": (("T8", "T9", "T10"), ("T12", "L1"), ("L2", "L3", "L4")),
    "lumbar": (("T11", "T12", "L1"), ("L2", "L3"), ("L4", "L5")),
}
COBB_RANGE_DEG = (10.0, 80.0)
ROTATION_RATIO_RANGE = (0.2, 0.5)
KYPHOSIS_RANGE_DEG = (20.0, 60.0)
LORDOSIS_RANGE_DEG = (30.0, 65.0)
SEGMENT_VARIATION = 0.10
SIZE_RANGE = (0.85, 1.15)
CORONAL_BALANCE_MM = 10.0
SAGITTAL_BALANCE_MM = 20.0
CALIBRATION_TOLERANCE_DEG = 0.05
CALIBRATION_ITERATIONS = 40
KEPT_FRACTION_DRAW = (0.0, 0.5)
KEPT_FRACTION_RANGE = (-0.6, 0.7)


@dataclass
class SyntheticSpine:
    """A generated spine: positions (17,3) mm, rotations (17,3,3) (directors as columns), its kind
    (``KINDS``), the frontal Cobb target of each structural curve top to bottom, the kyphosis
    T4–T12 and lordosis L1–L5 as measured on it, and the seed that regenerates it
    (``generate_spine(seed, kind)``).

    Per structural curve, top to bottom: ``ends`` and ``apexes`` as measured on the spine
    (``measures.frontal_curves``), the designed ``convexity`` and ``apical_rotation_ratio`` r.
    ``size_scale`` and ``ds`` (16,) mm are the drawn overall size and segment lengths."""

    positions: FloatArray
    rotations: FloatArray
    kind: str
    cobb_target_deg: tuple[float, ...]
    kyphosis_deg: float
    lordosis_deg: float
    seed: int
    ends: tuple[tuple[str, str], ...] = ()
    apexes: tuple[str, ...] = ()
    convexity: tuple[str, ...] = ()
    apical_rotation_ratio: tuple[float, ...] = ()
    size_scale: float = 1.0
    ds: FloatArray = field(default_factory=lambda: np.zeros(N_LEVELS - 1))


@dataclass(frozen=True)
class _Curve:
    upper: int
    apex: int
    lower: int
    rising: int  # +1: tilt rises caudally (convex right); −1: falls (convex left)
    apex_fraction: float
    target_deg: float
    rotation_ratio: float


@dataclass(frozen=True)
class _Design:
    ds: FloatArray
    curves: tuple[_Curve, ...]
    offset_fraction: float  # where the curve knots sit inside their admissible offset range
    kept_fraction: float  # tilt kept at T1 (or L5) relative to the neighbouring end vertebra
    balance_at_bottom: bool  # which compensatory piece is solved for balance first
    balance_x: float
    balance_y: float


def _pick(rng: np.random.Generator, names: tuple[str, ...]) -> int:
    return LEVEL_INDEX[names[int(rng.integers(len(names)))]]


def _design(rng: np.random.Generator, kind: str) -> tuple[_Design, float, float, float]:
    """Random design of one spine; also returns the kyphosis and lordosis targets and the size."""

    def curve(upper: int, apex: int, lower: int, rising: int, target: float) -> _Curve:
        return _Curve(
            upper, apex, lower, rising, float(rng.uniform(0.4, 0.6)), target, float(rng.uniform(*ROTATION_RATIO_RANGE))
        )

    cobb = float(rng.uniform(*COBB_RANGE_DEG))
    if kind == "double":
        ups, apx, _ = CURVE_LEVELS["thoracic"]
        _, lapx, lows = CURVE_LEVELS["lumbar"]
        junction = _pick(rng, ("T11", "T12", "L1"))
        rising = 1 if rng.random() < 0.85 else -1
        lumbar_cobb = float(np.clip(cobb * rng.uniform(0.6, 1.2), *COBB_RANGE_DEG))
        curves: tuple[_Curve, ...] = (
            curve(_pick(rng, ups), _pick(rng, apx), junction, rising, cobb),
            curve(junction, _pick(rng, lapx), _pick(rng, lows), -rising, lumbar_cobb),
        )
    elif kind in CURVE_LEVELS:
        ups, apx, lows = CURVE_LEVELS[kind]
        p_right = 0.85 if kind == "thoracic" else 0.35
        rising = 1 if rng.random() < p_right else -1
        curves = (curve(_pick(rng, ups), _pick(rng, apx), _pick(rng, lows), rising, cobb),)
    else:
        raise ValueError(f"unknown kind {kind!r}; known: {list(KINDS)}")
    size = float(rng.uniform(*SIZE_RANGE))
    ds = size * rest_segment_lengths() * rng.uniform(1 - SEGMENT_VARIATION, 1 + SEGMENT_VARIATION, N_LEVELS - 1)
    design = _Design(
        ds=ds,
        curves=curves,
        offset_fraction=float(rng.uniform(0.35, 0.65)),
        kept_fraction=float(rng.uniform(*KEPT_FRACTION_DRAW)),
        balance_at_bottom=bool(rng.random() < 0.5),
        balance_x=float(rng.uniform(-CORONAL_BALANCE_MM, CORONAL_BALANCE_MM)),
        balance_y=float(rng.uniform(-SAGITTAL_BALANCE_MM, SAGITTAL_BALANCE_MM)),
    )
    kyphosis = float(rng.uniform(*KYPHOSIS_RANGE_DEG))
    lordosis = float(rng.uniform(*LORDOSIS_RANGE_DEG))
    return design, kyphosis, lordosis, size


def _end_tilts(design: _Design, amplitudes: FloatArray, offset_fraction: float) -> dict[int, float]:
    """Tilt knots of the structural curves (ends and apexes), degrees.

    The knots are fixed up to a common offset; the offset is placed at ``offset_fraction`` of its
    admissible range, in which every end vertebra that is a tilt minimum has a negative tilt and
    every maximum a positive one (each curve crosses the vertical, as a balanced curve does).
    """
    rel: dict[int, float] = {design.curves[0].upper: 0.0}
    ends: list[tuple[int, int]] = [(design.curves[0].upper, -design.curves[0].rising)]
    for c, amp in zip(design.curves, amplitudes, strict=True):
        rel[c.apex] = rel[c.upper] + c.rising * amp * c.apex_fraction
        rel[c.lower] = rel[c.upper] + c.rising * amp
        ends.append((c.lower, c.rising))
    margin = 0.15 * float(np.min(amplitudes))
    lo, hi = -np.inf, np.inf
    for index, sign in ends:  # sign +1: a maximum, needs rel + o >= margin
        if sign > 0:
            lo = max(lo, margin - rel[index])
        else:
            hi = min(hi, -margin - rel[index])
    offset = lo + offset_fraction * (hi - lo) if lo <= hi else 0.5 * (lo + hi)
    return {i: v + offset for i, v in rel.items()}


def _frontal_angles(design: _Design, amplitudes: FloatArray, params: dict[str, float]) -> FloatArray:
    """Frontal tangent angles φ (17,), degrees: PCHIP in arc length through the curve knots and
    the T1 / L5 knots, which keep the fractions ``top`` / ``bottom`` of the tilt of the
    neighbouring end vertebra."""
    knots = _end_tilts(design, amplitudes, params["offset"])
    first, last = design.curves[0].upper, design.curves[-1].lower
    if first > 0:
        knots[0] = params["top"] * knots[first]
    if last < N_LEVELS - 1:
        knots[N_LEVELS - 1] = params["bottom"] * knots[last]
    s = np.concatenate([[0.0], np.cumsum(design.ds)])
    idx = np.array(sorted(knots))
    return np.asarray(PchipInterpolator(s[idx], [knots[i] for i in idx])(s), dtype=float)


def _balance(design: _Design, amplitudes: FloatArray, beta: FloatArray) -> dict[str, float]:
    """Shape parameters that put L5 at ``balance_x`` from T1 in x.

    Starting from the drawn values, one parameter at a time is solved for within a range, in this
    order, until balance is reached: the kept fraction of one compensatory piece in 0–0.6, the
    offset fraction in 0.25–0.75, the other kept fraction in ``KEPT_FRACTION_RANGE``, the first
    again in that range, the offset fraction in 0.1–0.9. A parameter whose range cannot reach
    balance is left at its best end.
    """
    params = {"offset": design.offset_fraction, "top": design.kept_fraction, "bottom": design.kept_fraction}
    has = {"top": design.curves[0].upper > 0, "bottom": design.curves[-1].lower < N_LEVELS - 1}
    a, b = ("bottom", "top") if design.balance_at_bottom else ("top", "bottom")
    steps = [
        (a, (0.0, 0.6)),
        ("offset", (0.25, 0.75)),
        (b, KEPT_FRACTION_RANGE),
        (a, KEPT_FRACTION_RANGE),
        ("offset", (0.1, 0.9)),
    ]

    def gap(value: float, name: str) -> float:
        trial = dict(params)
        trial[name] = value
        phi = _frontal_angles(design, amplitudes, trial)
        return float(centreline_from_angles(design.ds, phi, beta)[-1, 0] - design.balance_x)

    for name, (lo, hi) in steps:
        if name != "offset" and not has[name]:
            continue
        g_lo, g_hi = gap(lo, name), gap(hi, name)
        if g_lo * g_hi <= 0:
            params[name] = float(brentq(gap, lo, hi, args=(name,), xtol=1e-9))
            break
        params[name] = lo if abs(g_lo) < abs(g_hi) else hi
    return params


def _angles(design: _Design, amplitudes: FloatArray, sagittal: tuple[float, float]) -> tuple[FloatArray, FloatArray]:
    """Frontal and sagittal angles (17,) each, balanced in x and y."""
    beta = sagittal_profile_deg(*sagittal)
    params = {"offset": design.offset_fraction, "top": design.kept_fraction, "bottom": design.kept_fraction}
    for _ in range(3):
        phi = _frontal_angles(design, amplitudes, params)
        beta = beta + balance_offset_deg(design.ds, phi, beta, 1, design.balance_y)
        params = _balance(design, amplitudes, beta)
    return _frontal_angles(design, amplitudes, params), beta


def _frontal_deviation(positions: FloatArray, upper: int, lower: int) -> FloatArray:
    """Signed frontal distance (mm, + toward patient left) of vertebrae upper..lower from their chord."""
    xz = positions[:, [0, 2]]
    c = xz[lower] - xz[upper]
    c = c / np.linalg.norm(c)
    n = np.array([-c[1], c[0]])
    if n[0] < 0:
        n = -n
    return np.asarray((xz[upper : lower + 1] - xz[upper]) @ n, dtype=float)


def _axial_rotation_deg(design: _Design, positions: FloatArray) -> FloatArray:
    """ψ (17,), degrees, toward the convexity of every curve of the spine, compensatory ones too.

    The curves are those of the spine without axial rotation (turning points of its frontal tilt,
    ``measures.tilt_turning_points``; T1 and L5 close the first and last pieces). On each, ψ is
    gain·(frontal deviation from the chord of its end vertebrae), with the gain that turns the
    apex (largest deviation) by r·Cobb, r being the ratio of the designed curve it overlaps most.
    """
    tilt = frontal_tilt_deg(frames_from_centreline(positions))
    ends = sorted({0, N_LEVELS - 1, *tilt_turning_points(tilt)})
    psi = np.zeros(N_LEVELS)
    for upper, lower in itertools.pairwise(ends):
        if lower - upper < 2:
            continue
        ratio = max(design.curves, key=lambda c: min(c.lower, lower) - max(c.upper, upper)).rotation_ratio
        dev = _frontal_deviation(positions, upper, lower)
        cobb = abs(float(tilt[lower] - tilt[upper]))
        psi[upper : lower + 1] = ratio * cobb * dev / max(float(np.max(np.abs(dev))), 1e-6)
    return psi


def _build(design: _Design, amplitudes: FloatArray, sagittal: tuple[float, float]) -> tuple[FloatArray, FloatArray]:
    phi, beta = _angles(design, amplitudes, sagittal)
    positions = centreline_from_angles(design.ds, phi, beta)
    psi = _axial_rotation_deg(design, positions)
    return positions, frames_from_centreline(positions, np.radians(psi))


def _match(curves: list[FrontalCurve], c: _Curve) -> FrontalCurve:
    """The measured curve that overlaps the designed one most (ties: the larger angle)."""

    def overlap(m: FrontalCurve) -> tuple[int, float]:
        return min(m.lower, c.lower) - max(m.upper, c.upper), m.angle_deg

    best = max(curves, key=overlap, default=None)
    if best is None or overlap(best)[0] <= 0:
        raise RuntimeError(f"designed curve {LEVELS[c.upper]}–{LEVELS[c.lower]} not found in the measured spine")
    return best


def generate_spine(seed: int, kind: str | None = None) -> SyntheticSpine:
    """One synthetic spine, deterministic for (seed, kind); kind drawn from ``KINDS`` if None."""
    rng = np.random.default_rng(seed)
    if kind is None:
        kind = KINDS[int(rng.integers(len(KINDS)))]
    design, kyphosis, lordosis, size = _design(rng, kind)
    targets = np.array([c.target_deg for c in design.curves])
    amplitudes = targets.copy()
    sag_targets = np.array([kyphosis, lordosis])
    sagittal = sag_targets.copy()
    best: tuple[float, FloatArray, FloatArray, list[FrontalCurve], FloatArray] | None = None
    # Per-curve exponent of the multiplicative update, halved when the error changes sign, so that
    # a steep response (an end vertebra switching level) does not make the iteration oscillate.
    exponent = np.ones(len(targets))
    previous = np.zeros(len(targets))
    for _ in range(CALIBRATION_ITERATIONS):
        positions, rotations = _build(design, amplitudes, (float(sagittal[0]), float(sagittal[1])))
        matched = [_match(frontal_curves(positions, rotations, min_cobb_deg=1.0), c) for c in design.curves]
        measured = np.array([m.angle_deg for m in matched])
        k4, _, lo = kyphosis_lordosis_deg(rotations)
        sag_measured = np.array([k4, lo])
        error = max(float(np.max(np.abs(measured - targets))), float(np.max(np.abs(sag_measured - sag_targets))))
        if best is None or error < best[0]:
            best = (error, positions, rotations, matched, sag_measured)
        if error < CALIBRATION_TOLERANCE_DEG:
            break
        sign = np.sign(measured - targets)
        exponent[sign * previous < 0] *= 0.5
        previous = sign
        amplitudes = amplitudes * (targets / measured) ** exponent
        sagittal = sagittal + sag_targets - sag_measured
    assert best is not None
    _, positions, rotations, matched, sag_measured = best
    return SyntheticSpine(
        positions=positions,
        rotations=rotations,
        kind=kind,
        cobb_target_deg=tuple(float(t) for t in targets),
        kyphosis_deg=float(sag_measured[0]),
        lordosis_deg=float(sag_measured[1]),
        seed=int(seed),
        ends=tuple((LEVELS[m.upper], LEVELS[m.lower]) for m in matched),
        apexes=tuple(LEVELS[m.apex] for m in matched),
        convexity=tuple("right" if c.rising > 0 else "left" for c in design.curves),
        apical_rotation_ratio=tuple(c.rotation_ratio for c in design.curves),
        size_scale=size,
        ds=design.ds,
    )


def generate_spines(n: int, seed: int = 0) -> list[SyntheticSpine]:
    """``n`` synthetic spines, deterministic for ``seed``. The kinds cycle through ``KINDS``
    (thoracic, thoracolumbar, lumbar, double), so any n >= 4 has single and double curves;
    spine k has its own seed drawn from ``numpy.random.SeedSequence(seed)``."""
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    seeds = [int(s) for s in np.random.SeedSequence(seed).generate_state(n)] if n else []
    return [generate_spine(s, KINDS[k % len(KINDS)]) for k, s in enumerate(seeds)]
