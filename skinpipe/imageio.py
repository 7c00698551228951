"""Guarded image IO (OpenImageIO) and colour conversion (OpenColorIO).

OpenImageIO reports most failures through return values rather than exceptions, and
reads some bad files "successfully" (a PNG renamed .exr is read as PNG, a failed
``read_image`` leaves zeros). Every call here checks what came back and raises
:class:`InputError` naming the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio
import PyOpenColorIO as OCIO
from numpy.typing import NDArray

from .errors import InputError
from .fileio import atomic_path

ACESCG = "lin_ap1_scene"
CHROMATICITIES = {
    # ACEScg: AP1 primaries and the ACES white point (Academy S-2014-004, table 1)
    ACESCG: (0.713, 0.293, 0.165, 0.830, 0.128, 0.044, 0.32168, 0.33767),
    # linear Rec.709 / sRGB primaries, D65 (ITU-R BT.709-6)
    "lin_rec709_scene": (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290),
}
"""OpenEXR ``chromaticities`` (red, green, blue, white xy) by OCIO interop id: an EXR
without the attribute means Rec.709 primaries by the OpenEXR standard."""
"""OCIO interop id of ACEScg, the scene-linear working space of every skinpipe image."""

# Extension -> OpenImageIO format names that may legitimately carry it.
_FORMATS = {
    ".exr": {"openexr"}, ".png": {"png"}, ".tif": {"tiff"}, ".tiff": {"tiff"},
    ".jpg": {"jpeg"}, ".jpeg": {"jpeg"},
}


@dataclass(frozen=True)
class LoadedImage:
    """Pixels as float32 (H, W, 3); integer formats normalised to [0, 1] code values."""

    path: Path
    pixels: NDArray[np.float32]
    is_float: bool
    bits: int
    exposure_s: float | None
    format_name: str


def oiio_error(obj: Any = None) -> str:
    """OpenImageIO's pending error message (global, or of ``obj``): its text can hold bytes
    of a corrupt file that are not UTF-8, which the binding would raise on."""
    try:
        return (obj if obj is not None else oiio).geterror()
    except UnicodeDecodeError:
        return "(the reader's message is not UTF-8 text: a corrupt file?)"


def read_image(path: str | Path, max_pixels: int = 64_000_000) -> LoadedImage:
    """Read an RGB(A) image with every OpenImageIO failure turned into an InputError."""
    path = Path(path)
    if not path.is_file():
        raise InputError("no such image file", path)
    if path.stat().st_size == 0:
        raise InputError("empty image file", path)
    expected = _FORMATS.get(path.suffix.lower())
    if expected is None:
        raise InputError(f"unsupported image type {path.suffix!r} (use {sorted(_FORMATS)})", path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"unreadable image: {oiio_error() or 'unknown error'}", path)
    try:
        fmt = inp.format_name()
        if fmt not in expected:
            raise InputError(f"file content is {fmt!r} but the name says {path.suffix}", path)
        spec = inp.spec()
        if spec.width <= 0 or spec.height <= 0 or spec.width * spec.height > max_pixels:
            raise InputError(f"implausible size {spec.width}x{spec.height}", path)
        if spec.nchannels not in (1, 3, 4):
            raise InputError(f"{spec.nchannels} channels; need 1 (grey), 3 or 4 (RGB[A])", path)
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        err = oiio_error(inp)
        if pixels is None or err:
            raise InputError(f"cannot read pixels (truncated?): {err or 'no data'}", path)
        exposure = spec.getattribute("ExposureTime")
        basetype = spec.format.basetype
    finally:
        inp.close()
    pixels = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    if spec.nchannels == 1:
        pixels = np.repeat(pixels, 3, axis=2)
    pixels = np.ascontiguousarray(pixels[..., :3])
    if not np.all(np.isfinite(pixels)):
        bad = int(np.count_nonzero(~np.isfinite(pixels)))
        raise InputError(f"{bad} non-finite (NaN/inf) pixel value(s)", path)
    is_float = basetype in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE)
    bits = {oiio.UINT8: 8, oiio.UINT16: 16}.get(basetype, 32)
    exposure_s = float(exposure) if isinstance(exposure, int | float) and exposure > 0 else None
    return LoadedImage(path, pixels, is_float, bits, exposure_s, fmt)


def _colour_header(spec: Any, colorspace: str) -> None:
    """The colour space as OIIO, OCIO and OpenEXR read it (``oiio:ColorSpace`` and
    ``chromaticities``), and no write time (OpenEXR ``capDate``): the same pixels give
    the same file."""
    spec.attribute("oiio:ColorSpace", colorspace)
    if colorspace in CHROMATICITIES:
        spec.attribute("chromaticities", oiio.TypeDesc("float[8]"), CHROMATICITIES[colorspace])
    spec.attribute("DateTime", "")


def write_exr(
    path: str | Path, pixels: NDArray[Any], colorspace: str = ACESCG,
    attributes: dict[str, Any] | None = None, channel_names: tuple[str, ...] | None = None,
    half: bool = False,
) -> Path:
    """Write a float EXR atomically, with the colour space in its header: the OCIO interop
    id (``oiio:ColorSpace``) and, for the spaces of :data:`CHROMATICITIES`, OpenEXR's
    ``chromaticities``. ``half``: 16-bit float pixels (what most pipelines keep beauty
    in; values above 65504 become inf, so the caller decides)."""
    path = Path(path)
    arr = np.ascontiguousarray(pixels, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    spec = oiio.ImageSpec(arr.shape[1], arr.shape[0], arr.shape[2], "half" if half else "float")
    _colour_header(spec, colorspace)
    spec.attribute("compression", "zip")
    if channel_names:
        spec.channelnames = channel_names
    for key, value in (attributes or {}).items():
        spec.attribute(key, value)
    _write(path, spec, arr)
    return path


def write_texture(path: str | Path, pixels: NDArray[Any], colorspace: str = ACESCG) -> Path:
    """Write a texture as renderers expect it, atomically: a tiled, MIP-mapped half-float
    OpenEXR made by OpenImageIO's ``make_texture`` (what ``maketx`` does), with the
    colour space and chromaticities of :func:`write_exr`."""
    path = Path(path)
    arr = np.ascontiguousarray(pixels, dtype=np.float32)
    spec = oiio.ImageSpec(arr.shape[1], arr.shape[0], arr.shape[2], "float")
    _colour_header(spec, colorspace)
    buf = oiio.ImageBuf(spec)
    buf.set_pixels(oiio.ROI(), arr)
    config = oiio.ImageSpec()
    config.format = oiio.TypeDesc("half")
    config.attribute("compression", "zip")
    # no SHA-1 fingerprint of the pixels (maketx's default, for a texture cache to find
    # duplicate files): 40 ms of a 1024^2 texture's 240, and a file per asset has none
    config.attribute("maketx:hash", 0)
    with atomic_path(path) as tmp:
        if not oiio.ImageBufAlgo.make_texture(oiio.MakeTxTexture, buf, str(tmp), config):
            raise OSError(f"{path}: make_texture failed: {oiio_error()}")
    return path


def write_ldr(
    path: str | Path, pixels: NDArray[Any], bits: int, attributes: dict[str, Any] | None = None
) -> Path:
    """Write an 8/16-bit PNG or TIFF atomically from [0, 1] code values (rounded, clipped)."""
    path = Path(path)
    top = (1 << bits) - 1
    dtype = np.uint8 if bits == 8 else np.uint16
    arr = np.clip(np.rint(np.asarray(pixels, dtype=np.float64) * top), 0, top).astype(dtype)
    fmt = "uint8" if bits == 8 else "uint16"
    spec = oiio.ImageSpec(arr.shape[1], arr.shape[0], arr.shape[2], fmt)
    if path.suffix.lower() in (".tif", ".tiff"):
        spec.attribute("compression", "zip")
    if path.suffix.lower() == ".png":
        # zlib's fastest level: a 768 x 768 preview in 50 ms and 220 KiB, against 154 ms
        # and 173 KiB at OpenImageIO's default 6 (the same pixels)
        spec.attribute("png:compressionLevel", 1)
    for key, value in (attributes or {}).items():
        spec.attribute(key, value)
    _write(path, spec, np.ascontiguousarray(arr))
    return path


def _write(path: Path, spec: Any, arr: NDArray[Any]) -> None:
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise OSError(f"{path}: cannot create an image writer: {oiio_error()}")
        try:
            if not out.open(str(tmp), spec):
                raise OSError(f"{path}: {oiio_error(out)}")
            if not out.write_image(arr):
                raise OSError(f"{path}: {oiio_error(out)}")
        finally:
            out.close()


# ------------------------------------------------------------------------------- colour


@lru_cache(maxsize=4)
def ocio_config(source: str = "ocio://default") -> Any:
    """An OCIO config from a file path or a built-in URI (``ocio://default``)."""
    try:
        return OCIO.Config.CreateFromFile(source)
    except (OCIO.Exception, OCIO.ExceptionMissingFile) as exc:
        # ExceptionMissingFile is not an OCIO.Exception in the Python bindings
        raise InputError(f"cannot load OCIO config {source!r}: {exc}") from exc


def check_colorspace(name: str, config_source: str = "ocio://default") -> str:
    """The canonical name of a colour space (name, alias or interop id), else InputError."""
    cs = ocio_config(config_source).getColorSpace(name)
    if cs is None:
        raise InputError(f"unknown OCIO colour space {name!r} in {config_source}")
    return str(cs.getName())


@lru_cache(maxsize=32)
def _cpu_processor(src: str, dst: str, config_source: str) -> Any:
    return ocio_config(config_source).getProcessor(src, dst).getDefaultCPUProcessor()


def convert_colorspace(
    pixels: NDArray[Any], src: str, dst: str = ACESCG, config_source: str = "ocio://default"
) -> NDArray[np.float32]:
    """Convert (..., 3) pixels between OCIO colour spaces; returns a new float32 array.

    OCIO spreads a NaN in one channel to all three; callers pass finite data only.
    """
    check_colorspace(src, config_source)
    check_colorspace(dst, config_source)
    out = np.ascontiguousarray(pixels, dtype=np.float32).copy()
    flat = out.reshape(-1, 3)
    _cpu_processor(src, dst, config_source).applyRGB(flat)
    return out


def colorspace_matrix(src: str, dst: str = ACESCG) -> NDArray[np.float64]:
    """The 3x3 matrix M with dst = M @ src for two linear colour spaces (probed via OCIO)."""
    basis = np.eye(3, dtype=np.float32)
    return convert_colorspace(basis, src, dst).astype(np.float64).T
