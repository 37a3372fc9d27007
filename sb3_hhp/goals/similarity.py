"""Similarity between sub-goal images: single-scale SSIM (Wang et al., 2004).

The paper measures how alike two sub-goals are with single-scale SSIM and rejects a candidate
sub-goal whose similarity to a stored one reaches ``b_similarity = 0.5`` (section 5.1, Algorithm 1
line 29). SSIM here is the usual setting (``skimage.metrics.structural_similarity`` with
``gaussian_weights=True, sigma=1.5, use_sample_covariance=False``): an 11x11 Gaussian window of
standard deviation 1.5, K1 = 0.01, K2 = 0.03, the mean of the SSIM map over the positions where
the window fits entirely, averaged over channels. It is computed by ``pytorch_msssim`` for a whole
set of goals in one batched call.

Images smaller than the window: the window side becomes the largest odd number that fits in the
image, ``min(11, H, W)`` rounded down to odd, with the same sigma (1.5) and the kernel truncated
and renormalised. A side of 1 pixel leaves a 1x1 window (pixel-wise SSIM).
"""

import numpy as np
import torch as th
from pytorch_msssim import ssim

#: Side of the Gaussian window of standard SSIM (Wang et al., 2004).
DEFAULT_WIN_SIZE = 11
#: Standard deviation of the Gaussian window, in pixels.
WIN_SIGMA = 1.5


def window_size(height: int, width: int) -> int:
    """
    Side of the Gaussian window used for images of ``height x width`` pixels.

    :param height: Image height in pixels, ``>= 1``.
    :param width: Image width in pixels, ``>= 1``.
    :return: 11, or the largest odd number ``<= min(height, width)`` when the image is smaller.
    """
    side = min(DEFAULT_WIN_SIZE, height, width)
    return side if side % 2 == 1 else side - 1


def _to_nchw(images: np.ndarray) -> th.Tensor:
    """(N, H, W) or (N, H, W, C) -> float32 tensor (N, C, H, W)."""
    tensor = th.as_tensor(np.asarray(images, dtype=np.float32))
    if tensor.ndim == 3:
        return tensor.unsqueeze(1)
    return tensor.permute(0, 3, 1, 2)


def ssim_to_set(image: np.ndarray, goals: np.ndarray, data_range: float = 255.0) -> np.ndarray:
    """
    SSIM between one image and each of ``N`` stored goal images, in one batched call.

    :param image: The image, shape ``(H, W)`` (grayscale) or ``(H, W, C)`` (channel last).
    :param goals: The stored images, shape ``(N, H, W)`` or ``(N, H, W, C)``, matching ``image``;
        ``N`` may be 0.
    :param data_range: Range of the pixel values (255 for uint8 images, 1 for images in [0, 1]),
        ``> 0``.
    :return: SSIM of ``image`` with each goal, float64 array of shape ``(N,)``, values in [-1, 1].
    """
    image = np.asarray(image)
    goals = np.asarray(goals)
    if not data_range > 0:
        raise ValueError(f"data_range must be > 0, got {data_range}")
    if image.ndim not in (2, 3):
        raise ValueError(f"image must have shape (H, W) or (H, W, C), got {image.shape}")
    if goals.ndim != image.ndim + 1 or goals.shape[1:] != image.shape:
        raise ValueError(f"goals must have shape (N, {', '.join(map(str, image.shape))}) to match image, got {goals.shape}")
    if min(image.shape[:2]) < 1 or (image.ndim == 3 and image.shape[2] < 1):
        raise ValueError(f"image must have at least one pixel and one channel, got {image.shape}")
    n_goals = goals.shape[0]
    if n_goals == 0:
        return np.zeros(0, dtype=np.float64)
    win_size = window_size(*image.shape[:2])
    goals_t = _to_nchw(goals)
    image_t = _to_nchw(image[None]).expand_as(goals_t)
    # pytorch_msssim squeezes spatial dimensions of size 1; with a 1x1 window, repeating a row or a
    # column leaves the pixel-wise SSIM map's mean unchanged.
    repeats = [1, 1, 2 if goals_t.shape[2] == 1 else 1, 2 if goals_t.shape[3] == 1 else 1]
    if repeats != [1, 1, 1, 1]:
        goals_t, image_t = goals_t.repeat(*repeats), image_t.repeat(*repeats)
    with th.no_grad():
        values = ssim(
            image_t,
            goals_t,
            data_range=data_range,
            size_average=False,
            win_size=win_size,
            win_sigma=WIN_SIGMA,
            K=(0.01, 0.03),
        )
    return values.double().numpy()


def ssim_pair(a: np.ndarray, b: np.ndarray, data_range: float = 255.0) -> float:
    """
    SSIM between two images of the same shape.

    :param a: Image of shape ``(H, W)`` or ``(H, W, C)``.
    :param b: Image of the same shape as ``a``.
    :param data_range: Range of the pixel values, ``> 0``.
    :return: Their SSIM in [-1, 1].
    """
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape:
        raise ValueError(f"b must have the same shape as a {a.shape}, got {b.shape}")
    return float(ssim_to_set(a, b[None], data_range=data_range)[0])
