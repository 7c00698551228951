"""Images resampled to a texture's texel centres."""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..device.choice import Device, or_default
from ..device.memory import run_on_host_arrays
from ..device.programs import Kernel, build
from ..device.sources import cl_source


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
    # 3x faster
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


def take_rows(rows: NDArray[Any], index: NDArray[np.integer]) -> NDArray[Any]:
    """``rows[index]``: the rows (N, ...) of ``rows`` at ``index``, by ``np.take`` where
    they are contiguous (8 ms against fancy indexing's 20 for 293 k rows of 3 floats of a
    texture 4096 map, the same values) and by fancy indexing where they are a view of a
    wider array (``np.take`` would first copy all of it: 0.2 s)."""
    if rows.flags.c_contiguous:
        return np.take(rows, index, axis=0)
    return rows[index]


def put_rows(rows: NDArray[Any], index: NDArray[np.integer], values: NDArray[Any]) -> None:
    """``rows[index] = values`` for C-contiguous ``rows`` (N, ...) and ``values`` of its
    dtype: each row written as one item of bytes by ``np.put`` (a texture 4096 normal
    map's 10 M rows of 3 floats: 0.04 s against fancy assignment's 0.16, the same
    bytes); fancy assignment otherwise."""
    values = np.asarray(values)
    if not (rows.flags.c_contiguous and rows.ndim > 1 and values.dtype == rows.dtype
            and values.shape[1:] == rows.shape[1:]):
        rows[index] = values
        return
    row = np.dtype((np.void, rows.dtype.itemsize * int(np.prod(rows.shape[1:]))))
    np.put(rows.reshape(rows.shape[0], -1).view(row).reshape(-1), index,
           np.ascontiguousarray(values).reshape(values.shape[0], -1).view(row).reshape(-1))


def resampled_texels(image: NDArray[Any], size: int, index: NDArray[np.integer]
                     ) -> NDArray[np.float32]:
    """The texels at flat indices ``index`` (N,) of ``resample_bilinear(image, size)``,
    (N, C): the same floats (each product and sum in the same order), without making
    the (S, S, C) image (201 MB at texture 4096 for the few texels a lookup reads)."""
    img = np.asarray(image, np.float32)
    h, w = img.shape[:2]
    pixels = img.reshape(h * w, *img.shape[2:])  # rows by flat pixel index: take_rows
    if (h, w) == (size, size):  # resample_bilinear's copy: each texel its own
        return take_rows(pixels, index)
    ty, tx = np.divmod(np.asarray(index), size)
    x0, fx = _axis_weights(w, size)
    y0, fy = _axis_weights(h, size)
    xa, xb = x0[tx], np.minimum(x0 + 1, w - 1)[tx]
    ya, yb = y0[ty] * w, np.minimum(y0 + 1, h - 1)[ty] * w
    left, right = (1 - fx)[tx, None], fx[tx, None]
    top = take_rows(pixels, ya + xa) * left
    top += take_rows(pixels, ya + xb) * right
    bottom = take_rows(pixels, yb + xa) * left
    bottom += take_rows(pixels, yb + xb) * right
    top *= (1 - fy)[ty, None]
    bottom *= fy[ty, None]
    top += bottom
    return top


_POWER_KERNEL = cl_source(__package__, "resample_power.cl")


def times_resampled_power(rgb: NDArray[np.float32], image: NDArray[Any], power: float,
                          device: Device | None = None) -> None:
    """``rgb *= max(resample_bilinear(image, S), 0) ** power`` in place for an (S, S, 3)
    float32 ``rgb`` and an (H, W, 3) ``image``, on the OpenCL device without making the
    resampled (S, S, 3) image (201 MB at texture 4096): a render's albedo weight after
    the blur (d'Eon et al. 2007's split) from the albedo's own texture. The same floats
    as numpy's for powers 1 and 1/2 (:data:`EXACT_POWERS`); others within OpenCL's pow.
    ``device``: where it runs (None: :func:`~..device.choice.or_default`)."""
    src = np.ascontiguousarray(image, np.float32)
    size = rgb.shape[0]
    if rgb.shape != (size, size, 3) or rgb.dtype != np.float32 or src.ndim != 3 or \
            src.shape[2] != 3 or not rgb.flags.c_contiguous:
        raise ValueError(f"rgb must be (S, S, 3) float32 and image (H, W, 3); got "
                         f"{rgb.shape} {rgb.dtype} and {src.shape}")
    h, w = src.shape[:2]
    if (h, w) == (size, size):  # resample_bilinear's copy: each texel its own
        x0 = y0 = np.arange(size)
        fx = fy = np.zeros(size, np.float32)
    else:
        (x0, fx), (y0, fy) = _axis_weights(w, size), _axis_weights(h, size)
    device = or_default(device)
    run_on_host_arrays(_power_kernel(device, EXACT_POWERS.get(power, 0)), device, (size, size),
                       [src, x0.astype(np.int32), fx, y0.astype(np.int32), fy, np.int32(w),
                        np.int32(h), np.int32(size), np.float32(power)], [rgb])


EXACT_POWERS = {1.0: 1, 0.5: 2}
"""The powers :func:`times_resampled_power` takes as numpy does, bit for bit, and their
kernels' POWER."""


@lru_cache(maxsize=6)
def _power_kernel(device: Device, mode: int) -> Any:
    return Kernel(build(device, _POWER_KERNEL, [f"-DPOWER={mode}"]),
                  "times_resampled_power", 2)
