"""A plausible skin albedo texture for an asset that has none (the sample face scan has
no colour): a tone per region, freckles and moles, as on the paper's figure 7 subject,
so that colour bleeding under the skin shows in a render.

The texture is painted in texture space on the asset's UV layout (unwrapped with xatlas
and written back first if the mesh has no usable UVs), spots are placed and sized in mm
on the surface, and the result is written as an ACEScg EXR and bound to the material's
``diffuseColor`` through a UsdUVTexture.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pxr import Sdf, Usd, UsdShade

from ..errors import InputError
from ..imageio import write_texture
from ..render.device.choice import Device
from ..render.diffusion.push_pull import dilate_charts, push_pull
from ..render.surface.texture_maps import TextureMaps, rasterize, texel_rows
from ..render.surface.unwrap import triangulate
from ..render.surface.uvs import ensure_skin_uvs
from ..usd.author import MTLX_NAME
from ..usd.io import export_layer_atomic
from ..usd.materialx import (
    MTLX_COLORSPACE,
    SubsurfaceMaps,
    author_usd_texture,
    mtlx_document,
    usd_network_values,
    write_mtlx_document,
)
from ..usd.schema import PROFILES_REL, WORKING_COLORSPACE

# Linear ACEScg tones; about sRGB (225, 170, 145) for the face, redder lips and nose.
REGION_TONES: dict[str, tuple[float, float, float]] = {
    "forehead": (0.60, 0.42, 0.31),
    "cheekbone": (0.62, 0.40, 0.31),
    "cheek": (0.63, 0.39, 0.31),
    "nose": (0.63, 0.38, 0.30),
    "chin": (0.58, 0.40, 0.31),
    "lips": (0.52, 0.22, 0.19),
}
DEFAULT_TONE = (0.60, 0.41, 0.31)
FRECKLE_TINT = np.array([0.74, 0.62, 0.52])
MOLE_TINT = np.array([0.28, 0.17, 0.12])
FRECKLE_DENSITY = {"cheek": 1.0, "cheekbone": 1.0, "nose": 0.9, "forehead": 0.25}
OTHER_FRECKLE_DENSITY = 0.05


@dataclass(frozen=True)
class Spots:
    """Pigment spots on the surface: centres (K, 3) in scene units, radii (K,) in mm and
    multiplicative tints (K, 3)."""

    centres: NDArray[np.float64]
    radii_mm: NDArray[np.float64]
    tints: NDArray[np.float64]


def _draw(weights: NDArray[Any], count: int, rng: np.random.Generator) -> NDArray[np.int64]:
    """``count`` indices drawn in proportion to ``weights`` (>= 0, some > 0) by inverse
    CDF: rng.choice(p=...) checks and normalises p on every call."""
    cdf = np.cumsum(weights)
    return np.minimum(np.searchsorted(cdf, rng.random(count) * cdf[-1], side="right"),
                      cdf.size - 1)


def place_spots(position: NDArray[Any], area_mm2: NDArray[Any], freckle_density: NDArray[Any],
                freckles: int = 700, moles: int = 5, seed: int = 7) -> Spots:
    """Freckles (0.3-1.0 mm) at surface points drawn in proportion to area times
    ``freckle_density``, and a few moles (1.0-1.8 mm) drawn in proportion to area
    (``position``, ``area_mm2`` and ``freckle_density`` per covered texel)."""
    rng = np.random.default_rng(seed)
    p = area_mm2 * freckle_density
    if not p.sum() > 0:
        return Spots(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)))
    freckle_at = _draw(p, freckles, rng)
    freckle_radii = rng.uniform(0.3, 1.0, freckles)
    freckle_tints = FRECKLE_TINT + rng.uniform(-0.06, 0.06, (freckles, 3))
    at = np.concatenate([freckle_at, _draw(area_mm2, moles, rng)])
    return Spots(position[at].astype(np.float64),
                 np.concatenate([freckle_radii, rng.uniform(1.0, 1.8, moles)]),
                 np.concatenate([freckle_tints, np.broadcast_to(MOLE_TINT, (moles, 3))]))


def paint_skin_albedo(maps: TextureMaps, region_names: tuple[str, ...],
                      meters_per_unit: float, seed: int = 7) -> NDArray[np.float32]:
    """The albedo map (S, S, 3) in linear ACEScg for ``maps``' layout."""
    from scipy.spatial import cKDTree  # lazy: 0.39 s to import

    covered = np.flatnonzero(maps.triangle.ravel() >= 0)
    pos = texel_rows(maps.surface[0], covered).astype(np.float64)
    # The texels' tree is built (scipy releases the GIL) while the tone is worked out:
    # 0.08-0.12 s at texture 1024, most of it hidden.
    with ThreadPoolExecutor(1) as pool:
        tree_ahead = pool.submit(cKDTree, pos, balanced_tree=False, compact_nodes=False)
        base, freckle_density = _region_tone(maps, covered, region_names)
        base = _spotted(base, pos, maps, covered, freckle_density, meters_per_unit, seed,
                        tree_ahead)
    out = np.zeros((maps.size * maps.size, 3), np.float32)
    out[covered] = np.clip(base, 0.0, 1.0)
    return out.reshape(maps.size, maps.size, 3)


def _region_tone(maps: TextureMaps, covered: NDArray[np.intp], region_names: tuple[str, ...]
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Each covered texel's tone (N, 3) and freckle density (N,): its regions' blended."""
    if maps.region_weights is None or not region_names:
        return (np.broadcast_to(np.asarray(DEFAULT_TONE), (covered.size, 3)).copy(),
                np.full(covered.size, OTHER_FRECKLE_DENSITY))
    tones = np.array([REGION_TONES.get(n, DEFAULT_TONE) for n in region_names])
    densities = np.array([FRECKLE_DENSITY.get(n, OTHER_FRECKLE_DENSITY) for n in region_names])
    weights = texel_rows(maps.region_weights, covered).astype(np.float64)
    return weights @ tones, weights @ densities


def _spotted(base: NDArray[Any], pos: NDArray[Any], maps: TextureMaps,
             covered: NDArray[np.intp], freckle_density: NDArray[Any],
             meters_per_unit: float, seed: int, tree_ahead: Any) -> NDArray[Any]:
    """The ``covered`` texels' albedo: ``base`` tone with blotchiness and pigment spots;
    ``tree_ahead`` is the future of a cKDTree of ``pos``."""
    # low-frequency blotchiness (+-4%), a function of the surface point so seams match
    mm = pos * meters_per_unit * 1000.0
    base *= 1.0 + 0.04 * np.sin(mm[:, :1] * 0.21 + 1.3) * np.sin(mm[:, 1:2] * 0.17 + 0.4)
    area_mm2 = np.take((maps.mm_per_texel_u * maps.mm_per_texel_v).ravel(),
                       covered).astype(np.float64)
    spots = place_spots(pos, area_mm2, freckle_density, seed=seed)
    if spots.radii_mm.size:
        # every spot's texels in one query (the spots' tints multiply, in any order);
        # unbalanced and not compacted: 2x faster to build
        tree = tree_ahead.result()
        scale = 1.0 / (meters_per_unit * 1000.0)  # mm -> scene units
        found = tree.query_ball_point(spots.centres, 2.5 * spots.radii_mm * scale,
                                      workers=-1, return_sorted=False)
        counts = np.fromiter((len(f) for f in found), np.int64, len(found))
        if counts.sum():
            which = np.repeat(np.arange(counts.size), counts)
            texel = np.fromiter(itertools.chain.from_iterable(found), np.intp, counts.sum())
            offset = np.take(pos, texel, axis=0)
            offset -= np.take(spots.centres, which, axis=0)
            d_mm = np.linalg.norm(offset, axis=1) / scale
            falloff = np.exp(-0.5 * (d_mm / (0.6 * spots.radii_mm[which])) ** 4)[:, None]
            np.multiply.at(base, texel, 1.0 - (1.0 - spots.tints[which]) * falloff)
    return base


def _wire_texture(edit: Any, material_path: str, rel: str,
                  maps: SubsurfaceMaps | None = None) -> dict[str, Any] | None:
    """``rel`` (relative to the material's layer) into the material's preview surface's
    diffuseColor through a UsdUVTexture reading ``st``, and into its OpenPBR network
    through MaterialX's image node (with ``maps``, relative likewise, its subsurface);
    returns the OpenPBR values (None without one)."""
    mat = UsdShade.Material(edit.GetPrimAtPath(material_path))
    surface = mat.ComputeSurfaceSource()[0]
    reader = UsdShade.Shader.Define(edit, f"{material_path}/StReader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    tex = UsdShade.Shader.Define(edit, f"{material_path}/AlbedoTexture")
    tex.CreateIdAttr("UsdUVTexture")
    file_input = tex.CreateInput("file", Sdf.ValueTypeNames.Asset)
    file_input.Set(Sdf.AssetPath(f"./{rel}"))
    file_input.GetAttr().SetColorSpace(WORKING_COLORSPACE)
    # "raw": no transfer function. UsdPreviewSurface's "auto" means the same for a float
    # EXR, but importers that guess (Blender 5.0) read "auto" as sRGB; the primaries are
    # said by the file attribute's colorSpace (ACEScg) and the EXR's chromaticities
    tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("raw")
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
        reader.CreateOutput("result", Sdf.ValueTypeNames.Float2))
    rgb = tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    surface.GetInput("diffuseColor").ConnectToSource(rgb)
    openpbr = edit.GetPrimAtPath(f"{material_path}/OpenPBR")
    if not openpbr:
        return None
    author_usd_texture(edit, material_path, f"./{rel}", MTLX_COLORSPACE, None if maps is None
                       else replace(maps, colour=f"./{maps.colour}",
                                    radius_scale=f"./{maps.radius_scale}"))
    return usd_network_values(UsdShade.Shader(openpbr))


def author_albedo_texture(stage: Any, mesh_path: str, texture: Path,
                          before_save: Callable[[], Any] | None = None,
                          maps: SubsurfaceMaps | None = None) -> str:
    """Bind ``texture`` (an ACEScg EXR beside the look layer) to the mesh's material and
    its regions' materials (:func:`_wire_texture`; the mesh's reads ``maps``' painted
    subsurface, paths beside the texture), rewrite look.mtlx to match; saves the
    materials' layer atomically and returns its path. ``before_save`` runs (and may
    raise) before anything is written: e.g. waiting for the textures themselves."""
    prim = stage.GetPrimAtPath(mesh_path)
    binding = UsdShade.MaterialBindingAPI(prim)
    material, _ = binding.ComputeBoundMaterial()
    if not material:
        raise InputError(f"{mesh_path} has no bound material to carry an albedo texture")
    layer = material.GetPrim().GetPrimStack()[0].layer
    if not layer.realPath:
        raise InputError(f"material {material.GetPath()} lives in an anonymous layer")
    paths = [material.GetPath()]
    for subset in binding.GetMaterialBindSubsets():
        bound, _ = UsdShade.MaterialBindingAPI(subset.GetPrim()).ComputeBoundMaterial()
        if bound and bound.GetPrim().GetPrimStack()[0].layer == layer \
                and bound.GetPath() not in paths:
            paths.append(bound.GetPath())
    edit = Usd.Stage.Open(layer)
    folder = Path(layer.realPath).resolve().parent

    def relative(path: str | Path) -> str:
        return Path(path).resolve().relative_to(folder).as_posix()

    rel = relative(texture)
    own = None if maps is None else SubsurfaceMaps(
        relative(maps.colour), relative(maps.radius_scale), maps.radius)
    networks = {}
    for path in paths:
        values = _wire_texture(edit, str(path), rel,
                               own if path == material.GetPath() else None)
        if values is not None:
            networks[path.name] = values
    document = None if not networks else mtlx_document(
        networks, rel, None if own is None else {material.GetPath().name: own})
    if before_save is not None:
        before_save()
    if document is not None:
        write_mtlx_document(Path(layer.realPath).parent / MTLX_NAME, document)
    export_layer_atomic(layer, layer.realPath)
    return str(layer.realPath)


ALBEDO_NAME = "albedo.exr"
"""The texture :func:`bake_sample_albedo` writes beside the asset."""


def bake_sample_albedo(asset: Path, size: int = 2048, seed: int = 7,
                       progress: Any = None, device: Device | None = None) -> Path:
    """Paint the sample albedo for the first skin mesh of ``asset`` (unwrapping it first
    when it has no usable UVs) and bind it; returns the texture's path. ``device``: the
    OpenCL device its maps are made on (None: the environment's)."""
    stage, scene, mesh, uv, uv_tris, _ = ensure_skin_uvs(asset, progress)
    maps = rasterize(mesh.mesh.points, triangulate(mesh.mesh), uv, uv_tris, size,
                     scene.meters_per_unit, mesh.region_weights, device)
    if progress:
        progress(f"paint albedo {size}x{size}")
    albedo = paint_skin_albedo(maps, mesh.region_names, scene.meters_per_unit, seed)
    folder = Path(asset).resolve().parent
    texture = folder / ALBEDO_NAME
    media = region_media(stage, mesh.path)
    painted = None
    if media is not None and maps.region_weights is not None:
        colour, scale, radius = paint_subsurface_maps(maps, albedo, media,
                                                      scene.meters_per_unit)
        painted = SubsurfaceMaps(str(folder / SUBSURFACE_COLOUR_NAME),
                                 str(folder / SUBSURFACE_SCALE_NAME), radius)
    image = _as_image(albedo, maps, device)
    # OpenImageIO makes the MIP-mapped textures without the GIL while MaterialX builds and
    # validates the material document (0.34 and 0.3 s at 1024); nothing is saved until
    # the textures are written
    with ThreadPoolExecutor(1) as pool:
        def write_all() -> None:
            write_texture(texture, image, WORKING_COLORSPACE)
            if painted is not None:
                write_texture(painted.colour, _as_image(colour, maps, device),
                              WORKING_COLORSPACE)
                write_texture(painted.radius_scale, _as_image(scale, maps, device),
                              DATA_COLORSPACE)

        written = pool.submit(write_all)
        author_albedo_texture(stage, mesh.path, texture, before_save=written.result,
                              maps=painted)
    return texture


SUBSURFACE_COLOUR_NAME = "subsurface_color.exr"
SUBSURFACE_SCALE_NAME = "subsurface_radius_scale.exr"
"""The blended subsurface maps :func:`bake_sample_albedo` writes beside the albedo."""
DATA_COLORSPACE = "data"
"""OCIO's name for values that are not colours (the radius scale)."""


def region_media(stage: Any, mesh_path: str) -> list[tuple[Any, Any]] | None:
    """Each region's (mean free path mm (3,), subsurface colour over total reflectance
    (3,)) from the media on its profile prims, in region order; None where an asset's
    profiles carry no media (authored before skinpipe wrote them)."""
    targets = stage.GetPrimAtPath(mesh_path).GetRelationship(PROFILES_REL).GetTargets()
    out = []
    for target in targets:
        prim = stage.GetPrimAtPath(target)
        mfp = prim.GetAttribute("medium:meanFreePathMm").Get() if prim else None
        colour = prim.GetAttribute("medium:subsurfaceColor").Get() if prim else None
        total = prim.GetAttribute("medium:totalReflectance").Get() if prim else None
        if mfp is None or colour is None or total is None:
            return None
        out.append((np.array(mfp, np.float64),
                    np.array(colour, np.float64) / np.maximum(np.array(total), 1e-6)))
    return out or None


def paint_subsurface_maps(maps: TextureMaps, albedo: NDArray[np.float32],
                          media: list[tuple[Any, Any]], meters_per_unit: float
                          ) -> tuple[NDArray[np.float32], NDArray[np.float32], float]:
    """OpenPBR's subsurface colour (the albedo times the regions' C / R, blended by the
    region weights) and radius scale (the blended mean free path over its largest, the
    radius, in scene units) for ``maps``' layout: (colour, scale, radius)."""
    covered = np.flatnonzero(maps.triangle.ravel() >= 0)
    assert maps.region_weights is not None
    w = texel_rows(maps.region_weights, covered).astype(np.float64)
    w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-12)
    mfp_units = np.array([m for m, _ in media]) / (meters_per_unit * 1000.0)
    radius = float(mfp_units.max())
    colour = np.zeros((maps.size * maps.size, 3), np.float32)
    scale = np.zeros_like(colour)
    colour[covered] = np.clip(albedo.reshape(-1, 3)[covered] * (w @ np.array(
        [f for _, f in media])), 0.0, 1.0)
    scale[covered] = w @ mfp_units / radius
    shape = (maps.size, maps.size, 3)
    return colour.reshape(shape), scale.reshape(shape), radius


def _as_image(texels: NDArray[np.float32], maps: TextureMaps, device: Device | None
              ) -> NDArray[np.float32]:
    """A texture-space map as the texture is written: charts pushed and dilated beyond
    their borders (MIP levels and filtering read there), row 0 at v = 1. ``texels`` is
    filled in place (its covered texels keep their values)."""
    return dilate_charts(push_pull(texels, maps.coverage, in_place=True, device=device),
                         maps.coverage)[::-1]
