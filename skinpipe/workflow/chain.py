"""One subject through the stages: the steps that ``skinpipe run``, ``skinpipe demo`` and
``skinpipe batch`` share, written once.

ingest -> fit (each region's ingested profile, its scale free) -> author (regions from
landmarks or a primvar, measured samples embedded) -> (paint) -> validate -> shot ->
render (-> the demo's comparison renders). Nothing here prints: progress goes to a
callback, results come back as data for the caller to show.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio
from pxr import UsdGeom

from ..capture.ingest import ingest_capture_set, read_capture_set
from ..errors import InputError
from ..imageio import oiio_error, write_ldr
from ..profile.fit import FitOptions, check_terms, fit_sum_of_gaussians
from ..profile.io import read_fit_inputs, read_profile_csv, write_fit_json
from ..profile.types import FitResult, MeasuredProfile
from ..render.device.choice import open_device
from ..render.device.programs import start_prewarm
from ..render.diffusion.push_pull import push_pull_kernels
from ..render.options import RenderOptions
from ..render.outputs import render_files, write_outputs
from ..render.renderer import Renderer
from ..render.surface.texture_maps import texture_kernels
from ..render.surface.uvs import ensure_skin_uvs
from ..usd.author import (
    AssetPaths,
    RegionAssignment,
    assign_regions_from_landmarks,
    author_asset,
    check_landmarks_on_mesh,
    read_landmarks,
)
from ..usd.io import USD_SUFFIXES, open_stage_guarded, usd_inputs
from ..usd.materialx import library as mtlx_library
from ..usd.mesh import MeshData, ScanPreparation, load_mesh, prepare_scan, seal_scan
from ..usd.shot import author_shot
from ..usd.validate import validate_file
from .albedo import bake_sample_albedo

Progress = Callable[[str], None]


def _quiet(_: str) -> None:
    pass


def fit_ingested_profile(profile: MeasuredProfile, k: int) -> FitResult:
    """Fit ``k`` Gaussians to an ingested profile: it integrates to 1 over the plane with
    the tail beyond the image extrapolated, which is known to a few % only, so its total
    reflectance is fitted too (``free_scale``)."""
    return fit_sum_of_gaussians(profile, FitOptions(k=k, free_scale=True))


def measured_for(fits: list[FitResult], profiles_dir: Path | None
                 ) -> dict[str, MeasuredProfile]:
    """Each fit's measured samples: ``profiles_dir/<name>.csv``, else the fit's source CSV
    (where it exists)."""
    out = {}
    for fit in fits:
        if profiles_dir is not None:
            csv: Path | None = profiles_dir / f"{fit.name}.csv"
        else:
            csv = Path(fit.source) if fit.source else None
        if csv is not None and csv.is_file():
            out[fit.name] = read_profile_csv(csv, name=fit.name)
    return out


def _regions_from_primvar(mesh_path: Path, mesh: Any, mesh_prim: str | None,
                          region_primvar: str, region_names: list[str] | None
                          ) -> RegionAssignment:
    stage = open_stage_guarded(mesh_path)
    prim = stage.GetPrimAtPath(mesh_prim) if mesh_prim else next(
        p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar(region_primvar)
    if not pv or not pv.HasValue() or pv.GetInterpolation() != UsdGeom.Tokens.uniform:
        raise InputError(f"no uniform primvar {region_primvar!r} on {prim.GetPath()}",
                         mesh_path)
    idx = np.asarray(pv.Get(), dtype=np.int32)
    if not region_names:
        raise InputError("--region-primvar needs --region-names A,B,... (one per value)")
    if idx.size != mesh.n_faces or idx.min() < 0 or idx.max() >= len(region_names):
        raise InputError(f"{region_primvar} must hold one index in 0..{len(region_names) - 1}"
                         f" per face ({mesh.n_faces} faces)", mesh_path)
    return RegionAssignment(tuple(region_names), idx)


def author_inputs(fits_paths: list[Path], mesh_path: Path, landmarks: Path | None,
                  profiles_dir: Path | None) -> list[Path]:
    """The files the author stage reads (no output may replace them): FIT.jsons, the
    mesh (with its layers when it is USD), landmarks and measured profiles."""
    reads = [p for f in fits_paths for p in (sorted(f.glob("*.json")) if f.is_dir() else [f])]
    reads += usd_inputs(mesh_path) if mesh_path.suffix.lower() in USD_SUFFIXES and \
        mesh_path.is_file() else [mesh_path]
    reads += [p for p in (landmarks,) if p is not None]
    if profiles_dir is not None and profiles_dir.is_dir():
        reads += sorted(profiles_dir.glob("*.csv"))
    return reads


PREPARED_FACES = 60000
"""Faces a raw scan is decimated to by ``prepare`` (:func:`~..usd.mesh.prepare_scan`)."""


def author_from_files(fits_paths: list[Path], mesh_path: Path, out: Path, *,
                      landmarks: Path | None = None, region_primvar: str | None = None,
                      region_names: list[str] | None = None, blend_mm: float = 8.0,
                      profiles_dir: Path | None = None, meters_per_unit: float | None = None,
                      prepare: bool = False, target_faces: int = PREPARED_FACES,
                      name: str = "Face",
                      mesh_prim: str | None = None, progress: Progress = _quiet,
                      loaded: MeshData | None = None,
                      prepared: ScanPreparation | None = None) -> AssetPaths:
    """The author stage from files: FIT.json files (or folders of them) and a mesh to a
    USD asset, regions from landmarks or from a uniform primvar of a USD mesh
    (``loaded``: the mesh at ``mesh_path``, already loaded and validated; ``prepared``:
    its preparation, started earlier, which ``prepare`` then waits for)."""
    fits = read_fit_inputs(fits_paths)
    mesh = loaded if loaded is not None else load_mesh(mesh_path, meters_per_unit, mesh_prim)
    seal = None
    if prepare and prepared is not None:
        mesh, seal = prepared.result()
    elif prepare:
        progress(f"preparing the scan ({mesh.n_faces} faces -> {target_faces})")
        mesh = prepare_scan(mesh, target_faces)
        seal = seal_scan(mesh)
    if landmarks is not None:
        regions = assign_regions_from_landmarks(mesh, read_landmarks(landmarks), blend_mm)
    elif region_primvar is not None:
        regions = _regions_from_primvar(mesh_path, mesh, mesh_prim, region_primvar,
                                        region_names)
    else:
        raise InputError("give --landmarks or --region-primvar to place the regions")
    return author_asset(fits, mesh, regions, out, name=name,
                        measured=measured_for(fits, profiles_dir), seal=seal)


def chain_inputs(captures: Path, mesh_path: Path, landmarks: Path, k: int
                 ) -> tuple[list[Path], MeshData]:
    """Check every input of :func:`run_chain` before its first write: the capture set,
    the mesh (loaded and validated), the landmarks (each region's points on the mesh,
    one region per captured region) and ``k``. Returns the files it reads and the mesh
    (for :func:`run_chain`, which then does not load it again)."""
    check_terms(k)
    capture_set = read_capture_set(captures)
    mesh = load_mesh(mesh_path)
    marks = read_landmarks(landmarks)
    if set(marks) != set(capture_set.regions):
        raise InputError(f"the landmarks' regions {sorted(marks)} are not the captured ones "
                         f"{sorted(capture_set.regions)}", landmarks)
    check_landmarks_on_mesh(mesh, marks)
    return capture_set.files + author_inputs([], mesh_path, landmarks, None), mesh


@dataclass
class FitRow:
    """One region's fit, as ``run`` and ``demo`` show it."""

    region: str
    terms: int
    error_eq2c: float
    """Worst channel."""
    error_vs_truth: float | None
    seconds: float


@dataclass
class ChainResult:
    """What :func:`run_chain` did: ``report`` (report.json), one row per region, the
    render's ``render.json`` document, and whether the asset validated."""

    report: dict[str, Any]
    fit_rows: list[FitRow] = field(default_factory=list)
    render_doc: dict[str, Any] = field(default_factory=dict)

    @property
    def valid(self) -> bool:
        return bool(self.report["valid"])


def run_chain(captures: Path, mesh: Path, landmarks: Path, out: Path, k: int,
              prepare: bool, paint: bool, options: RenderOptions, ocio: str,
              truth: dict[str, Any] | None = None, comparisons: bool = False,
              progress: Progress = _quiet, loaded_mesh: MeshData | None = None
              ) -> ChainResult:
    """ingest -> fit -> author -> (paint) -> validate -> shot -> render (-> the demo's
    comparison renders, which reuse the render's texture-space work)."""
    start = time.perf_counter()
    result = ChainResult({"stages": {}, "regions": {}})
    report = result.report
    device = None
    if paint:
        # the device asked for is the first OpenCL work's (the loader lists its runtimes
        # once, at that first query); the painter's kernels are built (on PoCL, compiled)
        # and MaterialX's libraries loaded while the captures are ingested: 0.4-0.5 s of
        # a 1 s paint stage otherwise
        device = open_device(options.device)
        start_prewarm(device, [partial(texture_kernels, device),
                               partial(push_pull_kernels, device), mtlx_library])
    scan = None
    if prepare:
        scan = loaded_mesh = loaded_mesh if loaded_mesh is not None else load_mesh(mesh)
        # the scan is cleaned and decimated in a child process while the captures are
        # ingested and fitted: 4 s of the author stage otherwise
        progress(f"preparing the scan in a child process ({scan.n_faces} faces -> "
                 f"{PREPARED_FACES})")
    with ScanPreparation(scan, PREPARED_FACES) if scan is not None else nullcontext() as \
            preparation:
        progress(f"ingest {captures}")
        ingest = ingest_capture_set(captures, out / "profiles", progress=progress)
        report["stages"]["ingest"] = {"seconds": time.perf_counter() - start}
        fit_s = 0.0
        for name, entry in ingest["regions"].items():
            prof = read_profile_csv(entry["csv"])
            fit = fit_ingested_profile(prof, k)
            write_fit_json(out / "fits" / f"{name}.json", fit)
            fit_s += fit.seconds
            row: dict[str, Any] = {"ingest_seconds": entry["seconds"],
                                   "fit_seconds": fit.seconds, "fit_error": fit.error.tolist(),
                                   "fit": str(out / "fits" / f"{name}.json")}
            vs = None
            if truth and name in truth:
                # the shape: the render normalises each fit, so its scale (which carries
                # the extrapolated tail's error) does not reach the image
                err = truth[name].profile_error(prof.radius_mm, fit.evaluate(prof.radius_mm),
                                                over="disk")
                row["error_vs_truth"] = err.tolist()
                vs = float(err.max())
            report["regions"][name] = row
            result.fit_rows.append(FitRow(name, len(fit.variances_mm2),
                                          float(fit.error.max()), vs, fit.seconds))
            progress(f"fit {name}: eq. 2c error {fit.error.max():.2e}")
        report["stages"]["fit"] = {"seconds": fit_s}
        t0 = time.perf_counter()
        progress(f"author {out / 'asset'}")
        paths = author_from_files([out / "fits"], mesh, out / "asset", landmarks=landmarks,
                                  profiles_dir=out / "profiles", prepare=prepare,
                                  progress=progress, loaded=loaded_mesh, prepared=preparation)
        report["stages"]["author"] = {"seconds": time.perf_counter() - t0,
                                      "asset": str(paths.asset)}
    if paint:
        # the unwrap is its own stage: painting then finds the asset's UVs
        t0 = time.perf_counter()
        uvs = ensure_skin_uvs(paths.asset, progress)
        report["stages"]["unwrap"] = {"seconds": time.perf_counter() - t0, "uvs": uvs.note}
        t0 = time.perf_counter()
        texture = bake_sample_albedo(paths.asset, options.texture_size, progress=progress,
                                     device=device)
        report["stages"]["paint_albedo"] = {"seconds": time.perf_counter() - t0,
                                            "texture": str(texture)}
    t0 = time.perf_counter()
    check = validate_file(paths.asset)
    report["stages"]["validate"] = {"seconds": time.perf_counter() - t0,
                                    "problems": [p.message for p in check.problems]}
    scene = author_shot(paths.asset, out / "scene.usda")
    t0 = time.perf_counter()
    renderer = Renderer(open_stage_guarded(scene), options, progress)
    try:
        doc = render_files(scene, out / "render", options, None, ocio, "Face",
                           progress=progress, renderer=renderer)
        result.render_doc = doc
        report["stages"]["render"] = {"seconds": time.perf_counter() - t0,
                                      "tasks": doc["frames"][0]["tasks"],
                                      "render_json": str(out / "render" / "render.json")}
        if comparisons:
            t0 = time.perf_counter()
            report["comparisons"] = demo_comparisons(renderer, out / "render", ocio)
            report["stages"]["comparisons"] = {"seconds": time.perf_counter() - t0}
    finally:
        renderer.close()
    report["valid"] = not check.failed(strict=False)
    report["total_seconds"] = time.perf_counter() - start
    return result


def side_by_side(left: Path, right: Path, out: Path, labels: tuple[str, str]) -> Path:
    """Two display PNGs next to each other over a grey backdrop, labelled if OIIO can
    find a font."""
    tiles = []
    for path, label in zip((left, right), labels, strict=True):
        buf = oiio.ImageBuf(str(path))
        px = np.asarray(buf.get_pixels(oiio.FLOAT), dtype=np.float32)
        if buf.has_error or px.ndim != 3 or px.shape[2] < 4:
            raise InputError(f"cannot read {path}: {oiio_error(buf)}", path)
        # OpenImageIO reads a PNG's colour premultiplied by its alpha: over the backdrop
        rgb, a = px[..., :3], px[..., 3:4]
        tile = oiio.ImageBuf(oiio.ImageSpec(px.shape[1], px.shape[0], 3, "float"))
        tile.set_pixels(oiio.ROI(), np.ascontiguousarray(rgb + 0.18 * (1 - a)))
        oiio.ImageBufAlgo.render_text(tile, 12, 28, label, 22, "", [1.0, 1.0, 1.0])
        tiles.append(np.asarray(tile.get_pixels(oiio.FLOAT)))
    return write_ldr(out, np.concatenate(tiles, axis=1), 8)


def demo_comparisons(renderer: Renderer, out: Path, ocio: str) -> dict[str, Any]:
    """The paper's figure 7 (texture-mapped only vs with scattering) and per-region vs one
    profile, rendered with ``renderer`` (which has rendered the scene with scattering and
    per-region profiles), so only diffusion and shading run again."""
    base = replace(renderer.options, aovs=("beauty",), scattering=True, single_profile=None)
    result: dict[str, Any] = {}
    pngs = {"scattering": out / "Face.png"}
    for label, opts in (("texture_only", {"scattering": False}),
                        ("one_profile", {"single_profile": "mean"})):
        renderer.options = replace(base, **opts)
        t0 = time.perf_counter()
        images, log = renderer.render()
        written = write_outputs(out, f"Face_{label}", images,
                                renderer.delegate.working_colorspace, ocio)
        pngs[label] = Path(written["png"])
        result[label] = {"seconds": time.perf_counter() - t0, "cached": log.cached,
                         "png": written["png"]}
    result["figure7"] = str(side_by_side(pngs["texture_only"], pngs["scattering"],
                                         out / "figure7_texture_vs_scattering.png",
                                         ("texture-mapped only", "with scattering")))
    result["regions_vs_one"] = str(side_by_side(pngs["scattering"], pngs["one_profile"],
                                                out / "per_region_vs_one_profile.png",
                                                ("six regional profiles", "one mean profile")))
    return result
