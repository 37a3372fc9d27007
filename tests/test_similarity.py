"""Tests of the SSIM sub-goal similarity."""

import numpy as np
import pytest
import torch as th
from scipy.ndimage import gaussian_filter
from skimage.metrics import structural_similarity

from sb3_hhp.goals.similarity import ssim_pair, ssim_to_set, window_size

th.set_num_threads(1)


def _skimage_ssim(a: np.ndarray, b: np.ndarray, data_range: float) -> float:
    return structural_similarity(
        a,
        b,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=data_range,
        channel_axis=2 if a.ndim == 3 else None,
    )


def _reference_ssim(a: np.ndarray, b: np.ndarray, data_range: float, win_size: int) -> float:
    """Wang et al. (2004) SSIM in float64 with a Gaussian window (sigma 1.5) of side win_size,
    averaged over the positions where the window fits, then over channels."""
    a = np.atleast_3d(np.asarray(a, dtype=np.float64))
    b = np.atleast_3d(np.asarray(b, dtype=np.float64))
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    radius = win_size // 2
    values = []
    for channel in range(a.shape[2]):
        x, y = a[:, :, channel], b[:, :, channel]

        def blur(z: np.ndarray) -> np.ndarray:
            if radius == 0:
                return z
            return gaussian_filter(z, sigma=1.5, radius=radius, mode="reflect")

        mu_x, mu_y = blur(x), blur(y)
        var_x, var_y = blur(x * x) - mu_x**2, blur(y * y) - mu_y**2
        cov = blur(x * y) - mu_x * mu_y
        ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
        height, width = x.shape
        values.append(ssim_map[radius : height - radius, radius : width - radius].mean())
    return float(np.mean(values))


def _structured(shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    """A smooth gradient with a bright rectangle and mild noise, uint8."""
    height, width = shape[:2]
    yy, xx = np.mgrid[0:height, 0:width]
    image = 100 + 80 * np.sin(xx / 5.0) * np.cos(yy / 7.0)
    image[height // 4 : height // 2, width // 3 : 2 * width // 3] = 240
    if len(shape) == 3:
        image = np.stack([image * (0.6 + 0.2 * c) for c in range(shape[2])], axis=-1)
    return np.clip(image + rng.normal(0, 5, shape), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("shape", [(84, 84), (32, 48, 3), (20, 20, 4)])
def test_ssim_matches_skimage(shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(0)
    image = _structured(shape, rng)
    goals = np.stack(
        [
            rng.integers(0, 256, shape, dtype=np.uint8),  # unrelated noise
            _structured(shape, rng),  # same structure, other noise
            np.clip(image.astype(int) + rng.integers(-40, 40, shape), 0, 255).astype(np.uint8),
            np.roll(image, 3, axis=1),  # shifted
            255 - image,  # inverted
        ]
    )
    values = ssim_to_set(image, goals)
    assert values.shape == (len(goals),) and values.dtype == np.float64
    expected = np.array([_skimage_ssim(image, goal, 255.0) for goal in goals])
    np.testing.assert_allclose(values, expected, atol=1e-3)
    assert values.min() < 0.3 and values.max() > 0.5  # the cases really differ


def test_ssim_float_images_data_range_one() -> None:
    rng = np.random.default_rng(1)
    image = rng.random((30, 30))
    goals = np.stack([image * 0.9 + 0.05, rng.random((30, 30))])
    expected = [_skimage_ssim(image, goal, 1.0) for goal in goals]
    np.testing.assert_allclose(ssim_to_set(image, goals, data_range=1.0), expected, atol=1e-3)


def test_reference_agrees_with_skimage() -> None:
    """The float64 reference used for small images is itself checked against skimage (11x11)."""
    rng = np.random.default_rng(2)
    a, b = rng.integers(0, 256, (2, 25, 30)).astype(np.uint8)
    assert _reference_ssim(a, b, 255.0, 11) == pytest.approx(_skimage_ssim(a, b, 255.0), abs=1e-9)


@pytest.mark.parametrize("shape, win", [((7, 9), 7), ((8, 12), 7), ((6, 6, 3), 5), ((2, 5), 1), ((1, 6), 1), ((3, 1), 1)])
def test_small_images_use_the_largest_odd_window(shape: tuple[int, ...], win: int) -> None:
    assert window_size(*shape[:2]) == win
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, shape).astype(np.uint8)
    goals = rng.integers(0, 256, (3, *shape)).astype(np.uint8)
    goals[1] = image
    values = ssim_to_set(image, goals)
    expected = [_reference_ssim(image, goal, 255.0, win) for goal in goals]
    np.testing.assert_allclose(values, expected, atol=1e-4)
    assert values[1] == pytest.approx(1.0, abs=1e-5)


def test_pixelwise_ssim_by_hand() -> None:
    # 1x3 images: 1x1 window, so variances vanish and SSIM is the mean luminance term
    image = np.array([[0.0, 1.0, 2.0]])
    goal = np.array([[1.0, 2.0, 3.0]])
    c1 = (0.01 * 3.0) ** 2
    expected = np.mean((2 * image * goal + c1) / (image**2 + goal**2 + c1))
    assert ssim_pair(image, goal, data_range=3.0) == pytest.approx(expected, abs=1e-5)


@pytest.mark.parametrize("shape", [(40, 40), (24, 24, 3)])
def test_identical_image_has_ssim_one(shape: tuple[int, ...]) -> None:
    image = np.random.default_rng(4).integers(0, 256, shape).astype(np.uint8)
    assert ssim_pair(image, image.copy()) == pytest.approx(1.0, abs=1e-6)
    assert ssim_to_set(image, np.stack([image, image]))[1] == pytest.approx(1.0, abs=1e-6)


def test_batched_equals_pairs() -> None:
    rng = np.random.default_rng(5)
    image = rng.integers(0, 256, (16, 20, 3)).astype(np.uint8)
    goals = rng.integers(0, 256, (6, 16, 20, 3)).astype(np.uint8)
    goals[2] = image // 2
    batched = ssim_to_set(image, goals)
    pairs = np.array([ssim_pair(image, goal) for goal in goals])
    np.testing.assert_allclose(batched, pairs, atol=1e-6)
    # symmetric
    assert ssim_pair(goals[0], image) == pytest.approx(batched[0], abs=1e-6)


def test_empty_goal_set() -> None:
    values = ssim_to_set(np.zeros((10, 10)), np.zeros((0, 10, 10)))
    assert values.shape == (0,)
    values = ssim_to_set(np.zeros((10, 10, 3)), np.zeros((0, 10, 10, 3)))
    assert values.shape == (0,)


def test_bad_shapes_raise() -> None:
    with pytest.raises(ValueError, match=r"image must have shape \(H, W\) or \(H, W, C\)"):
        ssim_to_set(np.zeros(10), np.zeros((1, 10)))
    with pytest.raises(ValueError, match=r"goals must have shape \(N, 10, 10\)"):
        ssim_to_set(np.zeros((10, 10)), np.zeros((2, 10, 11)))
    with pytest.raises(ValueError, match=r"goals must have shape \(N, 10, 10, 3\)"):
        ssim_to_set(np.zeros((10, 10, 3)), np.zeros((10, 10, 3)))
    with pytest.raises(ValueError, match="same shape"):
        ssim_pair(np.zeros((10, 10)), np.zeros((10, 10, 1)))
    with pytest.raises(ValueError, match="data_range"):
        ssim_to_set(np.zeros((10, 10)), np.zeros((1, 10, 10)), data_range=0.0)
