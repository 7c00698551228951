"""Shading at the camera's hits: texture lookups (bilinear, in bands), the albedo in
texture space and its split around the diffusion, and the flux checks."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import OpenImageIO as oiio
from numpy.typing import NDArray

from ..errors import InputError
from ..imageio import (
    convert_colorspace,
    read_image,
)
from ..profile.medium import MediumEstimate
from ..usd.openpbr import region_medium
from .bands import in_bands
from .device.choice import Device
from .diffusion.push_pull import extrapolate_charts, push_pull
from .diffusion.surface_terms import SurfaceLight
from .light.raytrace import RayScene
from .scene import SceneMesh
from .surface.resample import (
    put_rows,
    resample_bilinear,
    resampled_texels,
    take_rows,
    times_resampled_power,
)
from .surface.texture_maps import (
    TextureMaps,
)


def normal_map(normals: NDArray[np.float32], texel: NDArray[np.intp],
               shape: tuple[int, int]) -> NDArray[np.float32]:
    """The (H, W, 3) normal map of ``shape`` from its covered texels' rows (``normals``
    at flat indices ``texel``), zero elsewhere as :func:`~.texture_maps.rasterize` leaves
    it: the same map, made again from the rows the irradiance keeps."""
    out = np.zeros((*shape, 3), np.float32)
    put_rows(out.reshape(-1, 3), texel, normals)
    return out


LOOKUP_BAND_POINTS = 1 << 17
"""Points a band of :func:`bilinear` looks up on one core (1.5 MB of RGB float32 out)."""


def bilinear(texture: NDArray[Any], uv: NDArray[Any]) -> NDArray[np.float32]:
    """Bilinear lookup of a (S, S, C) texture map (row j holds v = (j + 0.5) / S) at uv."""
    size_v, size_u = texture.shape[:2]
    flat = np.asarray(texture, np.float32).reshape(size_v * size_u, -1)
    # in bands of points on the host's cores: each point's four reads miss the cache
    # of a large map (the demo face's radiance at texture 4096, 0.6 M hits: 0.2 s on
    # one core)
    def band(s: slice) -> NDArray[np.float32]:
        return bilinear_of(lambda i: take_rows(flat, i), (size_v, size_u), uv[s])

    if len(uv) <= LOOKUP_BAND_POINTS:
        return band(slice(None))
    return np.concatenate(in_bands(band, len(uv), LOOKUP_BAND_POINTS))


def bilinear_of(texels: Callable[[NDArray[np.int64]], NDArray[np.float32]],
                shape: tuple[int, int], uv: NDArray[Any]) -> NDArray[np.float32]:
    """:func:`bilinear` of a texture of ``shape`` (rows, columns) that ``texels`` gives
    at flat texel indices (N,) as (N, C), rather than a map held whole."""
    size_v, size_u = shape
    x = np.clip(np.asarray(uv[:, 0], np.float32) * size_u - 0.5, 0, size_u - 1)
    y = np.clip(np.asarray(uv[:, 1], np.float32) * size_v - 0.5, 0, size_v - 1)
    x0 = np.minimum(x.astype(np.int64), size_u - 2 if size_u > 1 else 0)
    y0 = np.minimum(y.astype(np.int64), size_v - 2 if size_v > 1 else 0)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    dx, dy = int(size_u > 1), (size_u if size_v > 1 else 0)
    i = y0 * size_u + x0
    top = texels(i) * (1 - fx) + texels(i + dx) * fx
    bottom = texels(i + dy) * (1 - fx) + texels(i + dy + dx) * fx
    return top * (1 - fy) + bottom * fy


def albedo_image(mesh: SceneMesh, working: str) -> tuple[NDArray[np.float32], str]:
    """The albedo's own image, linear in the working space, in texture row order (the
    bottom row first; (1, 1, 3) for a constant), and what it came from. Its texture-space
    map is the image resampled (:func:`albedo_texture`)."""
    albedo = mesh.albedo
    if albedo.texture is None:
        return np.asarray(albedo.constant, np.float32).reshape(1, 1, 3), \
            "constant diffuseColor"
    img = read_image(albedo.texture)
    cs = albedo.colorspace or (working if img.is_float else "srgb_tx")
    px = img.pixels if cs == working else convert_colorspace(img.pixels, cs, working)
    # texture-space row j holds v = (j + 0.5) / size; image row 0 is the top (v = 1)
    return np.ascontiguousarray(px[::-1, :, :3], dtype=np.float32), f"{albedo.texture} ({cs})"


def mean_albedo(mesh: SceneMesh, working: str) -> NDArray[np.float64]:
    """The albedo's mean over its image (RGB, linear in the working space): its
    coarsest MIP level where the texture has levels (a tiled EXR made as renderers
    take one), else the whole image's mean."""
    albedo = mesh.albedo
    if albedo.texture is None:
        return np.asarray(albedo.constant, np.float64)
    image = oiio.ImageInput.open(str(albedo.texture))
    if image is None:
        raise InputError(f"cannot read the albedo texture: {oiio.geterror()}", albedo.texture)
    try:
        level = 0
        while image.seek_subimage(0, level + 1):
            level += 1
        image.seek_subimage(0, level)
        spec = image.spec()
        px = image.read_image(0, level, 0, spec.nchannels, oiio.FLOAT)
        is_float = spec.format.basetype in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE)
    finally:
        image.close()
    if px is None or not np.all(np.isfinite(px)):
        raise InputError("the albedo texture does not read back whole", albedo.texture)
    # decoded per pixel before the mean (sRGB's curve is not linear); every k-th pixel
    # of a large level is plenty for a mean
    px = np.asarray(px, np.float32).reshape(spec.height, spec.width, spec.nchannels)
    if spec.nchannels < 3:  # grey: read_image's rule
        px = np.repeat(px[..., :1], 3, axis=2)
    k = max(1, max(px.shape[:2]) // 256)
    sample = np.ascontiguousarray(px[::k, ::k, :3]).reshape(-1, 3)
    cs = albedo.colorspace or (working if is_float else "srgb_tx")
    if cs != working:
        sample = convert_colorspace(sample, cs, working)
    return sample.mean(axis=0).astype(np.float64)


def skin_media(mesh: SceneMesh, mean: NDArray[np.float64]
               ) -> tuple[NDArray[np.float64], list[MediumEstimate] | None, str | None]:
    """The mesh's ``mean`` albedo (:func:`mean_albedo`) as the media take it, and each
    region's medium made to reflect it (:func:`~skinpipe.usd.openpbr.region_medium`, the
    one OpenPBR is given): what the angular law and the light through thin parts scatter
    by; None and why where a profile inverts to no medium."""
    albedo = np.clip(mean, 1e-4, 1.0)
    level = (float(albedo[0]), float(albedo[1]), float(albedo[2]))
    try:
        return albedo, [region_medium(fit, None, level) for fit in mesh.fits], None
    except InputError as exc:
        return albedo, None, f"{mesh.path}: no medium for the angular law and thin parts ({exc})"


def media_summary(media: list[MediumEstimate]) -> dict[str, Any]:
    """``render.json``'s record of the media, per region."""
    return {"single_scattering_albedo": [m.single_scattering_albedo.round(5).tolist()
                                         for m in media],
            "mean_free_path_mm": [m.mean_free_path_mm.round(5).tolist() for m in media],
            "anisotropy": [m.anisotropy for m in media]}


def albedo_texture(image: NDArray[np.float32], size: int) -> NDArray[np.float32]:
    """The albedo map (S, S, 3) of :func:`albedo_image`'s ``image``: resampled to the
    texel centres, bilinear, and no less than 0."""
    out = resample_bilinear(image, size)
    return np.clip(out, 0.0, None, out=out)


def albedo_texels(image: NDArray[np.float32], size: int
                  ) -> Callable[[NDArray[np.int64]], NDArray[np.float32]]:
    """The texels of ``albedo_texture(image, size)`` at flat indices, the same floats,
    for :func:`bilinear_of`: lookups without the map."""
    def texels(index: NDArray[np.int64]) -> NDArray[np.float32]:
        out = resampled_texels(image, size, index)
        return np.clip(out, 0.0, None, out=out)
    return texels


# ------------------------------------------------------------------------ renderer


def ray_owners(camera_rays: RayScene, prim: NDArray[Any]) -> NDArray[Any]:
    """Per ray the (mesh, triangle) of the scene its hit ``prim`` in ``camera_rays``
    belongs to, (-1, -1) for a miss."""
    return np.where(prim[:, None] >= 0, camera_rays.owner[np.maximum(prim, 0)], -1)


def mesh_hits(owner: NDArray[Any], hits: tuple[NDArray[Any], ...], mesh: int
              ) -> tuple[NDArray[np.intp], NDArray[Any], NDArray[np.float64]]:
    """The rays whose first hit is on scene mesh ``mesh`` (indices), their triangles
    and barycentrics (N, 3, 1), from :func:`ray_owners` and the hits (prim, u, v, t)."""
    _, bu, bv, _ = hits
    sel = np.flatnonzero(owner[:, 0] == mesh)
    b = np.stack([1 - bu[sel] - bv[sel], bu[sel], bv[sel]], axis=1)[:, :, None]
    return sel, owner[sel, 1], b


def times_albedo_power(rgb: NDArray[np.float32], albedo: NDArray[np.float32], power: float,
                       rows: int = 256) -> None:
    """``rgb *= albedo ** power`` in place (the albedo split's weights before and after
    the blur, d'Eon et al. 2007), a square root for 0.5 (the default) rather than a
    general power, in bands of ``rows`` rows: the whole texture's weights at once were
    201 MB of new memory at texture 4096, at the diffusion's peak."""
    for y in range(0, rgb.shape[0], rows):
        band = albedo[y:y + rows]
        rgb[y:y + rows] *= np.sqrt(band) if power == 0.5 else np.power(band, power)


def times_albedo_weight(rgb: NDArray[np.float32], albedo: NDArray[np.float32] | None,
                        image: NDArray[np.float32] | None, power: float,
                        device: Device | None = None) -> None:
    """``rgb *= albedo ** power`` in place from the albedo map where one was made
    (:func:`times_albedo_power`), else from the albedo's own image on the device
    (:func:`~.resample.times_resampled_power`: the same floats for the powers of
    :data:`~.resample.EXACT_POWERS`, the only ones a render asks of it without a map)."""
    if albedo is not None:
        times_albedo_power(rgb, albedo, power)
    else:
        assert image is not None
        times_resampled_power(rgb, image, power, device)


def exitant_radiance(rgb: NDArray[np.float32], albedo: NDArray[np.float32] | None,
                     image: NDArray[np.float32] | None, power: float, coverage: NDArray[Any],
                     device: Device) -> NDArray[np.float32]:
    """The exitant radiance texture of diffused light ``rgb`` (H, W, 3; in place): times
    albedo^``power`` (:func:`times_albedo_weight`) / pi, pushed and pulled into the texels
    off the charts, continued linearly beside them (:mod:`.diffusion.push_pull`)."""
    times_albedo_weight(rgb, albedo, image, power, device)
    rgb *= np.float32(1.0 / math.pi)
    return extrapolate_charts(push_pull(rgb, coverage, in_place=True, device=device), coverage)


def surface_flux(rgb: NDArray[np.float32], maps: TextureMaps, rows: int = 256) -> float:
    """The flux of a texture of irradiance or radiance exitance ``rgb`` (H, W, 3) over its
    charts, summed over channels: sum of value x texel area in mm^2 (mm per texel along u
    times along v) x coverage. In bands of ``rows`` rows: the areas of the whole texture
    at once were 67 MB of new memory at texture 4096, at the diffusion's peak."""
    def flux(band: slice) -> float:
        area = maps.texel_area_mm2(band) * maps.coverage[band]
        return float((area.ravel() @ rgb[band].reshape(-1, 3)).sum(dtype=np.float64))

    total = 0.0
    for part in in_bands(flux, rgb.shape[0], rows):  # on the cores; added in band order
        total += part
    return total


def surface_radiance(light: SurfaceLight, device: Device, position_mm: NDArray[Any],
                     normal: NDArray[Any], albedo: NDArray[Any], power: float
                     ) -> NDArray[np.float32]:
    """The exitant radiance of the wide terms' ``light`` at surface points
    (:meth:`~.diffusion.surface_terms.SurfaceLight.at`), times albedo^``power`` / pi
    as the texture's radiance (:func:`times_albedo_weight`)."""
    rgb = light.at(device, position_mm, normal)
    rgb *= np.power(np.maximum(albedo, 0.0), np.float32(power)) * np.float32(1.0 / math.pi)
    return rgb
