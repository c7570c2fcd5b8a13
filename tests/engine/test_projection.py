"""Image axes from patient orientation, weak perspective, and its closed-form estimate."""

import numpy as np
import pytest

from spine_engine.projection import estimate_projection, image_axes, project

RNG = np.random.default_rng(3)


def test_image_axes_of_pa_and_lateral():
    e_c, e_r = image_axes(("L", "F"))
    np.testing.assert_array_equal(e_c, [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(e_r, [0.0, 0.0, -1.0])
    e_c, e_r = image_axes(("A", "F"))
    np.testing.assert_array_equal(e_c, [0.0, -1.0, 0.0])
    np.testing.assert_array_equal(e_r, [0.0, 0.0, -1.0])
    expected = {"L": [1, 0, 0], "R": [-1, 0, 0], "P": [0, 1, 0], "A": [0, -1, 0], "H": [0, 0, 1], "F": [0, 0, -1]}
    for col, vec in expected.items():
        row = "H" if col not in "HF" else "L"
        np.testing.assert_array_equal(image_axes((col, row))[0], vec)


@pytest.mark.parametrize("orientation", [("L", "X"), ("L", "R"), ("F", "H"), ("a", "F")])
def test_image_axes_rejects_bad_orientations(orientation):
    with pytest.raises(ValueError):
        image_axes(orientation)


def test_project_is_weak_perspective_and_batched():
    e_c, e_r = image_axes(("L", "F"))
    r = RNG.normal(size=(4, 5, 3)) * 100
    p = project(r, e_c, e_r, 1.2, np.array([10.0, -20.0]))
    assert p.shape == (4, 5, 2)
    np.testing.assert_allclose(p[..., 0], 1.2 * r[..., 0] + 10.0)
    np.testing.assert_allclose(p[..., 1], -1.2 * r[..., 2] - 20.0)


@pytest.mark.parametrize("orientation", [("L", "F"), ("A", "F"), ("R", "H")])
def test_estimate_projection_recovers_scale_and_translation(orientation):
    e_c, e_r = image_axes(orientation)
    s, T = 1.137, np.array([212.5, -31.0])
    pts = RNG.normal(size=(2, 3)) * 200
    s_hat, T_hat = estimate_projection(pts, project(pts, e_c, e_r, s, T), e_c, e_r)
    assert s_hat == pytest.approx(s, rel=1e-13)
    np.testing.assert_allclose(T_hat, T, atol=1e-10)
    # many noisy points: the least-squares optimum (zero gradient in s and T)
    pts = RNG.normal(size=(17, 3)) * 150
    image = project(pts, e_c, e_r, s, T) + RNG.normal(size=(17, 2))
    s_hat, T_hat = estimate_projection(pts, image, e_c, e_r)
    q = pts @ np.stack((e_c, e_r)).T
    resid = s_hat * q + T_hat - image
    assert abs(np.sum(resid * q)) < 1e-7 * np.sum(q * q)
    np.testing.assert_allclose(resid.sum(axis=0), 0.0, atol=1e-8)


def test_estimate_projection_rejects_degenerate_and_mirrored_data():
    e_c, e_r = image_axes(("L", "F"))
    # T1 and L5 differing only in depth project onto one point of the PA image
    same = np.array([[0.0, 0.0, 0.0], [0.0, 80.0, 0.0]])
    with pytest.raises(ValueError, match="same image point"):
        estimate_projection(same, [[5.0, 5.0], [5.0, 9.0]], e_c, e_r)
    pts = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, -400.0]])
    mirrored = project(pts, e_c, e_r, -1.1, np.zeros(2))
    with pytest.raises(ValueError, match="≤ 0"):
        estimate_projection(pts, mirrored, e_c, e_r)
    with pytest.raises(ValueError, match="at least 2"):
        estimate_projection(pts[:1], mirrored[:1], e_c, e_r)
    with pytest.raises(ValueError, match="expected"):
        estimate_projection(pts, mirrored[:1], e_c, e_r)
