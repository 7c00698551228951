"""Error against run time: each stage's trade-off measured in one run (JSON + PNG)."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import product
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..fileio import atomic_path, atomic_write_json
from ..profile.fit import FitOptions, fit_sum_of_gaussians
from ..profile.types import MeasuredProfile
from ..render.frame import TaskLog
from ..render.light.raytrace import RayScene
from ..render.options import SHADOW_SAMPLING, RenderOptions
from ..render.renderer import Renderer
from ..render.shading import bilinear, surface_radiance
from ..render.surface.texture_maps import vertex_normals
from ..render.surface.unwrap import triangulate
from ..usd.io import open_stage_guarded

FIT_METHODS: dict[str, dict[str, Any]] = {
    "ga+ipopt": {"init": "ga", "solver": "ipopt"},
    "naive+ipopt": {"init": "naive", "solver": "ipopt"},
    "ga+slsqp": {"init": "ga", "solver": "slsqp"},
}
"""The default (GA seed + IPOPT), IPOPT from a log-spaced start, and the paper's
GA + SQP with scipy's SLSQP standing in for MATLAB's fmincon."""


@dataclass
class TradeoffRow:
    profile: str
    method: str
    k: int
    seconds: float
    error_max: float
    error: list[float]
    objective: float
    status: str
    edge_error: list[float] | None = None
    """What a hard shadow edge shows (:func:`~..profile.edge.edge_report`): the largest
    difference as a share of the plateau, per channel."""
    edge_width_ratio: list[float] | None = None
    """10-90% edge width, fitted over measured, per channel."""
    shadow_light_ratio: list[float] | None = None


def fit_tradeoff(
    profiles: Sequence[MeasuredProfile],
    ks: Sequence[int] = tuple(range(1, 9)),
    methods: Sequence[str] = tuple(FIT_METHODS),
    seed: int = 0,
    progress: Any = None,
) -> list[TradeoffRow]:
    """Fit every profile with every k and method; wall seconds and eq. 2c error per fit."""
    rows = []
    for prof in profiles:
        for method in methods:
            for k in ks:
                start = time.perf_counter()
                fit = fit_sum_of_gaussians(prof, FitOptions(k=k, seed=seed, **FIT_METHODS[method]))
                seconds = time.perf_counter() - start
                edge = fit.edge or {}
                width = None if not edge else (edge["edge_width_mm"]
                                               / edge["edge_width_measured_mm"])
                rows.append(TradeoffRow(
                    prof.name, method, k, seconds, float(fit.error.max()),
                    [float(e) for e in fit.error], fit.objective, fit.status,
                    None if not edge else [float(e) for e in edge["edge_error"]],
                    None if width is None else [float(w) for w in width],
                    None if not edge else [float(s) for s in edge["shadow_light_ratio"]]))
                if progress is not None:
                    progress(f"{prof.name} {method} k={k}: error {fit.error.max():.2e}, "
                             f"{seconds:.2f} s")
    return rows


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of points not dominated in (seconds, error), both minimised (per profile)."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], np.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def _plot_tradeoff(
    points: Sequence[tuple[str, float, float, str]], path: Path, xlabel: str, title: str,
    ylabel: str = "eq. 2c error (max over R, G, B)",
) -> None:
    """Error (log) against seconds (log), one line per series; points labelled."""
    import matplotlib  # lazy: 0.18 s to import

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: 0.56 s to import

    fig, ax = plt.subplots(figsize=(7, 5), dpi=110)
    for series in dict.fromkeys(p[0] for p in points):
        sel = [p for p in points if p[0] == series]
        ax.plot([p[1] for p in sel], [max(p[2], 1e-8) for p in sel], marker="o", alpha=0.8,
                label=series)
        for p in sel:
            ax.annotate(p[3], (p[1], max(p[2], 1e-8)), fontsize=6)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(fontsize=6)
    ax.grid(True, which="both", alpha=0.3)
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    plt.close(fig)


def write_fit_report(rows: Sequence[TradeoffRow], out_dir: Path, default_k: int = 6) -> dict:
    """fit_tradeoff.json and fit_tradeoff.png (error vs seconds, log axes) in ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    front: set[int] = set()
    for prof in {r.profile for r in rows}:
        idx = [i for i, r in enumerate(rows) if r.profile == prof]
        front.update(idx[j] for j in pareto_front([(rows[i].seconds, rows[i].error_max)
                                                   for i in idx]))
    default_rows = [i for i, r in enumerate(rows) if r.method == "ga+ipopt" and r.k == default_k]
    doc = {
        "stage": "fit",
        "error_measure": "max over channels of eq. 2c (Park & Oh 2009)",
        "rows": [r.__dict__ | {"pareto": i in front} for i, r in enumerate(rows)],
        "default": {"method": "ga+ipopt", "k": default_k,
                    "on_pareto_front": [i in front for i in default_rows]},
    }
    atomic_write_json(out_dir / "fit_tradeoff.json", doc)
    _plot_tradeoff(
        [(f"{r.profile} {r.method}", r.seconds, r.error_max, str(r.k)) for r in rows],
        out_dir / "fit_tradeoff.png", "wall time per fit (s)", "Fit: error against run time "
        "(labels: k)",
    )
    return doc


def ingest_tradeoff(seeds: int = 30, option_seeds: int = 5, workers: int | None = None,
                    progress: Any = None) -> list[dict[str, Any]]:
    """Every case of :func:`~skinpipe.capture.study.standard_cases` on the sample
    subject's six regions: the must-hold cases over ``seeds`` seeds, the options and
    effects over ``option_seeds``; one row per case with its summary
    (:func:`~skinpipe.capture.study.summarise`), its settings and its per-region rows.
    The seeds run on ``workers`` processes (default: every core)."""
    import os

    from ..capture.study import run_case, settings_json, standard_cases, summarise

    workers = workers or os.cpu_count() or 1
    rows = []
    for case in standard_cases():
        n = seeds if case.group == "must-hold" else min(option_seeds, seeds)
        per_region = run_case(case, range(n), workers=workers)
        summary = summarise(per_region)
        rows.append({"case": case.name, "group": case.group, "seeds": n, **summary,
                     **settings_json(case), "rows": per_region})
        if progress is not None:
            err = summary["error_max"]
            progress(f"{case.group} / {case.name}: {n} seeds, worst channel "
                     f"{'-' if err is None else f'{err:.2%}'}, refused {summary['refused']}"
                     f" of {summary['regions']}, {summary['seconds']:.2f} s a region")
    return rows


def write_ingest_report(rows: Sequence[dict[str, Any]], out_dir: Path) -> dict:
    """ingest_tradeoff.json and ingest_tradeoff.png in ``out_dir``: per case the worst
    channel's error against the seconds per region; issue 20's must-hold."""
    from ..capture.study import must_hold

    out_dir.mkdir(parents=True, exist_ok=True)
    timed = [r for r in rows if r["error_max"] is not None and r["group"] == "options"]
    front = set(pareto_front([(r["seconds"], r["error_max"]) for r in timed]))
    pareto = {id(r): i in front for i, r in enumerate(timed)}
    doc = {"stage": "ingest",
           "error_measure": "max over channels, regions and seeds of eq. 2c, the ingested "
                            "profile against the simulator's observed truth (both "
                            "normalised over the plane), 0.05-4 mm",
           "default": {"case": "default", "on_pareto_front": [
               pareto.get(id(r), False) for r in rows if r["case"] == "default"]},
           "must_hold": must_hold({(r["group"], r["case"]): r for r in rows}),
           "rows": [dict(r) | {"pareto": pareto.get(id(r), False)} for r in rows]}
    atomic_write_json(out_dir / "ingest_tradeoff.json", doc)
    points = [(r["group"], r["seconds"], r["error_max"], r["case"]) for r in rows
              if r["error_max"] is not None]
    _plot_tradeoff(points, out_dir / "ingest_tradeoff.png", "ingest seconds per region",
                   "Ingest: worst channel's error against run time (labels: cases)")
    return doc


# ------------------------------------------------------------------------------ render


def render_tradeoff(scene: Path, sizes: Sequence[int] = (512, 1024, 2048),
                    grids: Sequence[int] = (0, 8, 12), light_samples: int = 8,
                    points: int = 400, seed: int = 0, progress: Any = None,
                    blurs: Sequence[str] = ("recursive",)) -> list[dict[str, Any]]:
    """Texture-space diffusion error against its time, per texture size, variance grid
    and blur (recursive pyramid or gather).

    The reference is a brute-force convolution on the surface: at ``points`` random
    surface points p, sum_j E_j A_j R_p(|p - p_j|) over every texel j of the finest
    irradiance map (E after the albedo split, A_j its area in mm^2, R_p each region's
    exact fitted profile blended by p's region weights, distances in 3D mm). Each row's
    diffused radiance is looked up at p's texture coordinates. Error: RMS over points
    of the relative difference, max over channels. Seconds: texture maps + irradiance +
    diffusion at that size.
    """
    from scipy.spatial import cKDTree  # lazy: 0.39 s to import

    stage = open_stage_guarded(scene)
    finest: dict[str, Any] = {}
    results = []
    cases = [(g, b) for g in grids for b in blurs]
    for size in sorted(sizes, reverse=True):
        for grid, blur in cases:
            # no image (8 x 8 pixels): interleaving period 2, not the period the texels
            # per pixel of such an image would take
            opts = RenderOptions(texture_size=size, light_samples=light_samples,
                                 variance_grid=grid, resolution=(8, 8), blur=blur,
                                 interleave_period=2)
            renderer = Renderer(stage, opts)
            try:
                sc = renderer.delegate.sync()
                if not sc.skin or not sc.lights:
                    raise InputError("the scene needs a skin mesh and lights", scene)
                log = TaskLog()
                rays = RayScene([(m.mesh.points, triangulate(m.mesh)) for m in sc.meshes])
                mesh = sc.skin[0]
                t0 = time.perf_counter()
                tex = renderer.texture_space(log, sc, mesh, rays)
                # the texture maps, irradiance and diffusion (its layout made beside the
                # irradiance), without the UVs and the albedo
                seconds = time.perf_counter() - t0 - sum(
                    log.seconds.get(task, 0.0) for task in ("unwrap", "albedo"))
            finally:
                renderer.close()
            if not finest:
                covered = tex.maps.triangle >= 0
                a = opts.albedo_split
                albedo = tex.albedo_map()
                finest = {
                    "pos": tex.maps.surface[0][covered].astype(np.float64) * sc.meters_per_unit
                    * 1000.0,
                    "area": (tex.maps.mm_per_texel_u * tex.maps.mm_per_texel_v)[covered].astype(
                        np.float64),
                    "flux": (tex.irradiance * np.power(albedo, a))[covered] * (
                        tex.maps.mm_per_texel_u * tex.maps.mm_per_texel_v)[covered][:, None],
                }
                rng = np.random.default_rng(seed)
                tris = tex.tris
                pick = rng.integers(0, tris.shape[0], points)
                b = rng.dirichlet([1, 1, 1], points)[:, :, None]
                p_mm = (mesh.mesh.points[tris[pick]] * b).sum(axis=1) * sc.meters_per_unit * 1e3
                uv = (tex.uv[tex.uv_tris[pick]] * b).sum(axis=1)
                rw = (mesh.region_weights[tris[pick]] * b).sum(axis=1)
                tree = cKDTree(finest["pos"])
                ref = np.zeros((points, 3))
                vmax = max(float(f.variances_mm2.max()) for f in mesh.fits)
                for n in range(points):
                    idx = np.asarray(tree.query_ball_point(p_mm[n], 4.0 * math.sqrt(vmax)))
                    d = np.linalg.norm(finest["pos"][idx] - p_mm[n], axis=1)
                    # each texel is a small square source: its footprint (variance
                    # area / 12 per axis) widens every term, or sub-texel terms would
                    # be point-sampled to nothing
                    foot = finest["area"][idx] / 12.0
                    prof = np.zeros((idx.size, 3))
                    for r, fit in enumerate(mesh.fits):
                        if rw[n, r] > 0:
                            w = fit.weights / fit.weights.sum(axis=0, keepdims=True)
                            for v, wk in zip(fit.variances_mm2, w, strict=True):
                                vv = v + foot
                                g = np.exp(-d * d / (2 * vv)) / (2 * math.pi * vv)
                                prof += rw[n, r] * g[:, None] * wk
                    ref[n] = (finest["flux"][idx] * prof).sum(axis=0)
                albedo_at = bilinear(albedo, uv)
                ref *= np.power(albedo_at, 1.0 - a) / math.pi
                normal = (vertex_normals(mesh.mesh.points, tris)[tris[pick]] * b).sum(axis=1)
                normal /= np.linalg.norm(normal, axis=1, keepdims=True)
                finest.update(uv=uv, ref=ref, p_mm=p_mm, normal=normal, albedo=albedo_at)
            got = bilinear(tex.radiance, finest["uv"]).astype(np.float64)
            if tex.surface_light is not None:  # the wide terms, summed on the surface
                got += surface_radiance(tex.surface_light, renderer.device, finest["p_mm"],
                                        finest["normal"], finest["albedo"],
                                        1.0 - opts.albedo_split)
            ref = finest["ref"]
            rel = np.sqrt(((got - ref) ** 2).mean(axis=0)) / np.maximum(ref.mean(axis=0), 1e-30)
            # per point, relative to its own value but at least 1e-3 of the brightest
            # point's: deep in a shadow the reference falls to 1e-30 while any blur
            # (float32, or a recursive filter's exponential tail) leaves ~1e-7
            point_rel = np.abs(got - ref).max(axis=1) / np.maximum(
                ref.max(axis=1), 1e-3 * float(ref.max()))
            diff = log.measures["diffusion"]
            results.append({"texture_size": size, "variance_grid": grid, "blur": blur,
                            "seconds": seconds,
                            "diffusion_seconds": log.seconds.get("diffusion", 0.0),
                            "error_max": float(rel.max()), "error": rel.tolist(),
                            "error_median_point": float(np.median(point_rel)),
                            "error_p90_point": float(np.percentile(point_rel, 90)),
                            "blur_passes": diff["blur_passes"],
                            "mm_per_texel": diff["mm_per_texel_median"],
                            "energy_ratio": diff["energy_ratio"]})
            if progress:
                progress(f"texture {size} grid {grid} {blur}: error {rel.max():.2e}, "
                         f"{seconds:.1f} s")
    rows = sorted(results, key=lambda r: (r["texture_size"], r["variance_grid"], r["blur"]))
    return rows


def write_render_report(rows: Sequence[dict[str, Any]], out_dir: Path,
                        default: tuple[int, int, str] = (1024, 12, "recursive")
                        ) -> dict[str, Any]:
    """render_tradeoff.json and render_tradeoff.png in ``out_dir``."""
    return _write_tradeoff(
        out_dir, "render", "RMS relative difference to a brute-force surface convolution, "
        "max over R, G, B", rows,
        dict(zip(("texture_size", "variance_grid", "blur"), default, strict=True)),
        [(f"{r['blur']}, grid {r['variance_grid'] or 'per-region'}", r["seconds"],
          r["error_max"], str(r["texture_size"])) for r in rows],
        "texture maps + irradiance + diffusion (s)",
        "Render: error against run time (labels: texture size)",
        "RMS relative error vs brute-force convolution")


def _write_tradeoff(out_dir: Path, stage: str, error_measure: str,
                    rows: Sequence[dict[str, Any]], default: dict[str, Any],
                    points: Sequence[tuple[str, float, float, str]], xlabel: str, title: str,
                    ylabel: str) -> dict[str, Any]:
    """``<stage>_tradeoff.json`` (the rows with their Pareto flags, the default's values
    and whether its rows are on the front) and ``<stage>_tradeoff.png`` in ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    front = set(pareto_front([(r["seconds"], r["error_max"]) for r in rows]))
    doc = {
        "stage": stage,
        "error_measure": error_measure,
        "rows": [dict(r) | {"pareto": i in front} for i, r in enumerate(rows)],
        "default": default | {"on_pareto_front": [
            i in front for i, r in enumerate(rows)
            if all(r.get(k) == v for k, v in default.items())]},
    }
    atomic_write_json(out_dir / f"{stage}_tradeoff.json", doc)
    _plot_tradeoff(points, out_dir / f"{stage}_tradeoff.png", xlabel, title, ylabel)
    return doc


def lighting_tradeoff(scene: Path, texture_size: int = 1024,
                      light_samples: Sequence[int] = (4, 8, 16, 32),
                      sampling: Sequence[str] = SHADOW_SAMPLING, reference_samples: int = 256,
                      progress: Any = None, sequences: Sequence[str] = ("sobol",)
                      ) -> list[dict[str, Any]]:
    """Irradiance error against its time, per light samples, shadow sampling (adaptive,
    interleaved, full) and light sample sequence (stratified, sobol), on the skin's
    texels at ``texture_size``.

    The reference is the same texels lit with ``reference_samples`` samples per light,
    every texel tracing all of them. Error: RMS over covered texels (weighted by their
    area in mm^2) of the difference in entering irradiance, over its mean, max over
    R, G, B. Seconds: the irradiance task (shadow rays, sampling, reconstruction).
    """
    stage = open_stage_guarded(scene)

    def irradiance(samples: int, mode: str, sequence: str
                   ) -> tuple[NDArray[Any], NDArray[Any], dict[str, Any]]:
        # the error is per texel: interleaving period 2, whatever the texels per pixel
        # (a larger one is chosen for an image that averages several texels a pixel)
        opts = RenderOptions(texture_size=texture_size, light_samples=samples,
                             shadow_sampling=mode, light_sequence=sequence, resolution=(8, 8),
                             interleave_period=2)
        renderer = Renderer(stage, opts)
        try:
            sc = renderer.delegate.sync()
            if not sc.skin or not sc.lights:
                raise InputError("the scene needs a skin mesh and lights", scene)
            log = TaskLog()
            rays = RayScene([(m.mesh.points, triangulate(m.mesh)) for m in sc.meshes])
            tex = renderer.skin_textures(log, sc, sc.skin[0])
            renderer.irradiance(log, sc, tex, rays, {})
        finally:
            renderer.close()
        covered = tex.maps.triangle >= 0
        area = (tex.maps.mm_per_texel_u * tex.maps.mm_per_texel_v)[covered]
        return tex.irradiance[covered].astype(np.float64), area, log.measures["irradiance"]

    reference, area, _ = irradiance(reference_samples, "full", "stratified")
    weights = area / area.sum()
    mean = (reference * weights[:, None]).sum(axis=0)
    rows = []
    for samples, mode, sequence in product(light_samples, sampling, sequences):
        got, _, measures = irradiance(samples, mode, sequence)
        rms = np.sqrt(((got - reference) ** 2 * weights[:, None]).sum(axis=0))
        error = float((rms / np.maximum(mean, 1e-30)).max())
        rows.append({"texture_size": texture_size, "light_samples": samples,
                     "shadow_sampling": mode, "light_sequence": sequence,
                     "seconds": measures["seconds"],
                     "rays_per_texel": measures["rays_per_texel"],
                     "penumbra_texels": measures["penumbra_texels"],
                     "error_max": error})
        if progress:
            progress(f"light samples {samples} {mode} {sequence}: error {error:.2e}, "
                     f"{measures['seconds']:.1f} s, {measures['rays_per_texel']:.1f} "
                     "rays a texel")
    return rows


def write_lighting_report(rows: Sequence[dict[str, Any]], out_dir: Path,
                          default: tuple[int, str, str] = (16, "interleaved", "sobol")
                          ) -> dict[str, Any]:
    """lighting_tradeoff.json and lighting_tradeoff.png in ``out_dir``."""
    return _write_tradeoff(
        out_dir, "lighting", "area-weighted RMS of the entering irradiance's difference to "
        "full sampling at many samples, over its mean, max over R, G, B", rows,
        dict(zip(("light_samples", "shadow_sampling", "light_sequence"), default,
                 strict=True)),
        [(f"{r['shadow_sampling']}, {r['light_sequence']}", r["seconds"], r["error_max"],
          str(r["light_samples"])) for r in rows],
        "irradiance (s)", "Irradiance: error against run time (labels: light samples)",
        "RMS relative error vs many samples")


# --------------------------------------------------------------------- one page


def _default_sentence(doc: dict[str, Any], what: str) -> str:
    flags = doc.get("default", {}).get("on_pareto_front", [])
    if not flags:
        return f"The default ({what}) was not among the measured rows."
    on = sum(bool(f) for f in flags)
    if on == len(flags):
        return f"The default ({what}) is on the Pareto front."
    return (f"The default ({what}) is on the Pareto front for {on} of {len(flags)} "
            "measured profiles; see the table for where it is not.")


def _table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return out


def _percent(value: float | None) -> str:
    return "-" if value is None else f"{value:.2%}"


def write_report_page(out_dir: Path) -> Path:
    """report.md in ``out_dir``: every stage's trade-off found there (fit_tradeoff.json,
    ingest_tradeoff.json, render_tradeoff.json, lighting_tradeoff.json) with its plot, its
    table, the Pareto front marked (*) and whether the default sits on it."""
    lines = ["# skinpipe: error against run time", "",
             "Each stage measured in one run; pick an operating point from the plots. "
             "Rows marked * are on the Pareto front (no other row is both faster and more "
             "accurate).", ""]
    found = False
    fit_path = out_dir / "fit_tradeoff.json"
    if fit_path.is_file():
        found = True
        doc = json.loads(fit_path.read_text())
        d = doc["default"]
        lines += ["## Fit", "", f"Error: {doc['error_measure']}. Seconds: wall time per fit.",
                  "", "![fit](fit_tradeoff.png)", "",
                  _default_sentence(doc, f"{d['method']}, k = {d['k']}"), ""]
        lines += ["Edge: what a hard shadow edge shows against the measured profile, the "
                  "worst channel: the largest difference of the edge (share of the plateau), "
                  "the 10-90% width and the light in the shadow, fitted over measured.", ""]

        def worst(values: list[float] | None, ratio: bool = False) -> str:
            if not values:
                return "-"
            v = max(values, key=lambda x: abs(x - 1)) if ratio else max(values)
            return f"{v:.3f}" if ratio else f"{v:.2%}"

        lines += _table(["profile", "method", "k", "seconds", "eq. 2c", "edge", "width",
                         "shadow light", ""],
                        [(r["profile"], r["method"], r["k"], f"{r['seconds']:.2f}",
                          f"{r['error_max']:.2e}", worst(r.get("edge_error")),
                          worst(r.get("edge_width_ratio"), True),
                          worst(r.get("shadow_light_ratio"), True),
                          "*" if r["pareto"] else "")
                         for r in doc["rows"]])
        lines.append("")
    ingest_path = out_dir / "ingest_tradeoff.json"
    if ingest_path.is_file():
        found = True
        doc = json.loads(ingest_path.read_text())
        lines += ["## Ingest", "", f"Error: {doc['error_measure']}. Seconds: ingest per "
                  "region. Groups: ingest's options on the realistic captures; the "
                  "captures' effects, each turned off (or hair on); issue 20's must-hold.",
                  "", "![ingest](ingest_tradeoff.png)", "",
                  _default_sentence(doc, "the default options") + " (among the options)", ""]
        lines += _table(["group", "case", "seeds", "seconds", "error mean", "error max",
                         "flux max", "refused", ""],
                        [(r["group"], r["case"], r["seeds"], f"{r['seconds']:.2f}",
                          _percent(r["error_mean"]), _percent(r["error_max"]),
                          _percent(r["flux_error_max"]), f"{r['refused']}/{r['regions']}",
                          "*" if r.get("pareto") else "") for r in doc["rows"]])
        lines += ["", "Must hold (issue 20):", ""]
        lines += _table(["condition", "value", "limit", "holds"],
                        [(k, _percent(v["value"]) if "limit" in v else
                          f"{v['value']}/{v['of']}", _percent(v["limit"]) if "limit" in v
                          else "all", "yes" if v["holds"] else "NO")
                         for k, v in doc["must_hold"].items()])
        lines.append("")
    render_path = out_dir / "render_tradeoff.json"
    if render_path.is_file():
        found = True
        doc = json.loads(render_path.read_text())
        d = doc["default"]
        lines += ["## Render", "", f"Error: {doc['error_measure']}. Seconds: texture maps + "
                  "irradiance + diffusion; diffusion alone beside it.", "",
                  "![render](render_tradeoff.png)", "",
                  _default_sentence(doc, f"texture {d['texture_size']}, grid "
                                    f"{d['variance_grid']}, {d.get('blur', 'recursive')}"), ""]
        lines += _table(["texture", "grid", "blur", "mm/texel", "seconds", "diffusion s",
                         "RMS error", "median point", ""],
                        [(r["texture_size"], r["variance_grid"] or "per-region",
                          r.get("blur", "recursive"), f"{r['mm_per_texel']:.3f}",
                          f"{r['seconds']:.2f}", f"{r['diffusion_seconds']:.2f}",
                          f"{r['error_max']:.2e}", f"{r['error_median_point']:.2e}",
                          "*" if r["pareto"] else "") for r in doc["rows"]])
        lines.append("")
    lighting_path = out_dir / "lighting_tradeoff.json"
    if lighting_path.is_file():
        found = True
        doc = json.loads(lighting_path.read_text())
        d = doc["default"]
        lines += ["## Irradiance (light samples, shadow sampling)", "",
                  f"Error: {doc['error_measure']}. Seconds: the irradiance task.", "",
                  "![lighting](lighting_tradeoff.png)", "",
                  _default_sentence(doc, f"{d['light_samples']} samples, "
                                    f"{d['shadow_sampling']}, "
                                    f"{d.get('light_sequence', 'stratified')}"), ""]
        lines += _table(["texture", "samples", "shadow sampling", "sequence", "rays/texel",
                         "seconds", "RMS error", ""],
                        [(r["texture_size"], r["light_samples"], r["shadow_sampling"],
                          r.get("light_sequence", "stratified"),
                          f"{r['rays_per_texel']:.1f}", f"{r['seconds']:.2f}",
                          f"{r['error_max']:.2e}", "*" if r["pareto"] else "")
                         for r in doc["rows"]])
        lines.append("")
    if not found:
        raise InputError("no *_tradeoff.json to gather: run 'skinpipe report fit|ingest|"
                         "render' into this directory first", out_dir)
    page = out_dir / "report.md"
    with atomic_path(page) as tmp:
        tmp.write_text("\n".join(lines))
    return page
