"""``spine bench perf``: time single registrations (initial configuration + fit) on a synthetic spine.

The problem is built here, with placeholder elastic values (not the calibrated profile): a rest
spine 450 mm long with kyphosis, lordosis and a 30° lateral curve, and a "patient" spine with a
45° curve and axial rotation whose vertebrae are projected on a PA view (s = 1.15) with 0.5 mm
landmark noise. Run with one BLAS thread for the single-core figure:

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python -m benches.perf
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy

from benches.clinic import truths_of_csv
from benches.clinic_films import CASES, build_payload, simulate_series
from benches.truth import payload_from_truth
from spine_engine.fit import RodParameters, ViewData, fit, initial_configuration
from spine_engine.projection import image_axes, project
from spine_engine.reconstruction import register
from spine_engine.rod import strains


def synthetic_spine(
    n: int = 17,
    length: float = 450.0,
    kyphosis_mm: float = 30.0,
    cobb_deg: float = 30.0,
    twist_deg: float = 0.0,
    apex: float = 0.5,
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """A smooth spine made by geometric construction: positions (n, 3) mm and rotations (n, 3, 3).

    Centreline over t ∈ [0, 1] from T1 (t = 0) to L5: z = −H t; sagittal y = a sin(πt/0.65)
    (kyphosis, convex posterior) then −a·(0.35/0.65) sin(π(t − 0.65)/0.35) (lordosis), which is
    C¹; frontal x a raised-cosine bump over [apex − 0.35, apex + 0.35] whose Cobb angle between
    its inflection points is ``cobb_deg``. H is set so the arc length is ``length``. Vertebrae
    sit at arc-length spacings growing linearly 24 → 34 (scaled to the length). d3 is the
    caudal unit tangent, d1 the projection of +x orthogonal to d3 turned about d3 by an axial
    rotation of ``twist_deg``·sin²-bump peaking at the apex, d2 = d3 × d1.
    """
    t_fine = np.linspace(0.0, 1.0, 4001)
    half = 0.35
    t0, t1 = apex - half, apex + half
    a_lord = kyphosis_mm * 0.35 / 0.65

    def curve(t: np.ndarray, height: float) -> np.ndarray:
        y = np.where(t <= 0.65, kyphosis_mm * np.sin(np.pi * t / 0.65), -a_lord * np.sin(np.pi * (t - 0.65) / 0.35))
        bump_len = 2.0 * half * height
        amp = np.tan(np.radians(cobb_deg) / 2.0) * bump_len / np.pi
        inside = (t >= t0) & (t <= t1)
        x = np.where(inside, amp * 0.5 * (1.0 - np.cos(2.0 * np.pi * (t - t0) / (t1 - t0))), 0.0)
        return np.stack((x, y, -height * t), axis=-1)

    height = length
    for _ in range(4):
        pts = curve(t_fine, height)
        arc = float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)))
        height *= length / arc
    pts = curve(t_fine, height)
    cum = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))))
    spacing = np.linspace(24.0, 34.0, n - 1)
    s_v = np.concatenate(([0.0], np.cumsum(spacing))) * cum[-1] / spacing.sum()
    t_v = np.interp(s_v, cum, t_fine)
    r = curve(t_v, height) + np.asarray(origin)
    h = 1e-6
    tangent = curve(np.clip(t_v + h, 0, 1), height) - curve(np.clip(t_v - h, 0, 1), height)
    d3 = tangent / np.linalg.norm(tangent, axis=1, keepdims=True)
    x_axis = np.array([1.0, 0.0, 0.0])
    d1 = x_axis - (d3 @ x_axis)[:, None] * d3
    d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
    d2 = np.cross(d3, d1)
    inside = (t_v >= t0) & (t_v <= t1)
    gamma = np.radians(twist_deg) * np.where(inside, np.sin(np.pi * (t_v - t0) / (t1 - t0)) ** 2, 0.0)
    d1 = np.cos(gamma)[:, None] * d1 + np.sin(gamma)[:, None] * d2
    d2 = np.cross(d3, d1)
    return r, np.stack((d1, d2, d3), axis=-1)


@dataclass(frozen=True)
class BenchCase:
    """One timed registration: the rod, its rest shape, the views, the exact ends and the truth."""

    params: RodParameters
    rest_positions: np.ndarray
    rest_rotations: np.ndarray
    views: list[ViewData]
    top: tuple[np.ndarray, np.ndarray]
    bottom: tuple[np.ndarray, np.ndarray]
    truth_positions: np.ndarray


def placeholder_parameters(rest_positions: np.ndarray, rest_rotations: np.ndarray) -> RodParameters:
    """Rest strains of the given shape with placeholder stiffness α = (1e6, 1e6, 5e5) N·mm², β = (5e3, 5e3, 1e4) N."""
    ds = np.linalg.norm(np.diff(rest_positions, axis=0), axis=1)
    u0, v0 = strains(rest_positions, rest_rotations, ds)
    ns = len(ds)
    return RodParameters(
        ds=ds,
        u0=u0,
        v0=v0,
        alpha=np.tile([1e6, 1e6, 5e5], (ns, 1)),
        beta=np.tile([5e3, 5e3, 1e4], (ns, 1)),
    )


def build_case(lateral: bool = False, seed: int = 0, weight: float = 10.0) -> BenchCase:
    """The benchmark case: 17 PA landmarks (and 17 lateral ones if ``lateral``)."""
    rng = np.random.default_rng(seed)
    rest_r, rest_R = synthetic_spine(cobb_deg=30.0, twist_deg=0.0)
    true_r, true_R = synthetic_spine(
        cobb_deg=45.0, twist_deg=15.0, kyphosis_mm=24.0, apex=0.45, origin=(5.0, -10.0, 1200.0)
    )
    views = []
    specs = [("pa", ("L", "F"), 1.15, (210.0, 80.0))]
    if lateral:
        specs.append(("lateral", ("A", "F"), 1.12, (190.0, 85.0)))
    idx = np.arange(len(true_r))
    for name, orientation, s, T in specs:
        e_c, e_r = image_axes(orientation)
        points = project(true_r, e_c, e_r, s, np.asarray(T)) + rng.normal(0.0, 0.5, (len(true_r), 2))
        views.append(ViewData(name, idx, points, e_c, e_r, s, np.asarray(T), weight))
    return BenchCase(
        params=placeholder_parameters(rest_r, rest_R),
        rest_positions=rest_r,
        rest_rotations=rest_R,
        views=views,
        top=(true_r[0], true_R[0]),
        bottom=(true_r[-1], true_R[-1]),
        truth_positions=true_r,
    )


def _stats(samples_ms: list[float]) -> dict[str, float]:
    a = np.asarray(samples_ms)
    return {
        "median_ms": float(np.median(a)),
        "p90_ms": float(np.percentile(a, 90)),
        "mean_ms": float(np.mean(a)),
    }


def run(repeats: int = 200, lateral: bool = False, warmup: int = 10) -> dict[str, object]:
    """Time ``repeats`` registrations; returns timings (ms) of initial configuration + fit and fit alone."""
    pb = build_case(lateral=lateral)
    total, fit_only = [], []
    out = None
    for k in range(warmup + repeats):
        start = time.perf_counter()
        r0, R0 = initial_configuration(pb.rest_positions, pb.rest_rotations, pb.views, pb.top, pb.bottom)
        mid = time.perf_counter()
        out = fit(pb.params, pb.views, pb.top, pb.bottom, r0, R0)
        end = time.perf_counter()
        if k >= warmup:
            total.append(1e3 * (end - start))
            fit_only.append(1e3 * (end - mid))
    assert out is not None
    err = np.linalg.norm(out.positions - pb.truth_positions, axis=1)
    return {
        "problem": "17 PA landmarks" + (" + 17 lateral" if lateral else ""),
        "repeats": repeats,
        "iterations": out.iterations,
        "converged": out.converged,
        "mean_3d_error_mm": float(err.mean()),
        "initial_plus_fit": _stats(total),
        "fit_only": _stats(fit_only),
    }


REAL_SPINES = Path(__file__).resolve().parents[1] / "tests" / "data" / "verse_dev.csv"


def clinic_payloads(case: str, spines_csv: Path = REAL_SPINES) -> list[dict[str, Any]]:
    """The payloads of ``spine bench clinic``'s case ``case`` for the VerSe dev spines (its simulated
    series, 1 mm noise, seed 0): no boundary, the films as a clinic sends them."""
    return [build_payload(simulate_series(t, 1.0, 0), CASES[case]).model_dump(mode="json", exclude_none=True)
            for t in truths_of_csv(spines_csv)]  # fmt: skip


def run_register(repeats: int, spines_csv: Path = REAL_SPINES, case: str | None = None) -> dict[str, object]:
    """Time the public ``register(payload)`` end to end (validation, patient rest rod, fit,
    measures, result model) with the calibrated default profile, cycling over real spines (VerSe
    dev): 17 PA landmarks projected from CT with T1 and L5 given (the paper's case), or, with
    ``case``, the payloads of that clinic case (``clinic_payloads``); also the fit alone as the
    result reports it, the number of spines cycled over and of timed calls (``repeats``)."""
    if case is None:
        payloads = [payload_from_truth(t.positions, t.rotations, list(range(17))) for t in truths_of_csv(spines_csv)]
        problem = f"register(), {len(payloads)} real spines, 17 PA"
    else:
        payloads = clinic_payloads(case, spines_csv)
        problem = f"register(), clinic ({case}), {len(payloads)} real spines"
    for payload in payloads[:5]:
        register(payload)
    total, fit_ms, iterations = [], [], []
    for k in range(repeats):
        start = time.perf_counter()
        result = register(payloads[k % len(payloads)])
        total.append((time.perf_counter() - start) * 1e3)
        fit_ms.append(result["fit"]["runtime_ms"])
        iterations.append(result["fit"]["iterations"])
    return {
        "problem": problem,
        "spines": len(payloads),
        "repeats": repeats,
        "iterations": f"{np.median(iterations):.0f}",
        "initial_plus_fit": _stats(fit_ms),
        "register_total": _stats(total),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="spine bench perf", description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=200, help="timed registrations (default 200)")
    parser.add_argument("--lateral", action="store_true", help="also time PA + lateral (17 + 17 landmarks)")
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    parser.add_argument("--out", type=Path, help="also write the results as JSON to this file")
    parser.add_argument("--register", action="store_true",
                        help="also time the public register() with the calibrated profile on real spines")
    parser.add_argument("--clinic", default="", metavar="CASES",
                        help="also time register() on these cases of spine bench clinic (e.g. adeg): no boundary")
    args = parser.parse_args(argv)
    unknown = [c for c in args.clinic if c not in CASES]
    if unknown:
        parser.error(f"--clinic: unknown cases {unknown} (known: {''.join(CASES)})")
    results = [run(args.repeats)]
    if args.lateral:
        results.append(run(args.repeats, lateral=True))
    if args.register:
        results.append(run_register(args.repeats))
    results += [run_register(args.repeats, case=case) for case in args.clinic]
    environment = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "cpus": os.cpu_count(),
        **{name: os.environ.get(name) for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")},
    }
    report = json.dumps({"environment": environment, "results": results}, indent=2)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(report + "\n")
    if args.json:
        print(report)
        return 0
    print(f"{'problem':<36} {'timed':<22} {'median ms':>10} {'p90 ms':>8} {'mean ms':>8} {'iter':>5}")
    for res in results:
        for key, label in (("initial_plus_fit", "initial config + fit"), ("fit_only", "fit only"),
                           ("register_total", "whole register()")):
            if key not in res:
                continue
            st = res[key]
            assert isinstance(st, dict)
            print(
                f"{res['problem']!s:<36} {label:<22} {st['median_ms']:>10.2f} {st['p90_ms']:>8.2f} "
                f"{st['mean_ms']:>8.2f} {res['iterations']!s:>5}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
