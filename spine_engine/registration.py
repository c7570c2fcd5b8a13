"""Compatibility module: the fit now lives in ``spine_engine.fit`` (issue #10, item 8).

Registration of the discrete Cosserat rod to radiograph landmarks (Li et al., CAIP 2009): see
``spine_engine.fit`` for the problem, its rows and derivatives, the banded algebra and the solver.
"""

from __future__ import annotations

from collections.abc import Sequence

from numpy.typing import ArrayLike

from .fit import FitOutput, FloatArray, RegistrationProblem, RodParameters, ViewData, fit, initial_configuration
from .fit.banded import band_to_dense
from .fit.solver import ETOL, FTOL, XTOL_MM, XTOL_RAD
from .fit.types import Pose


def residuals(
    params: RodParameters,
    views: Sequence[ViewData],
    top: Pose,
    bottom: Pose,
    positions: ArrayLike,
    rotations: ArrayLike,
) -> FloatArray:
    """Stacked residual vector ρ of a configuration (layout in ``fit.problem``); E = ‖ρ‖²."""
    return RegistrationProblem(params, views, top, bottom).residuals(positions, rotations)


def jacobian(
    params: RodParameters,
    views: Sequence[ViewData],
    top: Pose,
    bottom: Pose,
    positions: ArrayLike,
    rotations: ArrayLike,
) -> FloatArray:
    """Analytic Jacobian of ``residuals`` w.r.t. (δr_j, δθ_j), j = 1..N−2; see ``fit.problem``."""
    return RegistrationProblem(params, views, top, bottom).jacobian(positions, rotations)


__all__ = [
    "ETOL",
    "FTOL",
    "XTOL_MM",
    "XTOL_RAD",
    "FitOutput",
    "RegistrationProblem",
    "RodParameters",
    "ViewData",
    "band_to_dense",
    "fit",
    "initial_configuration",
    "jacobian",
    "residuals",
]
