"""Author stage: fitted profiles + a face mesh -> a USD asset (AOUSD asset structure).

```
ASSET_DIR/asset.usda   defaultPrim /<Name> (kind component), metersPerUnit, upAxis,
                       colour space, the scan's placement as its transform; sublayers
                       look.usda, payload geo.usdc (a set dresser can leave it unloaded)
ASSET_DIR/geo.usdc     the mesh about the asset's origin (its bounds' bottom centre), st,
                       region primvars, GeomSubsets, SkinProfileRegionsAPI
ASSET_DIR/look.usda    /<Name>/Looks: SkinDiffusionProfile prims (with their media), the
                       mesh's Material and one per region (Looks/Regions)
```
Every layer is exported to a temporary sibling, fsynced and renamed; input layers are
only read.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pxr import Gf, Kind, Sdf, Tf, Usd, UsdGeom, UsdShade, Vt

from ..errors import InputError
from ..profile.medium import MediumEstimate
from ..profile.types import FitResult, MeasuredProfile
from .io import export_layer_atomic
from .materialx import author_usd_network, write_mtlx
from .mesh import MeshData
from .openpbr import (
    SPECULAR_IOR,
    SPECULAR_ROUGHNESS,
    face_weighted_medium,
    openpbr_values,
    region_medium,
)
from .schema import (
    PROFILE_TYPE,
    PROFILES_REL,
    REGION_INDEX_PRIMVAR,
    REGION_WEIGHTS_PRIMVAR,
    REGIONS_API,
    SUBSET_FAMILY,
    WORKING_COLORSPACE,
    require_schema,
)

DEFAULT_ALBEDO = (0.62, 0.42, 0.33)
"""A mid skin tone in ACEScg, used for the preview material until a texture exists."""


MTLX_NAME = "look.mtlx"
"""The material as a MaterialX document, beside look.usda."""
ASSET_FILES = ("asset.usda", "geo.usdc", "look.usda", MTLX_NAME)
"""What :func:`author_asset` writes into the asset folder."""


@dataclass(frozen=True)
class RegionAssignment:
    """Region ``names`` (index i = region i), a region index per face, optional soft
    per-vertex weights (N, R) that sum to 1 per vertex."""

    names: tuple[str, ...]
    face_region: NDArray[np.int32]
    vertex_weights: NDArray[np.float32] | None = None


@dataclass(frozen=True)
class AssetPaths:
    asset: Path
    geo: Path
    look: Path
    seconds: float


# ------------------------------------------------------------------------------ regions


LANDMARK_TOLERANCE = 0.1
"""A landmark farther from the mesh than this share of its bounding-box diagonal is
refused: landmarks in the wrong unit (or for another mesh) would otherwise put every
face in one region without a word."""


def read_landmarks(path: str | Path) -> dict[str, NDArray[np.float64]]:
    """Landmarks JSON: ``{"regions": {"forehead": [[x, y, z], ...], ...}}``, mesh units."""
    path = Path(path)
    if not path.is_file():
        raise InputError("no such landmarks file", path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        regions = doc["regions"]
        out = {str(k): np.asarray(v, dtype=np.float64).reshape(-1, 3)
               for k, v in regions.items()}
    except (json.JSONDecodeError, KeyError, TypeError, ValueError, AttributeError) as exc:
        raise InputError(f"not a landmarks file ({{'regions': {{name: [[x, y, z], ...]}}}}): "
                         f"{exc}", path) from exc
    if not out or any(v.size == 0 or not np.isfinite(v).all() for v in out.values()):
        raise InputError("every region needs at least one finite 3D point", path)
    return out


OUTLIER_FACTOR = 20.0
"""A vertex farther from the mesh's median point than this many times the median
vertex's distance is a stray (a face scan's farthest vertex is about 2.5 times)."""


def check_landmarks_on_mesh(mesh: MeshData, landmarks: dict[str, NDArray[np.float64]]
                            ) -> None:
    """InputError naming the region whose landmarks lie farther from the mesh's nearest
    vertex than :data:`LANDMARK_TOLERANCE` of its bounding-box diagonal."""
    from scipy.spatial import cKDTree  # lazy: 0.39 s to import

    used = mesh.points[np.unique(mesh.face_indices)]  # a vertex no face uses is no skin
    # one stray vertex far away must not widen the tolerance for every landmark
    spread = np.linalg.norm(used - np.median(used, axis=0), axis=1)
    typical = float(np.median(spread))
    if typical > 0 and spread.max() > OUTLIER_FACTOR * typical:
        far = int(np.argmax(spread))
        raise InputError(
            f"a vertex at {used[far].round(4).tolist()} lies {spread[far]:.4g} units from "
            f"the mesh's median point, {spread[far] / typical:.0f} times the typical "
            f"{typical:.4g}: remove the stray vertex", mesh.source)
    diagonal = float(np.linalg.norm(np.ptp(used, axis=0)))
    tree = cKDTree(used)
    for name, points in landmarks.items():
        off = float(tree.query(points)[0].max())
        if off > LANDMARK_TOLERANCE * diagonal:
            raise InputError(
                f"region {name!r}: a landmark lies {off:.4g} mesh units from the nearest "
                f"mesh vertex, more than {LANDMARK_TOLERANCE:.0%} of its {diagonal:.4g}-unit "
                "diagonal (landmarks in another unit or for another mesh?)", mesh.source)


def assign_regions_from_landmarks(
    mesh: MeshData, landmarks: dict[str, NDArray[np.float64]], blend_mm: float = 8.0,
) -> RegionAssignment:
    """Soft regions from landmark points: each vertex's weight for a region falls off
    with its distance beyond the nearest region's, exp(-(d_r - d_min) / blend); each face
    takes the region with the largest mean weight over its vertices."""
    from scipy.spatial import cKDTree  # lazy: 0.39 s to import

    if not (math.isfinite(blend_mm) and blend_mm > 0):
        raise InputError(f"the region border width (blend) must be > 0 mm, got {blend_mm}")
    check_landmarks_on_mesh(mesh, landmarks)
    names = tuple(landmarks)
    blend = blend_mm / (mesh.meters_per_unit * 1000.0)
    dist = np.stack([cKDTree(landmarks[n]).query(mesh.points)[0] for n in names], axis=1)
    w = np.exp(-(dist - dist.min(axis=1, keepdims=True)) / max(blend, 1e-12))
    w /= w.sum(axis=1, keepdims=True)
    starts = np.concatenate([[0], np.cumsum(mesh.face_counts)[:-1]])
    face_w = np.add.reduceat(w[mesh.face_indices], starts, axis=0)
    return RegionAssignment(names, np.argmax(face_w, axis=1).astype(np.int32),
                            w.astype(np.float32))


# ----------------------------------------------------------------------------- authoring


def _layer_stage(meters_per_unit: float, up_axis: str, default_prim: str,
                 layer: Any = None) -> Any:
    stage = Usd.Stage.Open(layer) if layer is not None else Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    UsdGeom.SetStageUpAxis(stage, up_axis)
    stage.SetMetadata("defaultPrim", default_prim)
    return stage


def _f32(values: Any) -> list[float]:
    return [float(np.float32(x)) for x in np.asarray(values, dtype=np.float64).reshape(-1)]


def _author_profile(stage: Any, path: str, fit: FitResult,
                    measured: MeasuredProfile | None, medium: MediumEstimate) -> None:
    prim = stage.DefinePrim(path, PROFILE_TYPE)
    _author_medium(prim, medium)
    # Author every value, fallbacks included: without the plugin they would vanish.
    prim.CreateAttribute("region", Sdf.ValueTypeNames.Token).Set(fit.name)
    prim.CreateAttribute("variances", Sdf.ValueTypeNames.FloatArray).Set(
        Vt.FloatArray(_f32(fit.variances_mm2)))
    prim.CreateAttribute("weights", Sdf.ValueTypeNames.Color3fArray).Set(
        Vt.Vec3fArray([Gf.Vec3f(*_f32(w)) for w in fit.weights]))
    tr = np.ones(3) if fit.total_reflectance is None else fit.total_reflectance
    prim.CreateAttribute("totalReflectance", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*_f32(tr)))
    prim.CreateAttribute("lengthUnit", Sdf.ValueTypeNames.Token, variability=Sdf.VariabilityUniform
                         ).Set("mm")
    prim.CreateAttribute("fit:error", Sdf.ValueTypeNames.Float3).Set(Gf.Vec3f(*_f32(fit.error)))
    prim.CreateAttribute("fit:solver", Sdf.ValueTypeNames.String).Set(fit.solver)
    prim.CreateAttribute("fit:status", Sdf.ValueTypeNames.String).Set(fit.status)
    # fit:seconds is left out: the run's timings live in run records, not in the asset
    if measured is not None:
        prim.CreateAttribute("measured:radiusMm", Sdf.ValueTypeNames.FloatArray).Set(
            Vt.FloatArray(_f32(measured.radius_mm)))
        prim.CreateAttribute("measured:values", Sdf.ValueTypeNames.Color3fArray).Set(
            Vt.Vec3fArray.FromNumpy(np.asarray(measured.values, dtype=np.float32)))
        if measured.stddev is not None:
            prim.CreateAttribute("measured:stddev", Sdf.ValueTypeNames.Color3fArray).Set(
                Vt.Vec3fArray.FromNumpy(np.asarray(measured.stddev, dtype=np.float32)))


def _author_medium(prim: Any, medium: MediumEstimate) -> None:
    """The region's medium (:mod:`skinpipe.profile.medium`) on its profile prim."""
    for name, kind, value in (
            ("singleScatteringAlbedo", Sdf.ValueTypeNames.Color3f,
             medium.single_scattering_albedo),
            ("meanFreePathMm", Sdf.ValueTypeNames.Color3f, medium.mean_free_path_mm),
            ("totalReflectance", Sdf.ValueTypeNames.Color3f, medium.total_reflectance),
            ("subsurfaceColor", Sdf.ValueTypeNames.Color3f, medium.subsurface_colour),
            ("error", Sdf.ValueTypeNames.Float3, medium.error_eq2c),
            ("edgeError", Sdf.ValueTypeNames.Float3, medium.edge_error)):
        prim.CreateAttribute(f"medium:{name}", kind).Set(Gf.Vec3f(*_f32(value)))
    prim.CreateAttribute("medium:anisotropy", Sdf.ValueTypeNames.Float).Set(
        float(medium.anisotropy))
    prim.CreateAttribute("medium:model", Sdf.ValueTypeNames.Token,
                         variability=Sdf.VariabilityUniform).Set(medium.model)


def _author_material(stage: Any, path: str, values: dict[str, Any]) -> str:
    """A Material at ``path``: a UsdPreviewSurface (usdview, Storm, USD's universal
    context) and the OpenPBR network of ``values`` in the ``mtlx`` context."""
    material = UsdShade.Material.Define(stage, path)
    preview = UsdShade.Shader.Define(stage, f"{path}/PreviewSurface")
    preview.CreateIdAttr("UsdPreviewSurface")
    preview.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(
        Gf.Vec3f(*values["base_color"]))
    preview.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(SPECULAR_ROUGHNESS)
    preview.CreateInput("ior", Sdf.ValueTypeNames.Float).Set(SPECULAR_IOR)
    material.CreateSurfaceOutput().ConnectToSource(
        preview.CreateOutput("surface", Sdf.ValueTypeNames.Token))
    author_usd_network(stage, path, values)
    return path


def _author_look_variants(look: Any, root: str, subset_paths: Sequence[Any],
                          region_materials: Sequence[str]) -> None:
    """The variant set skinLook on the root: ``perRegion`` (the default) binds each
    region's subset to its own material, a hard change at region borders; ``blended``
    binds none, so the mesh's SkinMaterial shows, whose subsurface follows the soft
    region weights once the albedo is painted (:mod:`skinpipe.workflow.albedo`)."""
    variants = look.GetPrimAtPath(root).GetVariantSets().AddVariantSet(LOOK_VARIANT_SET)
    for name in LOOK_VARIANTS:
        variants.AddVariant(name)
    variants.SetVariantSelection("perRegion")
    with variants.GetVariantEditContext():
        for path, material in zip(subset_paths, region_materials, strict=True):
            subset = look.OverridePrim(path)
            UsdShade.MaterialBindingAPI.Apply(subset).GetDirectBindingRel().SetTargets(
                [Sdf.Path(material)])
    variants.SetVariantSelection("perRegion")


LOOK_VARIANT_SET = "skinLook"
LOOK_VARIANTS = ("perRegion", "blended")
"""How other renderers get the regions: a material per region (default) or one material
whose subsurface maps blend them."""
REGION_LOOKS = "Looks/Regions"
"""Where each region's material lives under the asset's root."""
BIND_SUBSET_PREFIX = "look_"
"""Name prefix of the materialBind GeomSubsets that bind region materials."""


def asset_origin(points: NDArray[Any], up_axis: str) -> NDArray[np.float64]:
    """Where the asset's root sits in the mesh's coordinates: the bottom centre of its
    bounds (a scan arrives in scanner coordinates, hundreds of mm from its origin)."""
    p = np.asarray(points, dtype=np.float64)
    lo, hi = p.min(axis=0), p.max(axis=0)
    origin = (lo + hi) / 2
    up = {"Y": 1, "Z": 2}[str(up_axis)]
    origin[up] = lo[up]
    return origin


def _define_mesh(stage: Any, path: str, mesh: MeshData, origin: NDArray[Any]) -> Any:
    """A polygon mesh (no subdivision) with its points about the asset's ``origin``."""
    umesh = UsdGeom.Mesh.Define(stage, path)
    pts = np.asarray(mesh.points - origin, dtype=np.float32)
    umesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
    umesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(mesh.face_counts))
    umesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(mesh.face_indices))
    umesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    umesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([pts.min(0), pts.max(0)])))
    return umesh


def _extents_hint(meshes: Sequence[MeshData], origin: NDArray[Any]) -> Any:
    """[min, max] over the meshes' points as :func:`_define_mesh` writes them."""
    pts = np.concatenate([np.asarray(m.points - origin, dtype=np.float32) for m in meshes])
    return Vt.Vec3fArray.FromNumpy(np.stack([pts.min(0), pts.max(0)]))


SEAL_GREY = 0.18
"""The seal's colour (linear, a neutral mid grey): it shows where the scan is open."""


def _author_seal(stage: Any, path: str, seal: MeshData, origin: NDArray[Any]) -> None:
    # Seen by the camera: hidden, it let the background show through the scan's cracks
    # (along the demo face's jaws and ear); shown, the cracks read as a neutral surface.
    umesh = _define_mesh(stage, path, seal, origin)
    umesh.CreateDisplayColorAttr([Gf.Vec3f(SEAL_GREY, SEAL_GREY, SEAL_GREY)])
    umesh.GetPrim().SetDocumentation(
        "Closes the scan's open rim (surface the scanner never saw) so that no light "
        "passes through the face and no camera sees through its cracks: a neutral grey "
        "surface, not skin, no texture space.")


def author_asset(
    fits: Sequence[FitResult],
    mesh: MeshData,
    regions: RegionAssignment,
    out_dir: str | Path,
    name: str = "Face",
    measured: dict[str, MeasuredProfile] | None = None,
    up_axis: str = "Y",
    albedo: tuple[float, float, float] = DEFAULT_ALBEDO,
    seal: MeshData | None = None,
) -> AssetPaths:
    """Write asset.usda, geo.usdc and look.usda for ``fits`` on ``mesh`` into ``out_dir``.

    ``seal`` (from :func:`skinpipe.usd.mesh.seal_scan`) becomes ``Geom/Seal``: geometry the
    scanner never saw, there to stop light, without skin profiles or texture space."""
    require_schema()
    start = time.perf_counter()
    if not name.isidentifier():
        raise InputError(f"asset name must be a valid prim name, got {name!r}")
    by_name = {f.name: f for f in fits}
    missing = [r for r in regions.names if r not in by_name]
    if missing:
        raise InputError(f"no fit for region(s) {missing}; fits given: {sorted(by_name)}")
    unused = sorted(set(by_name) - set(regions.names))
    if unused:
        raise InputError(f"fit(s) {unused} have no region on the mesh (regions: "
                         f"{list(regions.names)}): add them to the landmarks or leave them out")
    if regions.face_region.shape != (mesh.n_faces,):
        raise InputError(f"{regions.face_region.size} face regions for {mesh.n_faces} faces")
    out = Path(out_dir)
    paths = AssetPaths(out / "asset.usda", out / "geo.usdc", out / "look.usda", 0.0)
    if mesh.source is not None and mesh.source.resolve() in {
            p.resolve() for p in (paths.asset, paths.geo, paths.look)}:
        raise InputError("the output would overwrite the input mesh layer", mesh.source)
    root = f"/{name}"
    mpu = mesh.meters_per_unit
    ordered = [by_name[r] for r in regions.names]
    profile_paths = [f"{root}/Looks/Profiles/{Tf.MakeValidIdentifier(r)}"
                     for r in regions.names]

    # look.usda: profiles and material
    look = _layer_stage(mpu, up_axis, name)
    look.OverridePrim(root)
    UsdGeom.Scope.Define(look, f"{root}/Looks")
    UsdGeom.Scope.Define(look, f"{root}/Looks/Profiles")
    media = [region_medium(fit, (measured or {}).get(fit.name), albedo) for fit in ordered]
    for fit, ppath, medium in zip(ordered, profile_paths, media, strict=True):
        _author_profile(look, ppath, fit, (measured or {}).get(fit.name), medium)
    materials = {"SkinMaterial": openpbr_values(
        face_weighted_medium(media, regions.face_region), mpu, albedo)}
    material_path = _author_material(look, f"{root}/Looks/SkinMaterial",
                                     materials["SkinMaterial"])
    UsdGeom.Scope.Define(look, f"{root}/{REGION_LOOKS}")
    region_materials = []
    for region, medium in zip(regions.names, media, strict=True):
        key = Tf.MakeValidIdentifier(region)
        materials[key] = openpbr_values(medium, mpu, albedo)
        region_materials.append(_author_material(look, f"{root}/{REGION_LOOKS}/{key}",
                                                 materials[key]))

    # geo.usdc: mesh, regions
    geo = _layer_stage(mpu, up_axis, name)
    geo.OverridePrim(root)
    UsdGeom.Scope.Define(geo, f"{root}/Geom")
    origin = asset_origin(mesh.points, up_axis)
    umesh = _define_mesh(geo, f"{root}/Geom/Mesh", mesh, origin)
    pv_api = UsdGeom.PrimvarsAPI(umesh)
    if mesh.st is not None:
        pv_api.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex
                             ).Set(Vt.Vec2fArray.FromNumpy(np.asarray(mesh.st, np.float32)))
    prim = umesh.GetPrim()
    prim.ApplyAPI(REGIONS_API)
    prim.CreateRelationship(PROFILES_REL).SetTargets([Sdf.Path(p) for p in profile_paths])
    pv_api.CreatePrimvar(REGION_INDEX_PRIMVAR, Sdf.ValueTypeNames.IntArray,
                         UsdGeom.Tokens.uniform).Set(Vt.IntArray.FromNumpy(regions.face_region))
    if regions.vertex_weights is not None:
        pv_api.CreatePrimvar(REGION_WEIGHTS_PRIMVAR, Sdf.ValueTypeNames.FloatArray,
                             UsdGeom.Tokens.vertex, len(regions.names)).Set(
            Vt.FloatArray.FromNumpy(regions.vertex_weights.reshape(-1)))
    for i, region in enumerate(regions.names):
        faces = np.flatnonzero(regions.face_region == i).astype(np.int32)
        UsdGeom.Subset.CreateGeomSubset(umesh, Tf.MakeValidIdentifier(region),
                                        UsdGeom.Tokens.face, Vt.IntArray.FromNumpy(faces),
                                        SUBSET_FAMILY, UsdGeom.Tokens.partition)
    binding = UsdShade.MaterialBindingAPI.Apply(prim)
    binding.GetDirectBindingRel().SetTargets([Sdf.Path(material_path)])
    # a materialBind GeomSubset per region; which material each binds is the look's
    # choice (the skinLook variant set in look.usda)
    subset_paths = []
    for i, region in enumerate(regions.names):
        faces = np.flatnonzero(regions.face_region == i).astype(np.int32)
        subset_paths.append(binding.CreateMaterialBindSubset(
            BIND_SUBSET_PREFIX + Tf.MakeValidIdentifier(region),
            Vt.IntArray.FromNumpy(faces)).GetPath())
    _author_look_variants(look, root, subset_paths, region_materials)
    if seal is not None:
        _author_seal(geo, f"{root}/Geom/Seal", seal, origin)

    # asset.usda: the interface
    asset_layer = Sdf.Layer.CreateAnonymous("asset.usda")  # held here, outlives the stage
    asset = _layer_stage(mpu, up_axis, name, asset_layer)
    top = UsdGeom.Xform.Define(asset, root).GetPrim()
    Usd.ModelAPI(top).SetKind(Kind.Tokens.component)
    Usd.ModelAPI(top).SetAssetName(name)
    Usd.ModelAPI(top).SetAssetIdentifier(Sdf.AssetPath("./asset.usda"))
    Usd.ColorSpaceAPI.Apply(top).CreateColorSpaceNameAttr(WORKING_COLORSPACE)
    # the scan's placement: a transform of the root, which a set dresser overrides
    UsdGeom.Xformable(top).AddTranslateOp().Set(Gf.Vec3d(*origin.tolist()))
    # the box of everything under the root, in its own space: an unloaded payload still
    # has a size (Pixar's model guidelines ask extentsHint of a component)
    UsdGeom.ModelAPI(top).SetExtentsHint(_extents_hint(
        [mesh] if seal is None else [mesh, seal], origin))
    del asset  # composition arcs go on the bare layer: no stage composes them here
    asset_layer.subLayerPaths = ["./look.usda"]
    asset_layer.GetPrimAtPath(root).payloadList.Prepend(Sdf.Payload("./geo.usdc"))
    asset_layer.customLayerData = {
        "skinpipe:colorSpace": WORKING_COLORSPACE,
        "skinpipe:generator": "skinpipe author",
    }

    export_layer_atomic(geo.GetRootLayer(), paths.geo)
    write_mtlx(out / MTLX_NAME, materials)
    export_layer_atomic(look.GetRootLayer(), paths.look)
    export_layer_atomic(asset_layer, paths.asset)
    return AssetPaths(paths.asset, paths.geo, paths.look, time.perf_counter() - start)


# -------------------------------------------------------------------------------- reading


def read_profiles(stage: Any) -> dict[str, tuple[FitResult, MeasuredProfile | None]]:
    """Every SkinDiffusionProfile on the stage as (fit, measured samples), by prim path."""
    out = {}
    for prim in Usd.PrimRange(stage.GetPseudoRoot()):
        if prim.GetTypeName() != PROFILE_TYPE:
            continue

        def get(attr: str, default: Any = None, prim: Any = prim) -> Any:
            a = prim.GetAttribute(attr)
            value = a.Get() if a else None
            return default if value is None else value

        def numbers(attr: str, default: Any, prim: Any = prim) -> NDArray[np.float64]:
            value = get(attr, default)
            try:
                return np.array(value, dtype=np.float64)
            except (TypeError, ValueError):
                raise InputError(f"{prim.GetPath()}.{attr}: expected numbers, got "
                                 f"{type(value).__name__} {str(value)[:60]!r}",
                                 stage.GetRootLayer().realPath) from None

        variances = numbers("variances", []).reshape(-1)
        weights = numbers("weights", [])
        if weights.size % 3:
            raise InputError(f"{prim.GetPath()}.weights: {weights.size} numbers is not RGB "
                             "triples", stage.GetRootLayer().realPath)
        weights = weights.reshape(-1, 3)
        tr = numbers("totalReflectance", (1.0, 1.0, 1.0)).reshape(-1)
        fit = FitResult(
            name=str(get("region", prim.GetName())), variances_mm2=variances, weights=weights,
            error=numbers("fit:error", (math.nan,) * 3).reshape(-1),
            seconds=float(numbers("fit:seconds", 0.0)), status=str(get("fit:status", "")),
            solver=str(get("fit:solver", "")), iterations=0, objective=math.nan,
            k_requested=int(variances.size), share="", n_samples=0, radius_range_mm=(0.0, 0.0),
            total_reflectance=None if np.allclose(tr, 1.0) else tr,
        )
        if weights.shape[0] != variances.size:
            raise InputError(f"{prim.GetPath()}: {weights.shape[0]} weights for "
                             f"{variances.size} variances", stage.GetRootLayer().realPath)
        radius = numbers("measured:radiusMm", []).reshape(-1)
        measured = None
        if radius.size:
            values = numbers("measured:values", []).reshape(-1, 3)
            std = get("measured:stddev")
            measured = MeasuredProfile(radius, values, None if std is None else
                                       numbers("measured:stddev", []).reshape(-1, 3),
                                       name=fit.name)
        out[str(prim.GetPath())] = (fit, measured)
    return out
