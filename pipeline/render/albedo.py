"""A plausible skin albedo texture for an asset that has none (the sample face scan has
no colour): a tone per region, freckles and moles, as on the paper's figure 7 subject,
so that colour bleeding under the skin shows in a render.

The texture is painted in texture space on the asset's UV layout (unwrapped with xatlas
and written back first if the mesh has no usable UVs), spots are placed and sized in mm
on the surface, and the result is written as an ACEScg EXR and bound to the material's
``diffuseColor`` through a UsdUVTexture.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pxr import Sdf, Usd, UsdShade

from ..errors import InputError
from ..imageio import write_texture
from ..usd.author import MTLX_NAME
from ..usd.io import export_layer_atomic
from ..usd.materialx import MTLX_COLORSPACE, author_usd_texture, usd_network_values, write_mtlx
from ..usd.schema import WORKING_COLORSPACE
from .push_pull import dilate_charts, push_pull
from .renderer import ensure_skin_uvs
from .texture_maps import TextureMaps, rasterize
from .unwrap import triangulate

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


@dataclass(frozen=True)
class Spot:
    centre: NDArray[np.float64]  # scene units
    radius_mm: float
    tint: NDArray[np.float64]


def place_spots(maps: TextureMaps, region_names: tuple[str, ...],
                freckles: int = 700, moles: int = 5, seed: int = 7) -> list[Spot]:
    """Freckles (0.3-1.0 mm) where the region densities say, and a few moles (1.0-1.8 mm),
    at random surface points drawn in proportion to surface area."""
    rng = np.random.default_rng(seed)
    covered = maps.triangle >= 0
    area = (maps.mm_per_texel_u * maps.mm_per_texel_v)[covered].astype(np.float64)
    pos = maps.position[covered].astype(np.float64)
    density = np.full(area.size, 0.05)
    if maps.region_weights is not None:
        rw = maps.region_weights[covered]
        density = np.zeros(area.size)
        for r, name in enumerate(region_names):
            density += rw[:, r] * FRECKLE_DENSITY.get(name, 0.05)
    p = area * density
    if not p.sum() > 0:
        return []
    p /= p.sum()
    spots = []
    for i in rng.choice(area.size, size=freckles, p=p):
        spots.append(Spot(pos[i], float(rng.uniform(0.3, 1.0)),
                          FRECKLE_TINT + rng.uniform(-0.06, 0.06, 3)))
    uniform = area / area.sum()
    for i in rng.choice(area.size, size=moles, p=uniform):
        spots.append(Spot(pos[i], float(rng.uniform(1.0, 1.8)), MOLE_TINT))
    return spots


def paint_skin_albedo(maps: TextureMaps, region_names: tuple[str, ...],
                      meters_per_unit: float, seed: int = 7) -> NDArray[np.float32]:
    """The albedo map (S, S, 3) in linear ACEScg for ``maps``' layout."""
    from scipy.spatial import cKDTree  # lazy: 0.39 s to import

    covered = maps.triangle >= 0
    out = np.zeros((*covered.shape, 3), np.float32)
    tones = np.array([REGION_TONES.get(n, DEFAULT_TONE) for n in region_names])
    if maps.region_weights is not None and len(region_names):
        base = maps.region_weights[covered] @ tones
    else:
        base = np.broadcast_to(np.asarray(DEFAULT_TONE), (int(covered.sum()), 3)).copy()
    pos = maps.position[covered].astype(np.float64)
    # low-frequency blotchiness (+-4%), a function of the surface point so seams match
    mm = pos * meters_per_unit * 1000.0
    base *= 1.0 + 0.04 * np.sin(mm[:, :1] * 0.21 + 1.3) * np.sin(mm[:, 1:2] * 0.17 + 0.4)
    spots = place_spots(maps, region_names, seed=seed)
    if spots:
        # every spot's texels in one query (the spots' tints multiply, in any order)
        tree = cKDTree(pos, balanced_tree=False, compact_nodes=False)  # 2x faster to build
        scale = 1.0 / (meters_per_unit * 1000.0)  # mm -> scene units
        centres = np.array([sp.centre for sp in spots])
        radii = np.array([sp.radius_mm for sp in spots])
        tints = np.array([sp.tint for sp in spots])
        found = tree.query_ball_point(centres, 2.5 * radii * scale, workers=-1,
                                      return_sorted=False)
        counts = np.fromiter((len(f) for f in found), np.int64, len(found))
        if counts.sum():
            which = np.repeat(np.arange(len(spots)), counts)
            texel = np.concatenate([np.asarray(f, np.int64) for f in found if f])
            d_mm = np.linalg.norm(pos[texel] - centres[which], axis=1) / scale
            falloff = np.exp(-0.5 * (d_mm / (0.6 * radii[which])) ** 4)[:, None]
            np.multiply.at(base, texel, 1.0 - (1.0 - tints[which]) * falloff)
    out[covered] = np.clip(base, 0.0, 1.0)
    return out


def author_albedo_texture(stage: Any, mesh_path: str, texture: Path) -> str:
    """Bind ``texture`` (an ACEScg EXR beside the look layer) to the mesh's material's
    diffuseColor through a UsdUVTexture reading ``st``; saves the material's layer
    atomically and returns its path."""
    prim = stage.GetPrimAtPath(mesh_path)
    material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
    if not material:
        raise InputError(f"{mesh_path} has no bound material to carry an albedo texture")
    layer = material.GetPrim().GetPrimStack()[0].layer
    if not layer.realPath:
        raise InputError(f"material {material.GetPath()} lives in an anonymous layer")
    edit = Usd.Stage.Open(layer)
    mat = UsdShade.Material(edit.GetPrimAtPath(material.GetPath()))
    surface = mat.ComputeSurfaceSource()[0]
    base = str(mat.GetPath())
    reader = UsdShade.Shader.Define(edit, f"{base}/StReader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    tex = UsdShade.Shader.Define(edit, f"{base}/AlbedoTexture")
    tex.CreateIdAttr("UsdUVTexture")
    rel = Path(texture).resolve().relative_to(Path(layer.realPath).resolve().parent)
    file_input = tex.CreateInput("file", Sdf.ValueTypeNames.Asset)
    file_input.Set(Sdf.AssetPath(f"./{rel.as_posix()}"))
    file_input.GetAttr().SetColorSpace(WORKING_COLORSPACE)
    # "auto": the file says what it is (colorSpace metadata, USD's name for ACEScg, and the
    # EXR's chromaticities), rather than "raw" (taken as the renderer's working space)
    tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("auto")
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
        reader.CreateOutput("result", Sdf.ValueTypeNames.Float2))
    rgb = tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    surface.GetInput("diffuseColor").ConnectToSource(rgb)
    openpbr = edit.GetPrimAtPath(f"{base}/OpenPBR")
    if openpbr:  # the MaterialX network reads it with MaterialX's own image node
        author_usd_texture(edit, base, f"./{rel.as_posix()}", MTLX_COLORSPACE)
        write_mtlx(Path(layer.realPath).parent / MTLX_NAME,
                   usd_network_values(UsdShade.Shader(openpbr)), rel.as_posix())
    export_layer_atomic(layer, layer.realPath)
    return str(layer.realPath)


ALBEDO_NAME = "albedo.exr"
"""The texture :func:`bake_sample_albedo` writes beside the asset."""


def bake_sample_albedo(asset: Path, size: int = 2048, seed: int = 7,
                       progress: Any = None) -> Path:
    """Paint the sample albedo for the first skin mesh of ``asset`` (unwrapping it first
    when it has no usable UVs) and bind it; returns the texture's path."""
    stage, scene, mesh, uv, uv_tris, _ = ensure_skin_uvs(asset, progress)
    maps = rasterize(mesh.mesh.points, triangulate(mesh.mesh), uv, uv_tris, size,
                     scene.meters_per_unit, mesh.region_weights)
    if progress:
        progress(f"paint albedo {size}x{size}")
    albedo = paint_skin_albedo(maps, mesh.region_names, scene.meters_per_unit, seed)
    image = dilate_charts(push_pull(albedo, maps.coverage), maps.coverage)[::-1]  # row 0: v=1
    texture = Path(asset).resolve().parent / ALBEDO_NAME
    write_texture(texture, image, WORKING_COLORSPACE)
    author_albedo_texture(stage, mesh.path, texture)
    return texture
