"""Image error metrics against a reference: MAE, MPE, MNE (thesis Eq. 5.1) and relMSE.

All take linear-radiance images of equal shape, (H, W, C) float.
"""

from __future__ import annotations

import numpy as np

from .errors import ImageError


def compare(image: np.ndarray, reference: np.ndarray, eps: float = 1e-2) -> dict[str, float]:
    """Errors of ``image`` against ``reference``.

    MAE = mean |I - R|; MPE = mean max(I - R, 0); MNE = mean min(I - R, 0), so MAE = MPE - MNE
    (thesis Eq. 5.1: positive and negative errors kept apart, since the method's bias changes
    sign between lit regions and silhouettes). relMSE = mean (I - R)^2 / (R^2 + eps).
    ``ref_mean`` is the reference's mean, so MAE can be read as a fraction of it.
    """
    image = np.asarray(image, np.float64)
    reference = np.asarray(reference, np.float64)
    if image.shape != reference.shape:
        raise ImageError(f"images differ in size: {image.shape} vs {reference.shape}")
    d = image - reference
    return {
        "MAE": float(np.abs(d).mean()),
        "MPE": float(np.maximum(d, 0).mean()),
        "MNE": float(np.minimum(d, 0).mean()),
        "relMSE": float((d * d / (reference * reference + eps)).mean()),
        "ref_mean": float(reference.mean()),
    }


def binned(image: np.ndarray, k: int = 4) -> np.ndarray:
    """Means over k x k pixel blocks (edges that do not fill a block are dropped)."""
    image = np.asarray(image, np.float64)
    h, w = image.shape[0] // k * k, image.shape[1] // k * k
    return image[:h, :w].reshape(h // k, k, w // k, k, -1).mean(axis=(1, 3))


def bias_metrics(image: np.ndarray, reference: np.ndarray, k: int = 4) -> dict[str, float]:
    """Bias, with per-pixel noise mostly averaged away (docs/method.md, "What is known about accuracy"):
    relMAE of k x k-binned images and the ratio of the image means."""
    a, b = binned(image, k), binned(reference, k)
    return {
        "binned_relMAE": float(np.abs(a - b).mean() / max(b.mean(), 1e-12)),
        "mean_ratio": float(np.mean(image) / max(float(np.mean(reference)), 1e-12)),
    }
