"""``skinpipe fit``: sum-of-Gaussians fits of measured radial profiles."""

from __future__ import annotations

import argparse
import contextlib
import warnings
from pathlib import Path
from typing import Any

from ..errors import EXIT_OK, InputError
from .common import HelpFormatter, _eprint, add_force_option


def _float_list(text: str) -> tuple[float, ...]:
    if text.strip().lower() == "deon":
        from ..profile.reference_data import DEON_2007_SKIN

        return tuple(float(v) for v in DEON_2007_SKIN.variances_mm2)
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from exc


def _weight(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not (value >= 0 and value < float("inf")):  # NaN too
        raise argparse.ArgumentTypeError(f"a finite number >= 0, got {text!r}")
    return value


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "fit",
        help="fit a sum of Gaussians to measured radial profiles (CSV -> FIT.json)",
        description=(
            "Fit f(r) = sum_i w_i G(v_i, r) per colour channel, G the normalised 2D Gaussian "
            "(variance v in mm^2, radius r in mm), weights >= 0 summing to 1 per channel "
            "(Park & Oh 2009, eq. 1-2), by the profile's values (eq. 2a) and its radial "
            "energy (the light within each radius: what shadow edges show, an entry spike "
            "included). A genetic algorithm seeds the variances, casadi's IPOPT refines "
            "variances and weights. Reported per channel: eq. 2c (relative, r-weighted RMS "
            "of the values) and, against the measured profile, a hard shadow edge's "
            "spread error (share of the plateau), its 10-90%% width and the light in the "
            "shadow (docs/fit.md)."
        ),
        formatter_class=HelpFormatter,
    )
    p.add_argument("profiles", nargs="+", type=Path, metavar="PROFILE.csv",
                   help="header and columns radius_mm,R,G,B[,std_R,std_G,std_B]")
    p.add_argument("-k", type=int, default=6, help="Gaussians per variance grid (1-8)")
    p.add_argument("--share", choices=["channels", "none", "profiles"], default="channels",
                   help="curves sharing one variance grid: the 3 channels of a profile, none "
                        "(per channel), or all channels of all PROFILEs (one grid for a face: "
                        "fewer blur passes when rendering)")
    p.add_argument("--fixed-variances", type=_float_list, metavar="V1,V2,...",
                   help="fix the variance grid (mm^2), solve weights only; 'deon' for d'Eon "
                        "et al. 2007's skin grid")
    p.add_argument("--min-radius-mm", type=float, default=0.0,
                   help="leave out samples closer to the entry point (the paper drops them)")
    p.add_argument("--max-radius-mm", type=float, default=None,
                   help="leave out samples farther than this")
    p.add_argument("--free-scale", action="store_true",
                   help="also fit the total diffuse reflectance per channel (absolute captures)")
    p.add_argument("--use-stddev", action="store_true",
                   help="weight samples by 1/std^2 (from std_R,std_G,std_B) besides r dr")
    p.add_argument("--energy-weight", type=_weight, default=None, metavar="W",
                   help="weight of the radial energy term against the values' (both "
                        "normalised to the data; default 10; 0: the paper's eq. 2a alone)")
    p.add_argument("--solver", choices=["ipopt", "slsqp"], default="ipopt",
                   help="local refinement after the seed (slsqp = the paper's SQP, for comparison)")
    p.add_argument("--init", choices=["ga", "naive", "random"], default="ga",
                   help="starting point: genetic algorithm, log-spaced grid, or random grid")
    # None: FitOptions' defaults (20, 32), read when the verb runs (importing the fit
    # module here would load casadi for every verb's --help)
    p.add_argument("--generations", type=int, default=None,
                   help="GA generations (the seed; IPOPT and one-term hops refine it; "
                        "default 20)")
    p.add_argument("--population", type=int, default=None,
                   help="GA population size (default 32)")
    p.add_argument("--seed", type=int, default=0, help="random seed (GA); same seed, same fit")
    p.add_argument("-o", "--output", type=Path, required=True,
                   help="FIT.json for one profile; a directory (one <name>.json each) for several")
    add_force_option(p)
    p.set_defaults(handler=cmd_fit)


def cmd_fit(args: argparse.Namespace) -> int:
    from ..fileio import (
        check_output_file,
        check_path_name,
        record_outputs,
        staged_output_directory,
    )
    from ..profile.fit import FitOptions
    from ..profile.io import read_profile_csv

    fixed = args.fixed_variances or None
    ga = {name: value for name in ("generations", "population", "energy_weight")
          if (value := getattr(args, name)) is not None}
    options = FitOptions(
        k=args.k, share=args.share, fixed_variances_mm2=fixed, min_radius_mm=args.min_radius_mm,
        max_radius_mm=args.max_radius_mm, seed=args.seed, solver=args.solver, init=args.init,
        free_scale=args.free_scale, use_stddev=args.use_stddev, **ga,
    )
    profiles = [read_profile_csv(p) for p in args.profiles]
    for path, prof in zip(args.profiles, profiles, strict=True):
        _eprint(f"read {path}: {prof.radius_mm.size} samples to {prof.radius_mm.max():.3g} mm")
    reads = list(args.profiles)
    names = [p.name for p in profiles]
    if len(set(names)) != len(names):
        raise InputError(f"profile names (file stems) must be unique: {names}")
    several = len(profiles) > 1
    for name in names:
        check_path_name(name, "profile name", args.output)
    if several and args.output.suffix.lower() == ".json":
        raise InputError("several profiles write one JSON each: give -o a directory", args.output)
    if several:
        staged = staged_output_directory(args.output, "fit", reads, args.force,
                                         [f"{p.name}.json" for p in profiles])
    else:
        check_output_file(args.output, reads, args.force)
        staged = contextlib.nullcontext(None)
    with staged as out:
        _fit_groups(args, options, profiles, several, None if out is None else out.path)
    if not several:
        record_outputs(args.output.parent, [args.output.name], "fit")
    return EXIT_OK


def _fit_groups(args: argparse.Namespace, options: Any, profiles: list[Any], several: bool,
                out_dir: Path | None) -> None:
    from ..profile.fit import fit_profiles
    from ..profile.io import write_fit_json

    if args.share == "profiles" or not several:
        groups = [profiles]
    else:
        groups = [[p] for p in profiles]
    for i, group in enumerate(groups, start=1):
        if several:
            _eprint(f"[{i}/{len(groups)}] fitting {', '.join(p.name for p in group)}")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            results = fit_profiles(group, options)
        for w in caught:
            _eprint(f"warning: {w.message}")
        for res in results:
            target = args.output / f"{res.name}.json" if several else args.output
            write_fit_json(out_dir / f"{res.name}.json" if out_dir else target, res)
            errs = " ".join(f"{c}={e:.2e}" for c, e in zip("RGB", res.error, strict=True))
            print(f"{res.name}: {len(res.variances_mm2)} terms, eq.2c error {errs}, "
                  f"{res.seconds:.2f} s, {res.status} -> {target}")
            if res.edge is not None:
                e = res.edge
                print("  shadow edge: spread error " + " ".join(
                    f"{c}={x:.2%}" for c, x in zip("RGB", e["edge_error"], strict=True))
                    + "; 10-90% width " + " ".join(
                    f"{c}={f:.3g}/{m:.3g}" for c, f, m in zip(
                        "RGB", e["edge_width_mm"], e["edge_width_measured_mm"], strict=True))
                    + " mm (fit/measured); light in the shadow " + " ".join(
                    f"{c}={x:.3f}" for c, x in zip("RGB", e["shadow_light_ratio"], strict=True))
                    + "x measured")
            for note in res.warnings:
                _eprint(f"note: {res.name}: {note}")
