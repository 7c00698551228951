"""``skinpipe run``: ingest, fit, author, shot and render in one go."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from ..errors import EXIT_CHECK_FAILED, EXIT_OK, InputError
from .common import (
    HelpFormatter,
    TaskBar,
    add_force_option,
    add_render_options,
    ocio_source,
    render_options,
)
from .render import _print_render


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="ingest, fit, author and render in one go",
        description=(
            "Chain the stages on one capture set: ingest CAPTURES into OUT/profiles, fit "
            "each region into OUT/fits, author OUT/asset on MESH (regions from "
            "--landmarks), optionally paint a sample albedo, write the shot layer "
            "OUT/scene.usda and render it into OUT/render."
        ),
        formatter_class=HelpFormatter,
    )
    p.add_argument("captures", type=Path, help="capture set directory (capture.json)")
    p.add_argument("--mesh", type=Path, required=True, help="face mesh (USD, PLY, OBJ)")
    p.add_argument("--landmarks", type=Path, required=True, help="region landmarks JSON")
    p.add_argument("--prepare-scan", action="store_true", help="clean/decimate a raw scan")
    p.add_argument("--paint-albedo", action="store_true",
                   help="paint the procedural skin albedo (for meshes without colour)")
    p.add_argument("-k", type=int, default=6, help="Gaussians per profile")
    add_render_options(p)
    p.add_argument("-o", "--output", type=Path, required=True, help="output directory")
    add_force_option(p)
    p.set_defaults(handler=cmd_run)


def print_chain(result: Any) -> None:
    """The region table, the asset's validity, the render and the comparisons (stdout)."""
    print(f"{'region':<10} {'terms':>5} {'fit err (eq.2c)':>16} {'vs truth':>9} {'fit s':>6}")
    for row in result.fit_rows:
        vs = "-" if row.error_vs_truth is None else f"{row.error_vs_truth:.2e}"
        print(f"{row.region:<10} {row.terms:>5} {row.error_eq2c:>16.2e} {vs:>9} "
              f"{row.seconds:>6.2f}")
    report = result.report
    print(f"asset: {report['stages']['author']['asset']} "
          f"({'valid' if result.valid else 'INVALID'})")
    _print_render(result.render_doc)
    for key in ("figure7", "regions_vs_one"):
        if key in report.get("comparisons", {}):
            print(f"wrote {report['comparisons'][key]}")


def cmd_run(args: argparse.Namespace) -> int:
    if not (args.captures / "capture.json").is_file():
        raise InputError("not a capture set (no capture.json)", args.captures)
    return run_staged(args, "run", args.captures, args.mesh, args.landmarks,
                      args.prepare_scan, args.paint_albedo)


def run_staged(args: argparse.Namespace, verb: str, captures: Path, mesh: Path,
               landmarks: Path, prepare: bool, paint: bool,
               truth: dict[str, Any] | None = None) -> int:
    """The chain for ``run`` and ``demo``: every input checked first, every output staged
    and moved into ``args.output`` only when the whole chain has finished."""
    from ..fileio import atomic_write_json, staged_output_directory
    from ..render.options import TASK_SHARES
    from ..workflow.chain import chain_inputs, run_chain

    options = render_options(args)
    ocio = ocio_source(args)
    checks_start = time.perf_counter()
    reads, loaded = chain_inputs(captures, mesh, landmarks, args.k)
    checks_s = time.perf_counter() - checks_start
    with TaskBar(TASK_SHARES) as bar, staged_output_directory(
            args.output, verb, reads, args.force, ["report.json", "scene.usda"]) as out:
        result = run_chain(captures, mesh, landmarks, out.path, args.k, prepare, paint,
                           options, ocio, truth=truth,
                           comparisons=verb == "demo", loaded_mesh=loaded,
                           progress=lambda m: bar(m.replace(str(out.path), str(args.output))))
        result.report["stages"] = {"check_inputs": {"seconds": checks_s},
                                   **result.report["stages"]}
        atomic_write_json(out.path / "report.json", result.report)
    result.report = out.final(result.report)
    result.render_doc = out.final(result.render_doc)
    print_chain(result)
    print(f"wrote {args.output / 'report.json'} ({result.report['total_seconds']:.1f} s)")
    return EXIT_OK if result.valid else EXIT_CHECK_FAILED
