"""The solver's setup outside the loop: cached layout arrays are read-only, and the cheaper
normalisation in ``rotation_between`` gives the bits of ``np.linalg.norm``."""

import numpy as np
import pytest

from spine_engine.anatomy import length_correction, list_profiles, load_profile, rest_shape_unit
from spine_engine.clinical import polyline_length, size_factor
from spine_engine.fit import ViewData
from spine_engine.fit.banded import UPPER3
from spine_engine.fit.initial import _BAND_ROW, _band_bins
from spine_engine.projection import image_axes
from spine_engine.rotations import hat, rotation_between


def _reference_bins(n: int, layout: tuple[tuple[int, ...], ...]) -> tuple[np.ndarray, np.ndarray]:
    """The band and right-hand-side indices as ``initial_configuration`` built them per call."""
    _, b = UPPER3
    rows, cols, rhs = [], [], []
    for indices in layout:
        idx = np.asarray(indices, dtype=int)
        rows.append(np.broadcast_to(_BAND_ROW, (len(idx), len(_BAND_ROW))).ravel())
        cols.append((3 * idx[:, None] + b).ravel())
        rhs.append((3 * idx[:, None] + np.arange(3)).ravel())
    return np.concatenate(rows) * 3 * n + np.concatenate(cols), np.concatenate(rhs)


def test_band_bins_match_the_per_call_construction_and_are_read_only():
    layout = (tuple(range(17)), (0, 4, 9, 16))
    flat, bins = _band_bins(17, layout)
    ref_flat, ref_bins = _reference_bins(17, layout)
    assert flat.dtype == ref_flat.dtype and bins.dtype == ref_bins.dtype
    assert np.array_equal(flat, ref_flat) and np.array_equal(bins, ref_bins)
    assert _band_bins(17, layout)[0] is flat  # cached
    for arr in (flat, bins):
        with pytest.raises(ValueError):
            arr[0] = 1


def _reference_rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``rotation_between``'s general branch as it was, normalising with ``np.linalg.norm``."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    c = (hat(a) @ b[..., None])[..., 0]
    cos = np.einsum("...i,...i->...", a, b)
    out = (c / (1.0 + cos)[..., None])[..., :, None] * c[..., None, :] + hat(c)
    out.reshape(*out.shape[:-2], 9)[..., ::4] += cos[..., None]
    return out


def test_rotation_between_normalises_with_the_bits_of_linalg_norm():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(500, 3)) * rng.uniform(1e-3, 1e3, size=(500, 1))
    b = a + rng.normal(size=(500, 3)) * rng.uniform(1e-6, 1e2, size=(500, 1))
    assert np.array_equal(
        a / np.sqrt(np.add.reduce(a * a, axis=-1, keepdims=True)), a / np.linalg.norm(a, axis=-1, keepdims=True)
    )
    cos = np.einsum("ni,ni->n", a, b) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    a, b = a[cos > -0.85], b[cos > -0.85]
    assert np.array_equal(rotation_between(a, b), _reference_rotation_between(a, b))
    assert np.array_equal(rotation_between(a[0], b[0]), _reference_rotation_between(a[0], b[0]))


@pytest.mark.parametrize("name", list_profiles())
def test_size_factor_matches_the_uncached_formula(name: str):
    """``size_factor`` with the generic spine's projected length cached per rest shape, levels and
    axes gives the bits of the per-call computation (times the population's length correction), for
    every shipped profile and two layouts."""
    profile = load_profile(name)
    rng = np.random.default_rng(5)
    for orientation in (("L", "F"), ("A", "F")):
        e_c, e_r = image_axes(orientation)
        for indices in (np.arange(17), np.array([0, 3, 7, 11, 16])):
            points = rng.normal(size=(len(indices), 2)) * 40.0
            view = ViewData("pa", indices, points, e_c, e_r, 0.87, np.zeros(2), 1.0)
            generic = rest_shape_unit(profile)[1][indices]
            model = polyline_length(np.stack([generic @ e_c, generic @ e_r], axis=1))
            expected = polyline_length(points / 0.87) / model * length_correction(profile)
            assert size_factor(profile, view) == expected
            assert size_factor(profile, view) == expected  # from the cache
