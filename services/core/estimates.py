"""Which values of a result are model estimates rather than measured, and why, in words: the one
rule the DICOM SR (method MODEL-BASED) and the FHIR export (interpretation and note) both apply to a
result's ``fit`` block (``spine_engine.models.FitReport`` as JSON: ``unreliable``, ``assumed``,
``boundary``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

EXACT_ENDS = ("T1", "L5")
"""The vertebrae whose pose a boundary given exactly (``fit.boundary`` "given") fixes, axial rotation included."""


def _assumption(fit: Mapping[str, Any], name: str) -> Mapping[str, Any] | None:
    """The ``fit.assumed`` entry (``spine_engine.models.Assumption``: name, view, reason) named ``name``."""
    return next((a for a in fit.get("assumed") or [] if isinstance(a, Mapping) and a.get("name") == name), None)


def model_estimate_reason(fit: Mapping[str, Any], quantity: str, level: str | None = None) -> str | None:
    """Why a value of the result comes from the model's prior rather than the films, in plain words
    ending with the result's entry that says so; None when the films determine it.

    ``quantity`` is a ``fit.unreliable`` name (``axial_rotation``, ``kyphosis``, ``lordosis``,
    ``plane_of_max_curvature``, ``twist``, ``cobb``: every frontal Cobb angle, the largest included...), ``level``
    the vertebra an axial rotation is of. A value is a model estimate when ``fit.unreliable`` lists its quantity,
    and an axial rotation also when ``fit.assumed`` names ``population_axial_rotation`` (no pedicles: the
    population's mean given the frontal curves); never T1's and L5's axial rotation when the boundary was given
    exactly (their poses, the payload's). The SR marks these values MODEL-BASED (``services.dicom.sr.model_based``)
    and the FHIR export notes them (``services.fhir.export``)."""
    unreliable = set(fit.get("unreliable") or [])
    boundary = fit.get("boundary", "given")
    if quantity == "axial_rotation":
        if boundary == "given" and level in EXACT_ENDS:
            return None  # T1's and L5's poses are the payload's
        prior = _assumption(fit, "population_axial_rotation")
        if prior is not None:
            reason = prior.get("reason") or "no pedicles: the axial rotation is the population's mean"
            return f"{reason} (fit.assumed: population_axial_rotation)"
        if quantity in unreliable:
            return "no pedicle centres were given, so no film observes the vertebrae's turn about their axis; it " \
                "comes from the spine model (fit.unreliable: axial_rotation)"
        return None
    if quantity not in unreliable:
        return None
    if quantity in ("kyphosis", "lordosis"):
        shape = _assumption(fit, "population_sagittal_shape")
        if shape is not None and shape.get("reason"):
            return f"{shape['reason']} (fit.assumed: population_sagittal_shape; fit.unreliable: {quantity})"
        if "depth" in unreliable:
            return f"T1 and L5 were not given and fewer than 2 lateral landmarks place the spine in depth, so the " \
                f"{quantity} comes from the spine model's prior (fit.unreliable: {quantity})"
        films = "the lateral film's landmarks say little of it" if fit.get("lateral") else "no lateral film was given"
        ends = {"given": "T1 and L5 given", "soft": "T1 and L5 given with SDs"}.get(str(boundary),
                                                                                  "T1 and L5 not given")  # fmt: skip
        return f"{films} ({ends}): its standard deviation exceeds half the population's, so it stays close to the " \
            f"spine model's prior (fit.unreliable: {quantity})"
    if quantity == "cobb":
        return "the PA film's landmarks do not reach every level from T1 to L5 (two or more levels in a row " \
            "without one), or a Cobb angle's standard deviation exceeds half the population's: the frontal Cobb " \
            "angles depend on the spine model's prior where no landmark is, and each such angle's SD is at least " \
            "the population's (fit.unreliable: cobb)"
    if quantity == "plane_of_max_curvature":
        ends = " and T1 and L5 were not given" if boundary == "estimated" else ""
        return f"fewer than 2 lateral landmarks place the spine in depth{ends}: the plane of maximum curvature and " \
            "the Cobb angle in it come from the spine model's prior (fit.unreliable: plane_of_max_curvature)"
    return f"the films do not determine it: it comes from the spine model's prior (fit.unreliable: {quantity})"
