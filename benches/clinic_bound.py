"""``spine bench clinic-bound``: how close the films let any reconstruction come.

The 3D error of ``spine bench clinic`` removes only the global translation, so a rotation of the
whole spine that the films leave undetermined counts in full. This command computes, per spine and
case, the error that such a rotation causes for an **oracle**: an estimator that knows the spine's
exact shape and size and only has to place it. From the same simulated films
(``clinic_films.simulate_series``, same seed and noise as ``spine bench clinic``) it estimates

* ω, the spine's rotation vector (rad), about its centroid;
* per film: τ (3), the spine's translation relative to the film (mm; on a weak-perspective film
  its component along the beam has no effect and is left out), μ, the log of the film's
  magnification about its central ray, and ψ, the film's in-plane turn (rad; 0 on the PA by the
  engine's convention),

with the engine's priors (``Priors``): μ_PA ~ N(0, (0.035/1.125)²) (``clinical.PA_MAGNIFICATION_PRIOR``)
unless the geometry is given (μ then known), ψ_lateral ~ N(0, σ_ψ²), the component of τ along the
beam of a perspective film ~ N(0, 30²) (``fit.types.DEPTH_PRIOR_SD_MM``), and ω ~ N(0, diag σ_ω²).

Linearised at the truth θ = 0, the images are p(θ) ≈ p(0) + Jθ with J the Jacobian of
``clinic_films.Film.image`` (central differences, step 10⁻⁶), so the posterior of θ is Gaussian
with covariance Σ = (JᵀJ/σ² + P)⁻¹ (σ: the landmark noise SD, P: the priors' precisions); Σ_ω is
its rotation block. The posterior mean is then the best estimate under every symmetric convex loss
(Anderson's lemma), and its error in the bench's metric is

    bound = E[ mean_i |(R(δω) − I)(t_i − t̄)| ],   δω ~ N(0, Σ_ω)   (mm; Monte Carlo),

which no estimator that knows less (the shape) can beat on average, up to the linearisation.
Three prior settings are reported: the engine's (σ_ψ = 2°, ``fit.types.FILM_TURN_PRIOR_SD_DEG``, and
σ_ω of its standing orientation, ``engine_orientation_sd_deg``), then σ_ψ = the RMS of the bench's
own turns (|ψ| uniform in ``clinic_films.LATERAL_TURN_DEG``: the best Gaussian prior for these
films), then that with σ_ω the spread of the VerSe **dev** spines' orientations instead
(``orientation_spread``; the CT frames the truths come in).

Beside the bound, for comparison: the engine's own result on the same films (``clinic.run_one``:
3D error, shape error and the RMS of its best rotation about x, y, z) and a floor estimate, the
bound's rotations added to the engine's error vectors in the paper's case (f), T1/L5 given and
the films calibrated (more information than any of (a)–(e)): E[mean_i |e_i^(f) + (R(δω) − I)(t_i − t̄)|].
That one is an estimate, not a bound: it uses the engine's shape errors.

``--seeds N`` draws the films with N noise seeds and pools the figures (``pooled``): one seed's
spines give the engine's rotation RMS to within about ±30 %, too coarse to judge its ratio to the
oracle's SD; each seed's is kept beside the pooled one.

**What case (b)'s lateral film leaves unseen** (its row's ``unseen_top_shape``): the lateral film
from T4 down does not show T1–T3, whose depths the PA film's foreshortening and a prior must give;
the foreshortening reads an inclination only as well as the segment's length is known. An oracle
that knows the shape but the sagittal bends at T4, T3 and T2 and the lengths of the three chords
above T4 (``deformed_top``; prior: their covariance over VerSe dev, lengths relative to the
profile's rest lengths scaled to the spine's, ``top_prior_covariance``) places and deforms the spine
under the engine's priors as above; the posterior of those six, drawn, gives the shape error (after
the best rigid motion, ``shape_errors``) that no estimator knowing less avoids, and, added to the
engine's own case (a) errors on the same spine (T1–T3 carrying T4's), a floor estimate of case
(b)'s shape error. That oracle's rotation is given twice: its posterior SD, and the RMS of the best
rotation that aligns its drawn result on the truth (``unseen_top_rotation``), which is how the
engine's rotation is measured: a top of the wrong shape turns that alignment too.

**What placing the spine needs of its chords' lengths** (every row's ``chord_lengths_unknown``): an
oracle that knows the shape but the lengths of the chords T1–T2 … L3–L4 (``CHORD_JOINTS``, stretched
by ``stretched``; prior: their covariance over VerSe dev relative to the profile's proportions,
``chord_prior_covariance``) places the spine on the same films; its rotation SD under the engine's
priors and under the best Gaussian priors, and aligned as the engine's. A perspective PA film sees a
lean on its rows through the sagittal curve's depths, against the rows' spacing that the chords'
lengths set, so this oracle leans less surely than the bound's in (c).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from benches.clinic import run_one, verse_truths
from benches.clinic_films import CASES, LATERAL_TURN_DEG, Case, Film, FloatArray, Series, Truth, simulate_series
from benches.prior import relative_segment_lengths
from benches.report import format_table, write_json
from spine_engine.anatomy import load_profile, population_prior, rest_model
from spine_engine.clinical import PA_MAGNIFICATION_PRIOR
from spine_engine.fit.types import DEPTH_PRIOR_SD_MM, FILM_TURN_PRIOR_SD_DEG
from spine_engine.levels import LEVELS, N_LEVELS

TARGETS_MM = {"a": 1.2, "b": 2.0, "c": 1.5}
"""The clinic's targets for the mean 3D error on VerSe test, 1 mm noise, no boundary."""
BOUND_CASES = "abcde"
"""The cases without boundary ((f) has T1/L5 given: its rotation is known)."""
FILM_PARAMETERS = 5
"""τ (3), μ, ψ per film."""
STEP = 1e-6
"""Central-difference step of the Jacobian (mm and rad)."""


@dataclass(frozen=True)
class Priors:
    """The oracle's Gaussian priors (module docstring)."""

    film_turn_sd_deg: float = FILM_TURN_PRIOR_SD_DEG
    """σ_ψ of the lateral film's turn."""
    orientation_sd_deg: tuple[float, float, float] | None = None
    """σ_ω about x, y, z of the spine's rotation, or None (no prior)."""


def bench_turn_rms_deg() -> float:
    """RMS of the bench's film turns, |ψ| ~ U(a, b): √((b³ − a³) / (3(b − a))), degrees."""
    a, b = LATERAL_TURN_DEG
    return float(np.sqrt((b**3 - a**3) / (3.0 * (b - a))))


def orientation_spread(truths: Sequence[Truth], rounds: int = 5) -> tuple[float, float, float]:
    """SD about x, y, z (degrees) of the rotations that align each centred spine on the mean shape
    (Kabsch, the mean re-estimated ``rounds`` times): how differently the spines sit in their frames."""
    centred = [t.positions - t.positions.mean(axis=0) for t in truths]
    mean = np.mean(centred, axis=0)
    vectors = np.zeros((len(centred), 3))
    for _ in range(rounds):
        turns = [Rotation.align_vectors(mean, c)[0] for c in centred]
        mean = np.mean([q.apply(c) for q, c in zip(turns, centred, strict=True)], axis=0)
        vectors = np.array([q.as_rotvec(degrees=True) for q in turns])
    sd = vectors.std(axis=0)
    return float(sd[0]), float(sd[1]), float(sd[2])


def _films(series: Series, case: Case) -> list[tuple[Film, int]]:
    """(film, first level on it) of the films the case sends."""
    films = [(series.pa, 0)]
    if case.lateral_from is not None:
        films.append((series.lateral, case.lateral_from))
    return films


def bent(positions: FloatArray, beta: FloatArray, joints: Sequence[int]) -> FloatArray:
    """The positions (N, 3) with the vertebrae above each joint J (``joints``, lowest first) turned
    by β_J (rad) about the left–right axis (x) through r_J: a sagittal bend at J."""
    out = np.array(positions, dtype=float)
    for angle, j in zip(beta, joints, strict=True):
        c, s = np.cos(angle), np.sin(angle)
        rel = out[:j] - out[j]
        out[:j, 1] = out[j, 1] + c * rel[:, 1] - s * rel[:, 2]
        out[:j, 2] = out[j, 2] + s * rel[:, 1] + c * rel[:, 2]
    return out


def stretched(positions: FloatArray, stretch: FloatArray, joints: Sequence[int]) -> FloatArray:
    """The positions (..., N, 3) with the chord from each joint J up to J − 1 lengthened by the fraction
    ``stretch``[..., k] (J = ``joints``[k], lowest first), the vertebrae above it carried along; leading
    axes of ``positions`` and ``stretch`` are draws, broadcast together."""
    fractions = np.asarray(stretch, dtype=float)
    out = np.array(np.broadcast_to(positions, fractions.shape[:-1] + np.shape(positions)), dtype=float)
    for k, j in enumerate(joints):
        out[..., :j, :] += fractions[..., k, None, None] * (out[..., j - 1, :] - out[..., j, :])[..., None, :]
    return out


def deformed_top(positions: FloatArray, params: FloatArray, joints: Sequence[int]) -> FloatArray:
    """``stretched`` by params[k:] then ``bent`` by params[:k], k = len(joints): the top of the spine
    with other bends and chord lengths at the joints."""
    k = len(joints)
    return bent(stretched(positions, params[k:], joints), params[:k], joints)


def simulated_images(
    theta: FloatArray, truth: Truth, films: Sequence[tuple[Film, int]], perspective: bool,
    joints: Sequence[int] = (),
) -> FloatArray:
    """The films' noise-free images (detector mm, flattened) of the truth moved by θ (module
    docstring): r = R(ω)(t − t̄) + t̄ + τ_k on film k, the image scaled by e^μ_k about the central
    ray and the film turned by ψ_k more; with ``joints``, θ ends with a sagittal bend β_J at each and
    the stretch of the chord above each (``deformed_top``), applied before the rigid motion."""
    t = truth.positions
    if joints:
        t = deformed_top(t, theta[len(theta) - 2 * len(joints) :], joints)
    centre = t.mean(axis=0)
    moved = (t - centre) @ Rotation.from_rotvec(theta[:3]).as_matrix().T + centre
    out = []
    for k, (film, first) in enumerate(films):
        tau, mu, psi = np.split(theta[3 + FILM_PARAMETERS * k : 3 + FILM_PARAMETERS * (k + 1)], [3, 4])
        turned = dataclasses.replace(film, turn_deg=film.turn_deg + float(np.degrees(psi[0])))
        image = turned.image(moved[first:] + tau, perspective)
        out.append(((image - film.central_ray) * np.exp(mu[0]) + film.central_ray).ravel())
    return np.concatenate(out)


def image_jacobian(
    truth: Truth, films: Sequence[tuple[Film, int]], perspective: bool, joints: Sequence[int] = (),
    bends: bool = True,
) -> FloatArray:
    """∂p/∂θ at θ = 0 by central differences (``STEP``), (2·landmarks, 3 + 5·films + 2·joints); without
    the joints' bend columns when ``bends`` is False (3 + 5·films + joints: the bends known)."""
    first_bend = 3 + FILM_PARAMETERS * len(films)
    n = first_bend + 2 * len(joints)
    skipped = range(first_bend, first_bend + (0 if bends else len(joints)))
    columns = []
    for j in (j for j in range(n) if j not in skipped):
        step = np.zeros(n)
        step[j] = STEP
        plus = simulated_images(step, truth, films, perspective, joints)
        minus = simulated_images(-step, truth, films, perspective, joints)
        columns.append((plus - minus) / (2.0 * STEP))
    return np.stack(columns, axis=1)


def rotation_covariance(series: Series, case: Case, priors: Priors) -> FloatArray:
    """Σ_ω (3, 3), rad²: the rotation block of (JᵀJ/σ² + P)⁻¹ over the parameters the case leaves
    free (module docstring)."""
    return posterior_covariance(series, case, priors)[:3, :3]


def posterior_covariance(
    series: Series, case: Case, priors: Priors, joints: Sequence[int] = (), joint_covariance: FloatArray | None = None,
    bends: bool = True, jacobian: FloatArray | None = None,
) -> FloatArray:
    """(JᵀJ/σ² + P)⁻¹ over the parameters the case leaves free, in θ's order (ω first, the joints'
    bends and stretches last, ``simulated_images``), rad² and mm²; ``joint_covariance`` is their prior
    covariance, (2·len(joints))², or len(joints)² of the stretches alone when ``bends`` is False (the
    bends then known: their columns left out). ``jacobian``: J (``image_jacobian`` of the case's films
    with these joints and ``bends``) when already computed for another prior setting; it does not
    depend on P."""
    films = _films(series, case)
    J = image_jacobian(series.truth, films, case.perspective, joints, bends) if jacobian is None else jacobian
    precision = J.T @ J / series.noise_mm**2
    if joints:
        assert joint_covariance is not None
        m = len(joint_covariance)
        precision[-m:, -m:] += np.linalg.inv(joint_covariance)
    prior = np.zeros(J.shape[1])
    free = np.ones(J.shape[1], dtype=bool)
    if priors.orientation_sd_deg is not None:
        prior[:3] = 1.0 / np.radians(np.asarray(priors.orientation_sd_deg)) ** 2
    for k, (film, _) in enumerate(films):
        base = 3 + FILM_PARAMETERS * k
        beam_axis = base + int(np.argmax(np.abs(film.beam)))
        if case.perspective:
            prior[beam_axis] = 1.0 / DEPTH_PRIOR_SD_MM**2
        else:
            free[beam_axis] = False  # a weak perspective does not see it
        if case.perspective and case.acquisition:
            free[base + 3] = False  # SID and SOD given: the magnification is known
        elif k == 0:
            prior[base + 3] = 1.0 / (PA_MAGNIFICATION_PRIOR[1] / PA_MAGNIFICATION_PRIOR[0]) ** 2
        if k == 0:
            free[base + 4] = False  # the PA's turn is 0 by convention
        else:
            prior[base + 4] = 1.0 / np.radians(priors.film_turn_sd_deg) ** 2
    keep = np.flatnonzero(free)
    return np.asarray(np.linalg.inv(precision[np.ix_(keep, keep)] + np.diag(prior[keep])))


UNSEEN_TOP_JOINTS = (3, 2, 1)
"""T4, T3, T2 (lowest first, ``bent``): a sagittal bend at each moves vertebrae that case (b)'s lateral
film (T4–L5) does not show, T1–T3."""


def top_parameters(positions: FloatArray, rest_ds: FloatArray, joints: Sequence[int] = UNSEEN_TOP_JOINTS) -> FloatArray:
    """(2·len(joints),): the sagittal bend at each joint J, a_{J−1} − a_J (rad) with a_c = atan2(Δy, −Δz)
    the sagittal inclination of the chord from vertebra c to c + 1 (a bend β at J, ``bent``, adds β
    to it), then the chord from J − 1 to J over its rest length scaled to the spine's T1–L5 length,
    minus 1 (``stretched``'s fraction). ``rest_ds`` (N − 1,): the rest chord lengths."""
    d = np.diff(np.asarray(positions, dtype=float), axis=0)
    a = np.arctan2(d[:, 1], -d[:, 2])
    relative = relative_segment_lengths(positions, rest_ds)
    return np.array([a[j - 1] - a[j] for j in joints] + [relative[j - 1] for j in joints])


def top_prior_covariance(truths: Sequence[Truth]) -> FloatArray:
    """(6, 6): the covariance over ``truths`` (VerSe dev) of ``top_parameters`` at ``UNSEEN_TOP_JOINTS``
    (rad², and fractions² for the chords' lengths against the profile's rest lengths), the oracle's
    prior on what the lateral film of case (b) does not see. A prior that conditions on the rest of
    the spine predicts the bends no better on dev (``spine bench prior --coupling``)."""
    rest_ds = rest_model(load_profile()).ds
    return np.asarray(np.cov(np.array([top_parameters(t.positions, rest_ds) for t in truths]).T))


def best_rotations(moved: FloatArray, truth: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(Q (draws, 3, 3), m, t): the rotation Q that best aligns each centred configuration m (draws,
    N, 3) of ``moved`` on the centred ``truth`` t (N, 3), Q m_i ≈ t_i (Kabsch, by batched SVD)."""
    t = truth - truth.mean(axis=0)
    m = moved - moved.mean(axis=1, keepdims=True)
    u, _, vt = np.linalg.svd(np.einsum("dni,nj->dij", m, t))
    d = np.sign(np.linalg.det(u @ vt))
    u[:, :, -1] *= d[:, None]
    return np.swapaxes(u @ vt, 1, 2), m, t


def shape_errors(moved: FloatArray, truth: FloatArray) -> FloatArray:
    """(draws,) mean over vertebrae of |R m_i + c − t_i| after the best rigid motion (``best_rotations``)
    of each configuration ``moved`` (draws, N, 3) onto ``truth`` (N, 3), mm."""
    q, m, t = best_rotations(moved, truth)
    aligned = np.einsum("dij,dnj->dni", q, m)
    return np.asarray(np.linalg.norm(aligned - t[None], axis=2).mean(axis=1))


def aligned_rotation_rms(
    truth: FloatArray, posterior: FloatArray, deform: Callable[[FloatArray, FloatArray], FloatArray], draws: int,
    seed: int,
) -> FloatArray:
    """(3,) RMS over ``draws`` of the best rotation (degrees, about x, y, z) that aligns an oracle's
    drawn result on the truth, measured as the engine's (``clinic.rigid_difference``): (ω, shape
    parameters) drawn jointly from ``posterior`` (their block of ``posterior_covariance``, ω first), the
    spine deformed by ``deform``(truth, parameters (draws, k)) → (draws, N, 3), turned by ω about its
    centroid, then aligned. A shape of the wrong form turns the alignment too, as the engine's own
    shape error turns its."""
    draw = np.random.default_rng(seed).multivariate_normal(np.zeros(len(posterior)), posterior, draws)
    turns = Rotation.from_rotvec(draw[:, :3]).as_matrix()
    shapes = deform(truth, draw[:, 3:])
    centred = shapes - shapes.mean(axis=1, keepdims=True)
    q, _, _ = best_rotations(np.einsum("dij,dnj->dni", turns, centred), truth)
    return np.asarray(np.sqrt(np.mean(np.square(Rotation.from_matrix(q).as_rotvec(degrees=True)), axis=0)))


def unseen_top_rotation(truth: FloatArray, posterior: FloatArray, draws: int, seed: int) -> FloatArray:
    """``aligned_rotation_rms`` of the oracle of case (b)'s unseen top: its bends and stretches at
    ``UNSEEN_TOP_JOINTS`` (``deformed_top``)."""
    return aligned_rotation_rms(
        truth, posterior, lambda t, p: np.array([deformed_top(t, q, UNSEEN_TOP_JOINTS) for q in p]), draws, seed
    )


def unseen_top_shape(truth: FloatArray, top_posterior: FloatArray, engine_a_errors: FloatArray | None,
                     draws: int, seed: int) -> tuple[float, float]:
    """(bound, floor estimate), mm, of the shape error that T1–T3's unseen sagittal bends and chord
    lengths leave in case (b) (module docstring): ``draws`` of their posterior ``top_posterior``
    (the last six rows and columns of ``posterior_covariance`` with ``UNSEEN_TOP_JOINTS``) deform the
    spine ``truth`` (``deformed_top``), compared after the best rigid motion. The floor estimate adds
    the engine's case (a) errors on the same spine (a full lateral film) before the comparison, T1–T3
    carrying T4's (the top hangs off T4; NaN without them)."""
    joints = UNSEEN_TOP_JOINTS
    params = np.random.default_rng(seed).multivariate_normal(np.zeros(len(top_posterior)), top_posterior, draws)
    moved = np.array([deformed_top(truth, p, joints) for p in params])
    bound = float(shape_errors(moved, truth).mean())
    if engine_a_errors is None:
        return bound, float("nan")
    carried = np.array(engine_a_errors, dtype=float)
    carried[: joints[0]] = carried[joints[0]]
    return bound, float(shape_errors(moved + carried[None], truth).mean())


def mean_error(errors: FloatArray) -> float:
    """mean over draws and vertebrae of |e| for errors (draws, N, 3), mm."""
    return float(np.linalg.norm(errors, axis=2).mean())


def rotation_errors(covariance: FloatArray, centred: FloatArray, draws: int, seed: int) -> FloatArray:
    """(draws, N, 3) (R(δω) − I)(t_i − t̄) for δω ~ N(0, Σ_ω), mm."""
    rng = np.random.default_rng(seed)
    omegas = rng.multivariate_normal(np.zeros(3), covariance, draws)
    turns = Rotation.from_rotvec(omegas).as_matrix()
    return np.asarray(np.einsum("dij,nj->dni", turns, centred) - centred[None])


def expected_error(covariance: FloatArray, centred: FloatArray, draws: int, seed: int) -> float:
    """E[mean_i |(R(δω) − I)(t_i − t̄)|], δω ~ N(0, Σ_ω), mm (Monte Carlo, ``draws``)."""
    return mean_error(rotation_errors(covariance, centred, draws, seed))


@dataclass
class SpineBound:
    """The bound and the engine's figures for one spine in one case."""

    bounds_mm: dict[str, float]
    rotation_sd_deg: FloatArray
    """(3,) √diag Σ_ω under the engine's priors, degrees."""
    engine_error_mm: float
    engine_shape_mm: float
    engine_rotation_deg: FloatArray
    floor_mm: float


def bound_one(series: Series, case: Case, settings: dict[str, Priors], paper_errors: FloatArray | None,
              draws: int, seed: int) -> SpineBound:
    """The oracle's bound under each prior setting, the engine's result on the same films and the
    floor estimate (module docstring) for one spine."""
    centred = series.truth.positions - series.truth.positions.mean(axis=0)
    J = image_jacobian(series.truth, _films(series, case), case.perspective)
    covariances = {name: posterior_covariance(series, case, p, jacobian=J)[:3, :3] for name, p in settings.items()}
    samples = {name: rotation_errors(c, centred, draws, seed) for name, c in covariances.items()}
    outcome = run_one(series, case)
    floor = float("nan") if paper_errors is None else mean_error(samples["engine_priors"] + paper_errors[None])
    return SpineBound(
        bounds_mm={name: mean_error(s) for name, s in samples.items()},
        rotation_sd_deg=np.degrees(np.sqrt(np.diag(covariances["engine_priors"]))),
        engine_error_mm=float(outcome.per_level_mm.mean()) if outcome.ok else float("nan"),
        engine_shape_mm=outcome.shape_error_mm,
        engine_rotation_deg=outcome.rotation_error_deg,
        floor_mm=floor,
    )


def _rms(vectors: Sequence[FloatArray]) -> list[float]:
    """Component-wise RMS of (3,) vectors, NaN (a failed fit) left out."""
    return np.sqrt(np.nanmean(np.square(vectors), axis=0)).round(3).tolist()


def engine_case_errors(series: Series, key: str) -> FloatArray | None:
    """The engine's (17, 3) error vectors in case ``key`` on these films (None if it failed)."""
    outcome = run_one(series, CASES[key])
    return outcome.error_vectors if outcome.ok else None


def unseen_top_row(series: Sequence[Series], priors: Priors, top_covariance: FloatArray, draws: int,
                   seed: int) -> dict[str, Any]:
    """Case (b)'s ``unseen_top_shape`` over the spines: the bound and floor estimate (means, mm), the
    prior's and the posterior's SDs of the bends (degrees) and chord lengths (per cent), and the
    rotation SD of that oracle, which does not know T1–T3 (degrees; RMS over the spines)."""
    k = len(UNSEEN_TOP_JOINTS)
    covariances = [posterior_covariance(s, CASES["b"], priors, UNSEEN_TOP_JOINTS, top_covariance) for s in series]
    block = np.r_[0:3, len(covariances[0]) - 2 * k : len(covariances[0])]
    found = [unseen_top_shape(s.truth.positions, c[-2 * k :, -2 * k :], engine_case_errors(s, "a"), draws, seed)
             for s, c in zip(series, covariances, strict=True)]
    scale = np.concatenate([np.full(k, np.degrees(1.0)), np.full(k, 100.0)])
    posterior = [scale * np.sqrt(np.diag(c[-2 * k :, -2 * k :])) for c in covariances]
    prior = scale * np.sqrt(np.diag(top_covariance))
    return {
        "joints": ["T4", "T3", "T2"],
        "prior_sd": {"bend_deg": prior[:k].round(3).tolist(), "chord_length_pct": prior[k:].round(3).tolist()},
        "posterior_sd": {"bend_deg": _rms([p[:k] for p in posterior]),
                         "chord_length_pct": _rms([p[k:] for p in posterior])},
        "bound_mm": float(np.mean([f[0] for f in found])),
        "floor_estimate_mm": float(np.nanmean([f[1] for f in found])),
        "oracle_rotation_sd_deg_xyz": _rms([np.degrees(np.sqrt(np.diag(c[:3, :3]))) for c in covariances]),
        "oracle_aligned_rotation_rms_deg_xyz": _rms(
            [
                unseen_top_rotation(s.truth.positions, c[np.ix_(block, block)], draws, seed)
                for s, c in zip(series, covariances, strict=True)
            ]
        ),
    }


CHORD_JOINTS = tuple(range(N_LEVELS - 2, 0, -1))
"""L4, L3, …, T2 (lowest first, ``stretched``): a stretch at joint J lengthens the chord from J up to
J − 1, so these fifteen stretches are the lengths of the chords T1–T2 … L3–L4 that the oracle of
``chord_lengths_row`` does not know. L4–L5's is kept: the chords' lengths relative to the profile's
proportions at the spine's own T1–L5 length (``relative_segment_lengths``) sum to zero weighted by
the rest lengths, so fifteen of them carry their whole spread."""


def chord_prior_covariance(truths: Sequence[Truth]) -> FloatArray:
    """(15, 15): the covariance over ``truths`` (VerSe dev) of the relative lengths of the chords that
    ``CHORD_JOINTS`` stretch (fractions²), in their order: the prior of ``chord_lengths_row``'s oracle."""
    rest_ds = rest_model(load_profile()).ds
    relative = np.array([relative_segment_lengths(t.positions, rest_ds) for t in truths])
    return np.asarray(np.cov(relative[:, [j - 1 for j in CHORD_JOINTS]].T))


def chord_lengths_row(series: Sequence[Series], case: Case, settings: dict[str, Priors], chord_covariance: FloatArray,
                      draws: int, seed: int) -> dict[str, Any]:
    """What placing the spine needs of its chords' lengths: the rotation of an oracle that knows the
    spine's shape but the lengths of the chords T1–T2 … L3–L4 (``CHORD_JOINTS``; prior
    ``chord_covariance``), on the same films as the bound's oracle: its posterior SD about x, y and z
    under the engine's priors and under the best Gaussian priors (``prior_settings``), and the RMS of
    the best rotation aligning its drawn result on the truth under the engine's priors
    (``aligned_rotation_rms``), degrees, RMS over the spines. A lean seen through the depths of the
    sagittal curve on a film's rows (docs/accuracy.md, "What the films can tell") is read only as well
    as the rows' spacing, the chords' lengths, is known."""
    k = len(CHORD_JOINTS)
    jacobians = [image_jacobian(s.truth, _films(s, case), case.perspective, CHORD_JOINTS, bends=False) for s in series]
    covariances = {
        name: [posterior_covariance(s, case, settings[name], CHORD_JOINTS, chord_covariance, bends=False, jacobian=J)
               for s, J in zip(series, jacobians, strict=True)]
        for name in ("engine_priors", "bench_turn_and_orientation")
    }
    engine = covariances["engine_priors"]
    block = np.r_[0:3, len(engine[0]) - k : len(engine[0])]
    return {
        "chords": f"{LEVELS[0]}-{LEVELS[1]} to {LEVELS[N_LEVELS - 3]}-{LEVELS[N_LEVELS - 2]}",
        "prior_sd_pct": (100.0 * np.sqrt(np.diag(chord_covariance))).round(2).tolist(),
        "oracle_rotation_sd_deg_xyz": _rms([np.degrees(np.sqrt(np.diag(c[:3, :3]))) for c in engine]),
        "oracle_rotation_sd_deg_xyz_best_priors": _rms(
            [np.degrees(np.sqrt(np.diag(c[:3, :3]))) for c in covariances["bench_turn_and_orientation"]]
        ),
        "oracle_aligned_rotation_rms_deg_xyz": _rms(
            [
                aligned_rotation_rms(s.truth.positions, c[np.ix_(block, block)],
                                     lambda t, p: stretched(t, p, CHORD_JOINTS), draws, seed)
                for s, c in zip(series, engine, strict=True)
            ]
        ),
    }


def run(truths: Sequence[Truth], cases: Sequence[Case], settings: dict[str, Priors], noise_mm: float,
        seed: int, draws: int, top_covariance: FloatArray | None = None,
        chord_covariance: FloatArray | None = None) -> list[dict[str, Any]]:
    """One summary row per case: means over the spines (RMS for angles); case (b)'s row also has the
    shape its lateral film leaves unseen (``unseen_top_row``) when ``top_covariance`` is given, and
    every row the rotation of an oracle that does not know the chords' lengths (``chord_lengths_row``)
    when ``chord_covariance`` is."""
    series = [simulate_series(t, noise_mm, seed) for t in truths]
    paper = [engine_case_errors(s, "f") for s in series]
    rows = []
    for case in cases:
        found = [bound_one(s, case, settings, p, draws, seed) for s, p in zip(series, paper, strict=True)]
        row = {
            "case": case.key,
            "title": case.title,
            "spines": len(found),
            "target_mm": TARGETS_MM.get(case.key),
            "bound_mm": {name: float(np.mean([f.bounds_mm[name] for f in found])) for name in settings},
            "oracle_rotation_sd_deg_xyz": _rms([f.rotation_sd_deg for f in found]),
            "floor_estimate_mm": float(np.nanmean([f.floor_mm for f in found])),
            "engine_mean_3d_error_mm": float(np.nanmean([f.engine_error_mm for f in found])),
            "engine_shape_error_mm": float(np.nanmean([f.engine_shape_mm for f in found])),
            "engine_rotation_rms_deg_xyz": _rms([f.engine_rotation_deg for f in found]),
        }
        if case.key == "b" and top_covariance is not None:
            row["unseen_top_shape"] = unseen_top_row(series, settings["engine_priors"], top_covariance, draws, seed)
        if chord_covariance is not None:
            row["chord_lengths_unknown"] = chord_lengths_row(series, case, settings, chord_covariance, draws, seed)
        rows.append(row)
    return rows


def _pool(values: Sequence[Any]) -> Any:
    """One value from the same field of several seeds' rows: numbers averaged, vectors of numbers
    (angles' SDs and RMS, each over the same spines) pooled as √ of the mean of the squares, dicts
    field by field, anything else (names, counts) the first seed's."""
    first = values[0]
    if isinstance(first, dict):
        return {key: _pool([v[key] for v in values]) for key in first}
    if isinstance(first, list) and first and all(isinstance(x, (int, float)) for x in first):
        return np.sqrt(np.mean(np.square(values), axis=0)).round(3).tolist()
    if isinstance(first, float):
        return float(np.mean(values))
    return first


def pooled(runs: Sequence[Sequence[dict[str, Any]]]) -> list[dict[str, Any]]:
    """``run``'s rows over several noise seeds, pooled case by case (``_pool``), with each seed's
    engine rotation RMS beside them (``engine_rotation_rms_deg_xyz_by_seed``): one seed's 17 spines
    give it to within about ±30 %, so a ratio to the oracle's SD is judged on the pooled value."""
    rows = []
    for by_seed in zip(*runs, strict=True):
        row = _pool(list(by_seed))
        row["engine_rotation_rms_deg_xyz_by_seed"] = [r["engine_rotation_rms_deg_xyz"] for r in by_seed]
        row["engine_to_oracle_xyz"], row["engine_to_oracle_se_xyz"] = rotation_ratio(by_seed, row)
        if "chord_lengths_unknown" in row:
            chords = row["chord_lengths_unknown"]
            sd = np.asarray(chords["oracle_rotation_sd_deg_xyz"])
            oracle = np.asarray(row["oracle_rotation_sd_deg_xyz"])
            chords["to_oracle_xyz"] = (sd / oracle).round(3).tolist()
            best = np.asarray(chords["oracle_rotation_sd_deg_xyz_best_priors"])
            chords["best_priors_to_oracle_xyz"] = (best / oracle).round(3).tolist()
            chords["engine_to_it_xyz"] = (np.asarray(row["engine_rotation_rms_deg_xyz"]) / sd).round(3).tolist()
        rows.append(row)
    return rows


def rotation_ratio(
    by_seed: Sequence[dict[str, Any]], pooled_row: dict[str, Any]
) -> tuple[list[float], list[float | None]]:
    """(pooled engine RMS / pooled oracle SD about x, y, z; its standard error), the error from the
    seeds' own ratios: SE = SD_s(RMS_s / SD_s) / √S over the S seeds (None with one seed)."""
    ratio = np.asarray(pooled_row["engine_rotation_rms_deg_xyz"]) / np.asarray(pooled_row["oracle_rotation_sd_deg_xyz"])
    per_seed = np.array(
        [np.asarray(r["engine_rotation_rms_deg_xyz"]) / np.asarray(r["oracle_rotation_sd_deg_xyz"]) for r in by_seed]
    )
    se = per_seed.std(axis=0, ddof=1) / np.sqrt(len(per_seed)) if len(per_seed) > 1 else np.full(3, np.nan)
    return ratio.round(3).tolist(), [None if np.isnan(v) else round(float(v), 3) for v in se]


def engine_orientation_sd_deg() -> tuple[float, float, float]:
    """σ_ω about x, y, z (degrees) of the engine's orientation prior for a rigid turn of the spine: it
    holds T1's and L5's directors about d1, d2, d3 (≈ x, y, z) with SDs σ_T1 and σ_L5
    (``anatomy.PopulationPrior.orientation_sd_deg``), and a rigid turn moves both, so its precision
    about each axis is 1/σ_T1² + 1/σ_L5²."""
    prior = population_prior(load_profile())
    if prior is None:
        raise ValueError("the default profile has no population prior")
    top, bottom = (np.asarray(prior.orientation_sd_deg[level], dtype=float) for level in ("T1", "L5"))
    sd = 1.0 / np.sqrt(1.0 / top**2 + 1.0 / bottom**2)
    return float(sd[0]), float(sd[1]), float(sd[2])


def prior_settings(orientation_sd_deg: tuple[float, float, float]) -> dict[str, Priors]:
    """The three settings of the module docstring, by name."""
    bench = bench_turn_rms_deg()
    return {
        "engine_priors": Priors(orientation_sd_deg=engine_orientation_sd_deg()),
        "bench_turn": Priors(film_turn_sd_deg=bench, orientation_sd_deg=engine_orientation_sd_deg()),
        "bench_turn_and_orientation": Priors(film_turn_sd_deg=bench, orientation_sd_deg=orientation_sd_deg),
    }


def table(rows: Sequence[dict[str, Any]]) -> str:
    """The rows as an aligned text table."""
    head = ["case", "target mm", "bound: engine priors", "bench turn", "+ orientation", "floor est.",
            "engine 3D mm", "engine shape mm", "oracle SD x,y,z °", "engine RMS x,y,z °", "engine/oracle (± SE)"]
    body = [
        [r["case"], r["target_mm"] if r["target_mm"] is not None else "-", *r["bound_mm"].values(),
         r["floor_estimate_mm"], r["engine_mean_3d_error_mm"], r["engine_shape_error_mm"],
         " ".join(f"{v:.2f}" for v in r["oracle_rotation_sd_deg_xyz"]),
         " ".join(f"{v:.2f}" for v in r["engine_rotation_rms_deg_xyz"]),
         " ".join(f"{v:.2f}" + (f"±{e:.2f}" if e is not None else "")
                  for v, e in zip(r["engine_to_oracle_xyz"], r["engine_to_oracle_se_xyz"], strict=True))]
        for r in rows
    ]
    return format_table(head, body)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="spine bench clinic-bound", description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="VerSe folder with dev.csv and test.csv")
    parser.add_argument("--split", choices=["dev", "test"], default="test", help="VerSe split (default test)")
    parser.add_argument("--cases", default=BOUND_CASES, help=f"case letters among {BOUND_CASES} (default all)")
    parser.add_argument("--noise-mm", type=float, default=1.0, help="landmark noise SD, detector mm (default 1)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--seeds", type=int, default=1, metavar="N",
                        help="pool N noise seeds from --seed on (default 1): the engine's rotation RMS of one "
                        "seed's spines is noisy")
    parser.add_argument("--draws", type=int, default=4000, help="Monte Carlo draws of δω per spine (default 4000)")
    parser.add_argument("--json", action="store_true", help="print the rows as JSON instead of a table")
    parser.add_argument("--out", type=Path, default=Path("bench-out/clinic"), help="folder of the JSON")
    args = parser.parse_args(argv)
    unknown = [c for c in args.cases if c not in BOUND_CASES]
    if unknown or args.noise_mm <= 0 or args.seeds < 1:
        print(f"error: cases must be among {BOUND_CASES} (got {unknown}), --noise-mm > 0 and --seeds >= 1",
              file=sys.stderr)
        return 2
    try:
        truths = verse_truths(args.split, args.data)
        dev = verse_truths("dev", args.data)
        spread = orientation_spread(dev)
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    start = time.perf_counter()
    settings, top, chords = prior_settings(spread), top_prior_covariance(dev), chord_prior_covariance(dev)
    seeds = list(range(args.seed, args.seed + args.seeds))
    rows = pooled([run(truths, [CASES[c] for c in args.cases], settings, args.noise_mm, seed, args.draws, top, chords)
                   for seed in seeds])
    report = {
        "command": "spine bench clinic-bound " + " ".join(argv if argv is not None else sys.argv[1:]),
        "date": dt.date.today().isoformat(),
        "split": args.split,
        "noise_mm": args.noise_mm,
        "seeds": seeds,
        "draws": args.draws,
        "film_turn_sd_deg": {"engine": FILM_TURN_PRIOR_SD_DEG, "bench_rms": bench_turn_rms_deg()},
        "engine_orientation_sd_deg_xyz": list(engine_orientation_sd_deg()),
        "dev_orientation_sd_deg_xyz": list(spread),
        "seconds": round(time.perf_counter() - start, 1),
        "rows": rows,
    }
    write_json(args.out / f"clinic-bound-{args.split}.json", report)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(table(rows))
        for row in rows:
            if "chord_lengths_unknown" in row:
                c = row["chord_lengths_unknown"]
                print(f"case ({row['case']}), chord lengths {c['chords']} unknown: oracle rotation SD x,y,z "
                      f"{c['oracle_rotation_sd_deg_xyz']} deg ({c['to_oracle_xyz']} x the bound's oracle; best "
                      f"priors {c['oracle_rotation_sd_deg_xyz_best_priors']}, {c['best_priors_to_oracle_xyz']} x), "
                      f"aligned as the engine's {c['oracle_aligned_rotation_rms_deg_xyz']} deg; engine / it "
                      f"{c['engine_to_it_xyz']}")
            if "unseen_top_shape" in row:
                top = row["unseen_top_shape"]
                print(f"case (b), T1-T3 unseen: SD prior {top['prior_sd']} -> posterior {top['posterior_sd']}; "
                      f"shape bound {top['bound_mm']:.3f} mm, floor estimate with the engine's (a) errors "
                      f"{top['floor_estimate_mm']:.3f} mm; oracle rotation SD x,y,z "
                      f"{top['oracle_rotation_sd_deg_xyz']} deg, aligned as the engine's "
                      f"{top['oracle_aligned_rotation_rms_deg_xyz']} deg")
    return 0

