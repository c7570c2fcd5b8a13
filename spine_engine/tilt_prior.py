"""A calibrated prior on the frontal tilt of vertebrae given by their endplate midpoint only.

The midpoints fix where the vertebrae are, not how they are tilted: on real radiographs a
vertebra's transverse axis (the AASCE line from its left-edge midpoint to its right-edge
midpoint) is not perpendicular to the local chord of the midpoints, and the Cobb angle of a
chord-perpendicular model misses by 5–7° on AASCE 2019 (major Cobb MAE 5.32° on training, 7.43°
on test; docs/accuracy.md, method "(b-line)"). The prior
predicts each vertebra's frontal tilt from the frontal angles of the chords near it,

    θ̂_i = Σ_k c_ik φ_clip(i+k),   k ∈ the prior's window,   Σ_k c_ik = 1,

with φ_j the angle of the chord from landmark j to j + 1 (``observations.chord_angles_deg``,
degrees) and indices clipped to the chords that exist (0..15); with ``placement`` "shifted" the
window (contiguous) is instead moved inside 0..15 at the ends, so that every vertebra uses as many
distinct chords. Σ c = 1 makes the prediction turn with the image; no intercept keeps it
mirror-symmetric (a left curve is a mirrored right one). The coefficients are constrained least
squares on the ``training`` split of AASCE 2019 only, possibly blended toward the chord-normal
tilt (``toward_chord_normal``), written by ``spine bench aasce --calibrate``
(``spine_engine/priors/tilt_aasce2019.json``, with its provenance). In the registration each
predicted tilt is a soft tilt observation (``fit.ViewData``), weighted
``weight_fraction`` × the weight of a tilt from corners.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from .levels import N_LEVELS

FloatArray = npt.NDArray[np.float64]

PRIORS_DIR = Path(__file__).resolve().parent / "priors"
DEFAULT_PRIOR = "tilt_aasce2019"
WINDOW: tuple[int, ...] = (-2, -1, 0, 1)
"""Default window of ``chord_windows`` and ``fit_coefficients``: chords used for vertebra i, relative
to chord i (which joins vertebra i to i + 1). The shipped prior's own window (−3..+2, "shifted") is
in its JSON."""


@dataclass(frozen=True)
class TiltPrior:
    """Coefficients c (17, len(window)) of the tilt prior, the relative weight of its
    observations, and where they come from."""

    name: str
    window: tuple[int, ...]
    coefficients: FloatArray
    weight_fraction: float
    provenance: dict[str, Any] = field(default_factory=dict)
    placement: str = "clipped"
    """How the window meets the ends of the spine: "clipped" or "shifted" (``chord_windows``)."""
    cobb_sd_deg: dict[str, float] = field(default_factory=dict)
    """SD (degrees) a Cobb angle gains when no corner observed its end vertebrae's tilts, added in
    quadrature to its Laplace SD (``reconstruction``): "tilt_prior" when this prior's observations set
    those tilts, "no_tilt_prior" when only the rod did (``options.tilt_prior`` false). The Laplace SD
    is of the landmarks' centreline; how far a vertebra's endplate turns from it on a real radiograph
    is this residual. Calibrated on AASCE training so that the major angle's 95 % interval covers 95 %
    (``spine bench aasce --calibrate-cobb-sd``); empty: no term."""

    def model_tilt_cobb_sd_deg(self, with_prior: bool) -> float:
        """``cobb_sd_deg`` of a curve whose two end tilts are the model's (0 when not calibrated)."""
        return float(self.cobb_sd_deg.get("tilt_prior" if with_prior else "no_tilt_prior", 0.0))


def chord_windows(window: tuple[int, ...] = WINDOW, placement: str = "clipped") -> npt.NDArray[np.intp]:
    """Chord indices (17, len(window)) feeding each vertebra: i + k clipped to 0..15 ("clipped"), or
    the contiguous window moved inside 0..15 where it would stick out ("shifted")."""
    offsets = np.asarray(window)
    if placement == "clipped":
        return np.clip(np.arange(N_LEVELS)[:, None] + offsets[None, :], 0, N_LEVELS - 2)
    if placement != "shifted" or not np.array_equal(offsets, np.arange(offsets[0], offsets[0] + len(offsets))):
        raise ValueError(f"tilt prior: unknown placement {placement!r} or window {window} not contiguous")
    start = np.clip(np.arange(N_LEVELS) + offsets[0], 0, N_LEVELS - 1 - len(offsets))
    return start[:, None] + np.arange(len(offsets))[None, :]


def predict_tilts_deg(prior: TiltPrior, chord_deg: npt.ArrayLike) -> FloatArray:
    """Predicted frontal tilt (degrees) of each vertebra (..., 17) from the 16 chord angles (..., 16);
    NaN where a needed chord is missing (NaN in ``chord_deg``)."""
    phi = np.asarray(chord_deg, dtype=float)
    features = phi[..., chord_windows(prior.window, prior.placement)]
    return np.einsum("...ik,ik->...i", features, prior.coefficients)


def fit_coefficients(
    tilts_deg: npt.ArrayLike,
    chord_deg: npt.ArrayLike,
    window: tuple[int, ...] = WINDOW,
    ridge: float = 1e-3,
    placement: str = "clipped",
    weights: npt.ArrayLike | None = None,
) -> FloatArray:
    """Least-squares coefficients (17, len(window)) with Σ_k c_ik = 1, per vertebra i:

        min_c Σ_n w_ni (X_n c − θ_ni)² + λ‖c‖²  subject to 1ᵀc = 1

    (X_n the chord angles of the window in training spine n, θ_ni its observed tilt, w_ni its weight,
    1 without ``weights``), solved from its KKT system [XᵀWX + λI, 1; 1ᵀ, 0] [c; μ] = [XᵀWθ; 1].
    tilts (n, 17), chords (n, 16), weights (n, 17)."""
    T = np.asarray(tilts_deg, dtype=float)
    P = np.asarray(chord_deg, dtype=float)
    W = None if weights is None else np.asarray(weights, dtype=float)
    idx = chord_windows(window, placement)
    k = len(window)
    coefficients = np.empty((N_LEVELS, k))
    for i in range(N_LEVELS):
        X = P[:, idx[i]]
        WX = X if W is None else W[:, i, None] * X
        kkt = np.zeros((k + 1, k + 1))
        kkt[:k, :k] = WX.T @ X + ridge * np.eye(k)
        kkt[:k, k] = kkt[k, :k] = 1.0
        rhs = np.concatenate([WX.T @ T[:, i], [1.0]])
        coefficients[i] = np.linalg.lstsq(kkt, rhs, rcond=None)[0][:k]
    return coefficients


def toward_chord_normal(
    coefficients: npt.ArrayLike, window: tuple[int, ...], placement: str, blend: float
) -> FloatArray:
    """(1 − β) c + β c⊥: the coefficients blended with weight β = ``blend`` toward the chord-normal
    tilt c⊥, the mean of the chords on either side of the vertebra (0.5 φ_{i−1} + 0.5 φ_i, one-sided
    at T1 and L5: each vertebra perpendicular to the local line of its midpoints). Σ c stays 1."""
    idx = chord_windows(window, placement)
    normal = np.zeros(idx.shape)
    for i in range(N_LEVELS):
        for j in (max(i - 1, 0), min(i, N_LEVELS - 2)):
            where = np.flatnonzero(idx[i] == j)
            if not len(where):
                raise ValueError(f"tilt prior: window {window} ({placement}) does not hold chord {j} of vertebra {i}")
            normal[i, where[0]] += 0.5
    return (1.0 - blend) * np.asarray(coefficients, dtype=float) + blend * normal


def save_tilt_prior(prior: TiltPrior, path: Path) -> None:
    data = {
        "name": prior.name,
        "window": list(prior.window),
        "placement": prior.placement,
        "coefficients": np.round(prior.coefficients, 6).tolist(),
        "weight_fraction": prior.weight_fraction,
        "cobb_sd_deg": prior.cobb_sd_deg,
        "provenance": prior.provenance,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2, ensure_ascii=False) + "\n", encoding="utf-8")


@lru_cache(maxsize=4)
def load_tilt_prior(name: str = DEFAULT_PRIOR) -> TiltPrior:
    """The shipped prior ``spine_engine/priors/<name>.json``."""
    data = json.loads((PRIORS_DIR / f"{name}.json").read_text(encoding="utf-8"))
    coefficients = np.asarray(data["coefficients"], dtype=float)
    window = tuple(int(k) for k in data["window"])
    if coefficients.shape != (N_LEVELS, len(window)):
        raise ValueError(f"tilt prior {name!r}: coefficients must be (17, {len(window)}), got {coefficients.shape}")
    coefficients.setflags(write=False)
    return TiltPrior(
        data["name"],
        window,
        coefficients,
        float(data["weight_fraction"]),
        data.get("provenance", {}),
        data.get("placement", "clipped"),
        {str(k): float(v) for k, v in data.get("cobb_sd_deg", {}).items()},
    )
