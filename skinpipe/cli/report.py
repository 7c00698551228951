"""``skinpipe report``: each stage's error against its run time."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from ..errors import EXIT_OK, InputError
from ..render.options import BLURS, LIGHT_SEQUENCES, SHADOW_SAMPLING
from .common import HelpFormatter, _eprint, _int_pair, add_force_option


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "report",
        help="error against run time per stage (JSON + PNG, gathered on one report.md page)",
        description=(
            "Measure a stage's error/time trade-off in one run so that users can pick an "
            "operating point. 'fit': k = 1..8 with GA+IPOPT (default), IPOPT from a naive "
            "start, and GA+SLSQP (the paper's SQP), on the given profiles or, without any, "
            "on reference profiles (d'Eon et al. 2007 skin, Jensen et al. 2001 dipoles). "
            "'ingest': simulated captures of the six sample regions, ingested with each of "
            "ingest's options (merge, core model, tail, ring width, brackets) and with each "
            "capture effect turned off in turn (coarse pixels, footprint, black level, "
            "field, camera space, hair), the profile's error against the simulator's "
            "observed truth beside ingest time, and issue 20's must-hold over --seeds seeds "
            "(about 25 s a seed on two cores). "
            "'render SCENE': texture sizes (--sizes) x variance grids (--grids), the "
            "diffused radiance against a brute-force convolution on the surface with the "
            "exact per-region profiles, beside texture-map + irradiance + diffusion time "
            "(--blurs recursive,gather compares the diffusion blurs), and the irradiance's error "
            "against 256 light samples per texel beside its time, per light samples, shadow "
            "sampling (adaptive, interleaved, full) and light sequence (stratified, sobol). "
            "'all SCENE': the three. "
            "Every run also (re)writes OUTPUT/report.md, one page with each stage found in "
            "OUTPUT: plot, table, Pareto front, and whether the default sits on it."
        ),
        formatter_class=HelpFormatter,
    )
    p.add_argument("stage", choices=["fit", "ingest", "render", "all"],
                   help="which stage to measure ('all': fit, ingest and render)")
    p.add_argument("profiles", nargs="*", type=Path, metavar="PROFILE.csv|SCENE",
                   help="fit: profiles to fit (default: built-in reference profiles); "
                        "render and all: the scene (e.g. demo_out/scene.usda)")
    p.add_argument("--sizes", type=_ints(16, 16384, "texture size"),
                   default=[512, 1024, 2048], metavar="N,N",
                   help="render: texture sizes (4096 works: 3 min and 4.6 GiB on two cores "
                        "with --grids 0)")
    p.add_argument("--grids", type=_ints(0, 64, "variance grid"),
                   default=[0, 8, 12], metavar="N,N",
                   help="render: variance grids (0 = each region's own variances)")
    p.add_argument("--blurs", type=_choices(BLURS, "blur"),
                   default=["recursive"], metavar="B,B",
                   help="render: diffusion blurs to compare (recursive, gather)")
    p.add_argument("--light-samples", type=_ints(1, 1024, "light samples"),
                   default=[4, 8, 16, 32], metavar="N,N",
                   help="render: light samples per texel and light, each against 256 "
                        "samples traced by every texel")
    p.add_argument("--shadow-sampling", type=_choices(SHADOW_SAMPLING, "shadow sampling"),
                   default=list(SHADOW_SAMPLING), metavar="M,M",
                   help="render: shadow sampling modes to compare (adaptive, interleaved, "
                        "full)")
    p.add_argument("--light-sequences", type=_choices(LIGHT_SEQUENCES, "light sequence"),
                   default=list(LIGHT_SEQUENCES), metavar="S,S",
                   help="render: light sample sequences to compare (stratified, sobol)")
    p.add_argument("--lighting-size", type=lambda t: _ints(16, 16384, "texture size")(t)[0],
                   default=1024, metavar="N",
                   help="render: texture size of the light-sample comparison")
    p.add_argument("--k", type=_int_range, default=(1, 8), metavar="A:B",
                   help="range of k to try, inclusive")
    p.add_argument("--seeds", type=int, default=30,
                   help="ingest: seeds of the must-hold cases (the others use up to 5)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output directory")
    add_force_option(p)
    p.set_defaults(handler=cmd_report)


def _ints(lo: int, hi: int, what: str) -> Callable[[str], list[int]]:
    """An argparse type: comma-separated integers in [lo, hi], refused before any
    measuring starts."""
    def parse(text: str) -> list[int]:
        try:
            values = [int(v) for v in text.split(",")]
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what}: integers, comma-separated; got "
                                             f"{text!r}") from None
        bad = [v for v in values if not lo <= v <= hi]
        if bad:
            raise argparse.ArgumentTypeError(f"{what} must be {lo}-{hi}, got {bad}")
        return values
    return parse


def _choices(allowed: tuple[str, ...], what: str) -> Callable[[str], list[str]]:
    """An argparse type: a comma-separated list of ``allowed`` values."""
    def parse(text: str) -> list[str]:
        values = [v.strip() for v in text.split(",")]
        bad = [v for v in values if v not in allowed]
        if bad:
            raise argparse.ArgumentTypeError(f"unknown {what} {bad}; choose from "
                                             f"{', '.join(allowed)}")
        return values
    return parse


def _int_range(text: str) -> tuple[int, int]:
    lo, hi = _int_pair(text)
    if not 1 <= lo <= hi <= 8:
        raise argparse.ArgumentTypeError(f"need 1 <= A <= B <= 8, got {text!r}")
    return lo, hi


def _report_render(args: argparse.Namespace, scene: Path) -> None:
    from ..workflow.report import (
        lighting_tradeoff,
        render_tradeoff,
        write_lighting_report,
        write_render_report,
    )

    rows = render_tradeoff(scene, args.sizes, args.grids, progress=_eprint, blurs=args.blurs)
    lighting = write_lighting_report(lighting_tradeoff(
        scene, args.lighting_size, args.light_samples, args.shadow_sampling,
        progress=_eprint, sequences=args.light_sequences), args.output)
    print(f"{'samples':>7} {'shadow sampling':>15} {'sequence':>10} {'rays/texel':>10} "
          f"{'seconds':>8} {'error':>9}  pareto")
    for r in lighting["rows"]:
        print(f"{r['light_samples']:>7} {r['shadow_sampling']:>15} {r['light_sequence']:>10} "
              f"{r['rays_per_texel']:>10.1f} {r['seconds']:>8.2f} {r['error_max']:>9.2e}  "
              f"{'*' if r['pareto'] else ''}")
    doc = write_render_report(rows, args.output)
    print(f"{'texture':>7} {'grid':>4} {'blur':>9} {'mm/texel':>8} {'passes':>6} {'seconds':>8} "
          f"{'diffuse s':>9} {'error':>9}  pareto")
    for r in doc["rows"]:
        print(f"{r['texture_size']:>7} {r['variance_grid']:>4} {r['blur']:>9} "
              f"{r['mm_per_texel']:>8.3f} {r['blur_passes']:>6} {r['seconds']:>8.2f} "
              f"{r['diffusion_seconds']:>9.2f} {r['error_max']:>9.2e}  "
              f"{'*' if r['pareto'] else ''}")


def _report_ingest(args: argparse.Namespace) -> None:
    from ..workflow.report import ingest_tradeoff, write_ingest_report

    if not 1 <= args.seeds <= 1000:
        raise InputError(f"--seeds must be 1-1000, got {args.seeds}")
    rows = ingest_tradeoff(args.seeds, progress=_eprint)
    doc = write_ingest_report(rows, args.output)
    print(f"{'group':<9} {'case':<28} {'seeds':>5} {'seconds':>7} {'error max':>9} "
          f"{'flux max':>8} {'refused':>7}")
    for r in rows:
        err = "-" if r["error_max"] is None else f"{r['error_max']:.2%}"
        flux = "-" if r["flux_error_max"] is None else f"{r['flux_error_max']:.2%}"
        print(f"{r['group']:<9} {r['case']:<28} {r['seeds']:>5} {r['seconds']:>7.2f} "
              f"{err:>9} {flux:>8} {r['refused']:>3}/{r['regions']:<3}")
    for name, check in doc["must_hold"].items():
        value = f"{check['value']}/{check['of']}" if "of" in check else \
            f"{check['value']:.2%} (limit {check['limit']:.2%})"
        print(f"must hold: {name}: {value}, {'holds' if check['holds'] else 'DOES NOT HOLD'}")


def _report_fit(args: argparse.Namespace, profile_paths: list[Path]) -> None:
    from ..profile.io import read_profile_csv
    from ..workflow.report import fit_tradeoff, write_fit_report

    profiles = ([read_profile_csv(p) for p in profile_paths] if profile_paths
                else _reference_profiles())
    rows = fit_tradeoff(profiles, ks=range(args.k[0], args.k[1] + 1), progress=_eprint)
    doc = write_fit_report(rows, args.output)
    print(f"{'profile':<16} {'method':<12} {'k':>2} {'seconds':>8} {'error':>9}  pareto")
    for row in doc["rows"]:
        print(f"{row['profile']:<16} {row['method']:<12} {row['k']:>2} {row['seconds']:>8.3f} "
              f"{row['error_max']:>9.2e}  {'*' if row['pareto'] else ''}")


def cmd_report(args: argparse.Namespace) -> int:
    from ..fileio import check_output_file, record_outputs
    from ..usd.io import usd_inputs
    from ..workflow.report import write_report_page

    if args.output.exists() and not args.output.is_dir():
        raise InputError("is a file: give a folder for the report", args.output)
    scenes = [p for p in args.profiles if p.suffix in (".usd", ".usda", ".usdc", ".usdz")]
    reads = [p for p in args.profiles if p not in scenes]
    if args.stage in ("render", "all"):
        if len(scenes) != 1:
            raise InputError(f"report {args.stage} needs exactly one SCENE (.usd/.usda/.usdc)")
        scene = scenes[0]
        if not scene.is_file():
            raise InputError("scene not found", scene)
        reads += usd_inputs(scene)
    stages = ("fit", "ingest", "render") if args.stage == "all" else (args.stage,)
    # render also writes the irradiance's trade-off, lighting_tradeoff.json|png
    names = list(stages) + (["lighting"] if "render" in stages else [])
    written = [f"{s}_tradeoff.{ext}" for s in names for ext in ("json", "png")] + \
        ["report.md"]
    for name in written:  # before minutes of measuring, not after
        check_output_file(args.output / name, reads, args.force)
    if args.stage in ("fit", "all"):
        _report_fit(args, [p for p in args.profiles if p not in scenes])
    if args.stage in ("ingest", "all"):
        _report_ingest(args)
    if args.stage in ("render", "all"):
        _report_render(args, scene)
    page = write_report_page(args.output)
    record_outputs(args.output, written, "report")
    print(f"wrote {args.stage} trade-off JSON and PNG into {args.output}; page: {page}")
    return EXIT_OK


def _reference_profiles() -> list:
    import numpy as np

    from ..profile.models import dipole_profile, dipole_total_reflectance, sum_of_gaussians
    from ..profile.reference_data import DEON_2007_SKIN, JENSEN_2001
    from ..profile.types import MeasuredProfile

    r = np.linspace(0.0, 4.0, 200)
    out = [MeasuredProfile(r, sum_of_gaussians(DEON_2007_SKIN.variances_mm2,
                                               DEON_2007_SKIN.weights, r), name="deon2007")]
    for name in ("skin1", "skin2"):
        c = JENSEN_2001[name]
        out.append(MeasuredProfile(r, dipole_profile(r, c) / dipole_total_reflectance(c),
                                   name=f"dipole_{name}"))
    return out
