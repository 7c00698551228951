"""Scene delegate: the USD stage read into plain data for the renderer, with change
tracking (Hydra's pattern, without Hydra: usd-core ships no render delegate we can use).

What is read: meshes (world-space points, topology, ``st``, region primvars), UsdLux
DistantLight / SphereLight / RectLight / DomeLight (intensity, exposure, colour, angle,
size, latlong texture), the UsdGeomCamera, the bound material's albedo (constant or a
UsdUVTexture) and the SkinDiffusionProfile prims a skin mesh targets. Edits to the
stage arrive as ``Usd.Notice.ObjectsChanged`` and mark categories dirty; a new time
re-reads only what may vary in time. The renderer keys its caches on the content of
what comes out, so a camera-only change leaves texture-space work untouched.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pxr import Tf, Usd, UsdGeom, UsdLux, UsdShade

from ..errors import InputError
from ..profile.types import FitResult
from ..usd.author import read_profiles
from ..usd.mesh import MeshData, validate_mesh
from ..usd.schema import (
    CAMERA_VISIBILITY_PRIMVAR,
    PROFILES_REL,
    REGION_INDEX_PRIMVAR,
    REGION_WEIGHTS_PRIMVAR,
    REGIONS_API,
)
from ..usd.validate import profile_problems

CATEGORIES = ("geometry", "lights", "camera", "material")
LIGHT_TYPES = {"DistantLight": "distant", "SphereLight": "sphere", "RectLight": "rect",
               "DomeLight": "dome"}


def content_hash(*parts: Any) -> str:
    """A stable hash of arrays, numbers and strings (cache keys)."""
    h = hashlib.blake2b(digest_size=16)
    for p in parts:
        if isinstance(p, np.ndarray):
            h.update(str((p.dtype, p.shape)).encode())
            h.update(np.ascontiguousarray(p).tobytes())
        else:
            h.update(repr(p).encode())
    return h.hexdigest()


@dataclass(frozen=True)
class Light:
    """One UsdLux light in world space. ``radiance`` = intensity x 2^exposure x colour
    (linear, the stage's working space); ``matrix`` local-to-world (row vectors)."""

    path: str
    kind: str
    radiance: NDArray[np.float64]
    matrix: NDArray[np.float64]
    angle_deg: float = 0.53
    radius: float = 0.5
    width: float = 1.0
    height: float = 1.0
    texture: str | None = None
    normalize: bool = False

    @property
    def position(self) -> NDArray[np.float64]:
        return self.matrix[3, :3]

    @property
    def axis(self) -> NDArray[np.float64]:
        """The direction the light emits along (its local -Z in world space)."""
        d = -self.matrix[2, :3]
        return d / np.linalg.norm(d)

    def key(self) -> str:
        return content_hash(self.kind, self.radiance, self.matrix, self.angle_deg, self.radius,
                            self.width, self.height, self.texture, self.normalize)


@dataclass(frozen=True)
class Camera:
    """A pinhole or orthographic camera: world position, rotation (columns: right, up,
    back), apertures and focal length in the same unit. For ``orthographic`` the
    horizontal aperture is the view's width in scene units (USD's tenths of a unit,
    converted when read) and the focal length is unused."""

    path: str
    position: NDArray[np.float64]
    rotation: NDArray[np.float64]
    focal_length: float
    horizontal_aperture: float
    vertical_aperture: float
    projection: str = "perspective"

    def rays(self, width: int, height: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Origins and unit directions through pixel centres, row 0 at the top."""
        px, py = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        return self.rays_at(px.ravel(), py.ravel(), width, height)

    def rays_at(self, px: NDArray[Any], py: NDArray[Any], width: int, height: int
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Rays through image points (``px``, ``py``) in pixels of a width x height image,
        (0, 0) its top left corner. A perspective camera's origins are one point, a
        read-only view of it for every ray (a copy held 24 MB at 1024 x 1024 pixels
        through a render's peak)."""
        x = (np.asarray(px, np.float64) / width - 0.5) * self.horizontal_aperture
        # the image keeps square pixels: the vertical extent follows the aspect ratio
        vext = self.horizontal_aperture * height / width
        y = (0.5 - np.asarray(py, np.float64) / height) * vext
        if self.projection == "orthographic":  # parallel rays from the film plane
            film = np.stack([x, y, np.zeros_like(x)], axis=-1) @ self.rotation.T
            d = np.broadcast_to(-self.rotation[:, 2], film.shape).copy()
            return self.position + film, d
        local = np.stack([x, y, np.full_like(x, -self.focal_length)], axis=-1)
        d = local @ self.rotation.T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.broadcast_to(np.asarray(self.position, np.float64), d.shape), d

    def key(self) -> str:
        return content_hash(self.position, self.rotation, self.focal_length,
                            self.horizontal_aperture, self.vertical_aperture, self.projection)


@dataclass(frozen=True)
class Albedo:
    """The bound material's diffuse colour: a constant, or a texture read through ``st``."""

    constant: tuple[float, float, float]
    texture: Path | None = None
    colorspace: str | None = None


@dataclass(frozen=True)
class SceneMesh:
    """A mesh in world space. Skin meshes also carry regions, profiles and albedo."""

    path: str
    mesh: MeshData
    uv: NDArray[np.float64] | None = None
    uv_indices: NDArray[np.int32] | None = None  # per face-vertex; None = per vertex
    region_names: tuple[str, ...] = ()
    region_weights: NDArray[np.float32] | None = None  # (N, R) per vertex
    fits: tuple[FitResult, ...] = ()
    albedo: Albedo = Albedo((0.5, 0.5, 0.5))
    points_layer: str | None = None
    points_prim: str | None = None
    """The mesh's path in ``points_layer``."""
    camera_visible: bool = True
    """False for an occluder that only casts shadows (``primvars:skinpipe:cameraVisibility``
    = false, :data:`~skinpipe.usd.schema.CAMERA_VISIBILITY_PRIMVAR`)."""

    @property
    def is_skin(self) -> bool:
        return bool(self.fits)

    def geometry_key(self) -> str:
        return content_hash(self.mesh.points, self.mesh.face_indices, self.mesh.face_counts,
                            self.uv if self.uv is not None else 0,
                            self.uv_indices if self.uv_indices is not None else 0,
                            self.region_weights if self.region_weights is not None else 0)

    def fits_key(self) -> str:
        """The content of the profiles' terms: what the regions' media depend on."""
        return content_hash(*(f.variances_mm2 for f in self.fits),
                            *(f.weights for f in self.fits))


@dataclass
class SceneData:
    meshes: list[SceneMesh]
    lights: list[Light]
    camera: Camera | None
    meters_per_unit: float
    working_colorspace: str
    dirty: set[str] = field(default_factory=set)

    @property
    def skin(self) -> list[SceneMesh]:
        return [m for m in self.meshes if m.is_skin]


def _world_matrix(prim: Any, time: Any) -> NDArray[np.float64]:
    """``prim``'s local-to-world matrix; InputError if it is not finite or collapses space
    (a NaN or zero scale renders black without a word otherwise)."""
    m = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time), dtype=np.float64)
    if not np.isfinite(m).all():
        raise InputError(f"{prim.GetPath()}: its transform is not finite at time {time}: "
                         f"{m.tolist()}")
    if not abs(np.linalg.det(m[:3, :3])) > 1e-30:
        raise InputError(f"{prim.GetPath()}: its transform has zero scale (singular) at "
                         f"time {time}")
    return m


def _positive(prim: Any, name: str, value: Any, allow_zero: bool = False) -> float:
    """A light or camera size as a float; InputError unless finite and > 0 (or >= 0)."""
    v = float("nan") if value is None else float(value)
    if not (math.isfinite(v) and (v >= 0 if allow_zero else v > 0)):
        raise InputError(f"{prim.GetPath()}: {name} must be {'>= 0' if allow_zero else '> 0'}"
                         f" and finite, got {value!r}")
    return v


def _read_light(prim: Any, kind: str, time: Any) -> Light:
    api = UsdLux.LightAPI(prim)
    intensity = float(api.GetIntensityAttr().Get(time) or 0.0)
    exposure = float(api.GetExposureAttr().Get(time) or 0.0)
    colour = np.asarray(api.GetColorAttr().Get(time) or (1.0, 1.0, 1.0), dtype=np.float64)
    radiance = intensity * 2.0 ** exposure * colour
    if not np.all(np.isfinite(radiance)) or np.any(radiance < 0):
        raise InputError(f"light {prim.GetPath()}: intensity/exposure/colour give a non-finite "
                         f"or negative radiance {radiance.tolist()}")
    matrix = _world_matrix(prim, time)
    normalize = bool(api.GetNormalizeAttr().Get(time))
    if kind == "distant":
        return Light(str(prim.GetPath()), kind, radiance, matrix,
                     angle_deg=_positive(prim, "angle", UsdLux.DistantLight(prim)
                                         .GetAngleAttr().Get(time), allow_zero=True),
                     normalize=normalize)
    if kind == "sphere":
        return Light(str(prim.GetPath()), kind, radiance, matrix,
                     radius=_positive(prim, "radius", UsdLux.SphereLight(prim)
                                      .GetRadiusAttr().Get(time), allow_zero=True),
                     normalize=normalize)
    if kind == "rect":
        rect = UsdLux.RectLight(prim)
        return Light(str(prim.GetPath()), kind, radiance, matrix,
                     width=_positive(prim, "width", rect.GetWidthAttr().Get(time)),
                     height=_positive(prim, "height", rect.GetHeightAttr().Get(time)),
                     normalize=normalize)
    tex = UsdLux.DomeLight(prim).GetTextureFileAttr().Get(time)
    path = (tex.resolvedPath or tex.path) if tex is not None and tex.path else None
    if tex is not None and tex.path and not tex.resolvedPath:
        raise InputError(f"dome light {prim.GetPath()}: texture {tex.path!r} not found")
    return Light(str(prim.GetPath()), kind, radiance, matrix, texture=path)


def _read_camera(prim: Any, time: Any) -> Camera:
    cam = UsdGeom.Camera(prim)
    projection = str(cam.GetProjectionAttr().Get(time))
    if projection not in (UsdGeom.Tokens.perspective, UsdGeom.Tokens.orthographic):
        raise InputError(f"camera {prim.GetPath()}: unknown projection {projection!r}")
    m = _world_matrix(prim, time)
    rot = m[:3, :3].T  # columns = world images of local x, y, z
    rot = rot / np.linalg.norm(rot, axis=0, keepdims=True)
    focal = _positive(prim, "focalLength", cam.GetFocalLengthAttr().Get(time))
    hap = _positive(prim, "horizontalAperture", cam.GetHorizontalApertureAttr().Get(time))
    vap = _positive(prim, "verticalAperture", cam.GetVerticalApertureAttr().Get(time))
    near, far = cam.GetClippingRangeAttr().Get(time) or (1.0, 1e6)
    if not (math.isfinite(near) and 0 < near < far):
        raise InputError(f"camera {prim.GetPath()}: clipping range must be 0 < near < far, "
                         f"got ({near}, {far})")
    if projection == UsdGeom.Tokens.orthographic:
        # GfCamera: an orthographic view is the aperture wide, in tenths of a scene unit
        return Camera(str(prim.GetPath()), m[3, :3].copy(), rot, focal, hap * 0.1, vap * 0.1,
                      "orthographic")
    return Camera(str(prim.GetPath()), m[3, :3].copy(), rot, focal, hap, vap)


def _read_albedo(prim: Any, time: Any) -> Albedo:
    material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
    if not material:
        return Albedo((0.5, 0.5, 0.5))
    shader = material.ComputeSurfaceSource()[0]
    if not shader:
        return Albedo((0.5, 0.5, 0.5))
    inp = shader.GetInput("diffuseColor")
    if not inp:
        return Albedo((0.5, 0.5, 0.5))
    constant = tuple(float(c) for c in (inp.Get(time) or (0.5, 0.5, 0.5)))
    source = inp.GetConnectedSources()[0]
    if not source:
        return Albedo(constant)  # type: ignore[arg-type]
    tex_shader = UsdShade.Shader(source[0].source.GetPrim())
    file_input = tex_shader.GetInput("file")
    asset = file_input.Get(time) if file_input else None
    if asset is None or not asset.path:
        return Albedo(constant)  # type: ignore[arg-type]
    if not asset.resolvedPath:
        raise InputError(f"albedo texture {asset.path!r} on {tex_shader.GetPath()} not found")
    colorspace = file_input.GetAttr().GetColorSpace() or None
    return Albedo(constant, Path(asset.resolvedPath), colorspace)  # type: ignore[arg-type]


def _read_fits(prim: Any, names: list[str]) -> tuple[FitResult, ...]:
    stage = prim.GetStage()
    targets = prim.GetRelationship(PROFILES_REL).GetTargets()
    by_path = read_profiles(stage)
    fits = []
    for t in targets:
        if str(t) not in by_path:
            raise InputError(f"{prim.GetPath()}: {PROFILES_REL} targets {t}, which is not a "
                             "SkinDiffusionProfile")
        problems = profile_problems(stage.GetPrimAtPath(t))
        if problems:
            first = problems[0]
            raise InputError(f"{first.sites[0]}: {first.message} ({first.rule}; "
                             "'skinpipe validate' lists every finding)",
                             stage.GetRootLayer().realPath)
        fits.append(by_path[str(t)][0])
    if len(fits) != len(names):
        raise InputError(f"{prim.GetPath()}: {len(fits)} profiles for {len(names)} regions")
    return tuple(fits)


def _check_units(prim: Any, mpu: float) -> None:
    """The stage's metersPerUnit (its root layer's, else USD's fallback 0.01) must be the
    one the layers holding the skin's points say: a layer over an asset that does not
    restate it makes a millimetre face centimetres, ten times too large for its profiles."""
    stage = prim.GetStage()
    for spec in prim.GetAttribute("points").GetPropertyStack(Usd.TimeCode.Default()):
        root = spec.layer.pseudoRoot
        if not root.HasInfo("metersPerUnit"):
            continue
        layer_mpu = float(root.GetInfo("metersPerUnit"))
        if not math.isclose(layer_mpu, mpu, rel_tol=1e-6):
            root_layer = stage.GetRootLayer()
            said = "authors" if root_layer.pseudoRoot.HasInfo("metersPerUnit") else \
                "does not author it, so USD's fallback applies:"
            raise InputError(
                f"{prim.GetPath()}: its points are in {spec.layer.identifier}, whose "
                f"metersPerUnit is {layer_mpu:g}, but the stage's root layer {said} "
                f"metersPerUnit {mpu:g}; restate metersPerUnit = {layer_mpu:g} in "
                f"{root_layer.identifier}", root_layer.realPath or root_layer.identifier)
        return


def _read_mesh(prim: Any, time: Any, mpu: float) -> SceneMesh:
    _check_units(prim, mpu)
    mesh = UsdGeom.Mesh(prim)
    pts = mesh.GetPointsAttr().Get(time)
    counts = mesh.GetFaceVertexCountsAttr().Get(time)
    indices = mesh.GetFaceVertexIndicesAttr().Get(time)
    path = str(prim.GetPath())
    source = Path(prim.GetStage().GetRootLayer().realPath or path)
    if pts is None or counts is None or indices is None or len(pts) == 0:
        raise InputError(f"mesh {path} has no points or topology", source)
    p = np.asarray(pts, dtype=np.float64)
    if not np.all(np.isfinite(p)):
        bad = int(np.flatnonzero(~np.isfinite(p).all(axis=1))[0])
        raise InputError(f"mesh {path}: non-finite point {bad}: {p[bad].tolist()}", source)
    m = _world_matrix(prim, time)
    world = p @ m[:3, :3] + m[3, :3]
    data = validate_mesh(MeshData(world, np.asarray(counts, np.int32),
                                  np.asarray(indices, np.int32), mpu, None, source))
    uv = uv_idx = None
    st = UsdGeom.PrimvarsAPI(prim).GetPrimvar("st")
    if st and st.HasValue():
        values = np.asarray(st.Get(time), dtype=np.float64)
        interp = st.GetInterpolation()
        if interp in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying) and st.IsIndexed():
            values = np.asarray(st.ComputeFlattened(time), dtype=np.float64)
        if interp == UsdGeom.Tokens.faceVarying:
            uv = values
            uv_idx = (np.asarray(st.GetIndices(time), np.int32) if st.IsIndexed()
                      else np.arange(len(indices), dtype=np.int32))
        elif interp in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying):
            uv = values
        if uv is not None and (uv.ndim != 2 or uv.shape[1] != 2):
            uv = uv_idx = None
    points_layer = points_prim = None
    for spec in mesh.GetPointsAttr().GetPropertyStack(time):
        # the layer and the path there: a referenced or payloaded mesh has another path
        points_layer, points_prim = spec.layer.identifier, str(spec.path.GetPrimPath())
        break
    if not prim.HasAPI(REGIONS_API) and not prim.GetRelationship(PROFILES_REL):
        seen = UsdGeom.PrimvarsAPI(prim).GetPrimvar(CAMERA_VISIBILITY_PRIMVAR)
        return SceneMesh(path, data, uv, uv_idx, albedo=_read_albedo(prim, time),
                         points_layer=points_layer, points_prim=points_prim,
                         camera_visible=not (seen and seen.HasValue()
                                             and seen.Get(time) is False))
    pv = UsdGeom.PrimvarsAPI(prim)
    rel_targets = prim.GetRelationship(PROFILES_REL).GetTargets()
    names = [t.name for t in rel_targets]
    n_regions = len(names)
    weights_pv = pv.GetPrimvar(REGION_WEIGHTS_PRIMVAR)
    n = p.shape[0]
    if weights_pv and weights_pv.HasValue():
        w = np.asarray(weights_pv.Get(time), dtype=np.float32)
        if w.size != n * n_regions:
            raise InputError(f"{path}: {REGION_WEIGHTS_PRIMVAR} has {w.size} values, expected "
                             f"{n} points x {n_regions} regions", source)
        weights = w.reshape(n, n_regions)
    else:
        idx_pv = pv.GetPrimvar(REGION_INDEX_PRIMVAR)
        if not idx_pv or not idx_pv.HasValue():
            raise InputError(f"{path}: no {REGION_INDEX_PRIMVAR} or {REGION_WEIGHTS_PRIMVAR}",
                             source)
        face_region = np.asarray(idx_pv.Get(time), dtype=np.int64)
        if face_region.size != data.n_faces or face_region.min() < 0 or \
                face_region.max() >= n_regions:
            raise InputError(f"{path}: {REGION_INDEX_PRIMVAR} must hold one index in "
                             f"0..{n_regions - 1} per face", source)
        # per-vertex weights from the faces around each vertex (a soft border one ring wide)
        weights = np.zeros((n, n_regions), np.float32)
        np.add.at(weights, (data.face_indices, np.repeat(face_region, data.face_counts)), 1.0)
    total = weights.sum(axis=1, keepdims=True)
    weights = np.where(total > 0, weights / np.where(total > 0, total, 1), 1.0 / n_regions)
    return SceneMesh(path, data, uv, uv_idx, tuple(names), weights.astype(np.float32),
                     _read_fits(prim, names), _read_albedo(prim, time), points_layer,
                     points_prim)


class SceneDelegate:
    """Reads a stage into :class:`SceneData` and tracks edits through USD notices."""

    def __init__(self, stage: Any, camera_path: str | None = None) -> None:
        self.stage = stage
        self.camera_path = camera_path
        self.meters_per_unit = float(UsdGeom.GetStageMetersPerUnit(stage))
        layer_cs = stage.GetRootLayer().customLayerData.get("skinpipe:colorSpace")
        self.working_colorspace = str(layer_cs or "lin_ap1_scene")
        self._dirty: set[str] = set(CATEGORIES)
        self._time: Any = None
        self._cache: dict[str, Any] = {}
        self._listener = Tf.Notice.Register(Usd.Notice.ObjectsChanged, self._on_change, stage)

    def close(self) -> None:
        self._listener.Revoke()

    def _classify(self, path: Any) -> set[str]:
        prim = self.stage.GetPrimAtPath(path.GetPrimPath())
        if not prim:
            return set(CATEGORIES)  # removed or resynced: re-read everything
        type_name = prim.GetTypeName()
        if type_name in LIGHT_TYPES:
            return {"lights"}
        if type_name == "Camera":
            return {"camera"}
        if type_name == "Mesh":
            return {"geometry"}
        if type_name in ("Material", "Shader", "SkinDiffusionProfile"):
            return {"material"}
        # an xform above meshes, lights or the camera: whatever lies beneath it
        return set(CATEGORIES)

    def _on_change(self, notice: Any, sender: Any) -> None:
        for path in list(notice.GetResyncedPaths()) + list(notice.GetChangedInfoOnlyPaths()):
            self._dirty |= self._classify(path)

    def _time_varying(self) -> set[str]:
        out: set[str] = set()
        for prim in self.stage.Traverse():
            cats = self._classify(prim.GetPath())
            if cats == set(CATEGORIES) and not prim.IsA(UsdGeom.Xformable):
                continue
            xf = UsdGeom.Xformable(prim)
            if xf and xf.TransformMightBeTimeVarying():
                out |= cats if cats != set(CATEGORIES) else self._below(prim)
            for attr in prim.GetAttributes():
                if attr.ValueMightBeTimeVarying():
                    out |= cats if cats != set(CATEGORIES) else self._below(prim)
                    break
        return out

    def _below(self, prim: Any) -> set[str]:
        out: set[str] = set()
        for p in Usd.PrimRange(prim):
            if p != prim:
                cats = self._classify(p.GetPath())
                if cats != set(CATEGORIES):
                    out |= cats
        return out

    def sync(self, time: Any = None) -> SceneData:
        """Re-read what changed (notices) or what may vary at a new ``time``."""
        t = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
        dirty = set(self._dirty)
        if self._time is not None and t != self._time:
            dirty |= self._time_varying()
        self._time = t
        if "geometry" in dirty or "material" in dirty:
            meshes = []
            for prim in self.stage.Traverse():
                if prim.IsA(UsdGeom.Mesh) and UsdGeom.Imageable(prim).ComputeVisibility(t) != \
                        UsdGeom.Tokens.invisible:
                    meshes.append(_read_mesh(prim, t, self.meters_per_unit))
            self._cache["meshes"] = meshes
        if "lights" in dirty:
            lights = []
            for prim in self.stage.Traverse():
                kind = LIGHT_TYPES.get(prim.GetTypeName())
                if kind:
                    lights.append(_read_light(prim, kind, t))
            self._cache["lights"] = lights
        if "camera" in dirty:
            self._cache["camera"] = self._find_camera(t)
        self._dirty.clear()
        return SceneData(self._cache["meshes"], self._cache["lights"], self._cache["camera"],
                         self.meters_per_unit, self.working_colorspace, dirty)

    def _find_camera(self, t: Any) -> Camera | None:
        if self.camera_path:
            prim = self.stage.GetPrimAtPath(self.camera_path)
            if not prim or not prim.IsA(UsdGeom.Camera):
                raise InputError(f"--camera {self.camera_path}: no UsdGeomCamera at that path")
            return _read_camera(prim, t)
        for prim in self.stage.Traverse():
            if prim.IsA(UsdGeom.Camera):
                return _read_camera(prim, t)
        return None
