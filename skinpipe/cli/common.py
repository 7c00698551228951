"""Helpers shared by the verbs: stderr output, render options, argument types."""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from typing import Any

Handler = Callable[[argparse.Namespace], int]


def typed_default(default: list[Any] | tuple[Any, ...], metavar: object) -> str:
    """A list or tuple default as a user would type it: joined by ':' where the option's
    metavar has one (``A:B``), else by ',' (``N,N``), not as Python's repr."""
    sep = ":" if isinstance(metavar, str) and ":" in metavar else ","
    return sep.join(str(v) for v in default)


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """argparse's defaults in ``--help``, but only where the help does not state its own
    default already (argparse's would follow it with a second, often ``None``, one) and
    where there is one to show (not None, False, empty or suppressed); a list or tuple
    is shown as the option takes it (:func:`typed_default`)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        default = action.default
        nothing = default is None or default is False or default == argparse.SUPPRESS or \
            (isinstance(default, (str, tuple, list)) and not default)  # 0 is shown
        if nothing or "default" in text.lower():
            return action.help
        if isinstance(default, (list, tuple)):
            shown = typed_default(default, action.metavar).replace("%", "%%")
            return f"{text} (default: {shown})"
        return super()._get_help_string(action)


def _eprint(*args: object) -> None:
    # one write, line and newline together: a Ctrl-C between print's two writes left
    # the "interrupted" line glued to the last progress line
    sys.stderr.write(" ".join(str(a) for a in args) + "\n")
    sys.stderr.flush()


class TaskBar:
    """Progress of a render on stderr: ``[#####.....] 42% diffusion, 6.1 s, about 8 s
    left``. Messages naming a task of ``shares`` (each task's rough share of the work)
    move the bar; others are printed as they are. On a terminal the bar redraws one
    line; elsewhere (a farm log) each task is one line."""

    def __init__(self, shares: dict[str, float], frames: int = 1, width: int = 24) -> None:
        self.shares, self.frames, self.width = shares, max(frames, 1), width
        self.done = 0.0
        self.current: str | None = None
        self.start = 0.0  # the first task's start: a chain's earlier stages are not counted
        self.tty = sys.stderr.isatty()

    def __call__(self, message: str) -> None:
        task = message.split(" ", 1)[0]
        if task not in self.shares:
            self._line(message)
            return
        if self.current is not None:
            self.done += self.shares[self.current] / self.frames
        else:
            self.start = time.perf_counter()
        self.current = task
        share = min(self.done / sum(self.shares.values()), 0.99)
        elapsed = time.perf_counter() - self.start
        left = f", about {elapsed / share * (1 - share):.0f} s left" if share > 0.05 else ""
        fill = int(self.width * share)
        bar = f"[{'#' * fill}{'.' * (self.width - fill)}] {share:4.0%} {message}, " \
              f"{elapsed:.1f} s{left}"
        if self.tty:
            print(f"\r\033[K{bar}", end="", file=sys.stderr, flush=True)
        else:
            _eprint(bar)

    def _line(self, message: str) -> None:
        if self.tty:
            print("\r\033[K", end="", file=sys.stderr)
        _eprint(message)

    def __enter__(self) -> TaskBar:
        return self

    def __exit__(self, exc_type: object, *_: object) -> None:
        self.close(finished=exc_type is None)

    def close(self, finished: bool = True) -> None:
        """Clear the bar on a terminal; in a log, end a finished one with its total."""
        if self.tty:
            print("\r\033[K", end="", file=sys.stderr, flush=True)
        elif finished and self.current is not None:
            _eprint(f"[{'#' * self.width}] 100% done, {time.perf_counter() - self.start:.1f} s")


def _resolution(text: str) -> tuple[int, int]:
    try:
        w, _, h = text.lower().partition("x")
        return int(w), int(h or w)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected WxH, got {text!r}") from exc


def _int_pair(text: str) -> tuple[int, int]:
    """``A:B`` (or ``A`` for ``A:A``) as two ints; an argparse error otherwise."""
    try:
        a, _, b = text.partition(":")
        return int(a), int(b or a)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected A:B, got {text!r}") from exc


def _frames(text: str) -> tuple[int, int]:
    lo, hi = _int_pair(text)
    if lo > hi or hi - lo > 10000:
        raise argparse.ArgumentTypeError(f"need A <= B (at most 10000 frames), got {text!r}")
    return lo, hi


def _aovs(text: str) -> tuple[str, ...]:
    return tuple(a.strip() for a in text.split(",") if a.strip())


def add_force_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--force", action="store_true",
                   help="write over existing files skinpipe did not write, and over this "
                        "command's own inputs (a re-run into skinpipe's own output "
                        "folder never needs it)")


def add_render_options(p: argparse.ArgumentParser, resolution: str = "1024x1024",
                       texture_size: int = 1024) -> None:
    from ..render.options import (
        AOVS,
        BLURS,
        DATA_AOVS,
        INTERLEAVE_PERIODS,
        LAYOUT_CACHE_HELP,
        LIGHT_SEQUENCES,
        SHADOW_SAMPLING,
        TEXTURE_OUTPUTS,
    )

    p.add_argument("--camera", default=None, metavar="PRIM",
                   help="UsdGeomCamera prim path (default: the first camera on the stage)")
    p.add_argument("--resolution", type=_resolution, default=_resolution(resolution),
                   metavar="WxH", help=f"image size in pixels (default {resolution})")
    p.add_argument("--texture-size", type=int, default=texture_size, metavar="N",
                   help="texture-space maps are N x N texels")
    p.add_argument("--aovs", type=_aovs, default=AOVS, metavar="A,B",
                   help=f"AOVs to write, from {','.join(AOVS + DATA_AOVS)} (default: "
                        f"{','.join(AOVS)}; region: the face region index per pixel)")
    p.add_argument("--texture-outputs", type=_aovs, default=(), metavar="A,B",
                   help=f"texture-space maps to write to <name>_uv.exr, from "
                        f"{','.join(TEXTURE_OUTPUTS)} (irradiance and diffused radiosity "
                        "in RGB, stretch in mm per texel, region index; row 0 is v = 1)")
    p.add_argument("--light-samples", type=int, default=16,
                   help="light samples per texel and light (area and dome lights; "
                        "see --shadow-sampling for how many are traced)")
    p.add_argument("--shadow-sampling", choices=SHADOW_SAMPLING, default="interleaved",
                   help="interleaved: each texel of a PxP block traces 1/P^2 of the light "
                        "samples and borrows the rest from its neighbours (Keller & "
                        "Heidrich 2001; see --interleave-period); adaptive: the same, then "
                        "the texels whose neighbourhood's rays disagree (penumbrae) trace "
                        "the rest themselves; full: every texel traces all of them "
                        "(default interleaved)")
    p.add_argument("--interleave-period", default="auto", metavar="auto|P",
                   type=_period(INTERLEAVE_PERIODS),
                   help=f"P of interleaved and adaptive sampling, one of "
                        f"{', '.join(map(str, INTERLEAVE_PERIODS))} (at most what "
                        "--light-samples fills: a sample for each of the P^2 classes); "
                        "auto (default): 2, or larger where a pixel holds P x P texels "
                        "or more at the skin (rays go per pixel, not per texel, at least "
                        "the light's samples a pixel; the demo face at texture 4096 "
                        "takes 4, a quarter of the rays); "
                        "render.json says which")
    p.add_argument("--light-sequence", choices=LIGHT_SEQUENCES, default="sobol",
                   help="light sample points: sobol (scrambled Sobol; --light-samples "
                        "rounded up to a power of two; on the demo face 12%% less error "
                        "than the grid at 16 samples) or stratified (a jittered grid)")
    p.add_argument("--variance-grid", type=int, default=12, metavar="N",
                   help="re-express all regions' profiles on N shared variances (fewer "
                        "blurs; the error is in render.json); 0 = each region's own")
    p.add_argument("--blur", choices=BLURS, default="recursive",
                   help="diffusion blur: recursive Gaussian on a pyramid (cost independent "
                        "of width) or the per-tap gather kernel (cost grows with width)")
    p.add_argument("--no-scattering", action="store_true",
                   help="texture-mapped irradiance only (no subsurface diffusion)")
    p.add_argument("--single-profile", default=None, metavar="mean|REGION",
                   help="one profile for the whole face instead of one per region")
    p.add_argument("--albedo-split", type=float, default=0.5,
                   help="albedo exponent applied before scattering (0.5 = sqrt before/after)")
    p.add_argument("--roughness", type=float, default=0.35, help="Beckmann roughness")
    p.add_argument("--rho-s", type=float, default=0.25, help="specular scale rho_s")
    p.add_argument("--ior", type=float, default=1.4,
                   help="the skin's refractive index: light entering and leaving at an "
                        "angle loses a smooth dielectric's Fresnel share, relative to "
                        "normal incidence (where the profile was measured); 1 = "
                        "index-matched, where the light leaving follows each region's "
                        "medium by angle (its single scattering too)")
    p.add_argument("--no-transmission", action="store_true",
                   help="leave out light through the volume: by default light entering "
                        "at an angle scatters first where its refracted path takes it "
                        "(across a terminator, into a shadow), and what thin parts' far "
                        "side receives (ears, nostrils' rims) leaves the near side, by "
                        "each region's medium")
    p.add_argument("--no-write-uvs", action="store_true",
                   help="do not write xatlas UVs back into the asset's geo layer")
    p.add_argument("--ocio", default=None,
                   help="OCIO config for the display PNG (default: $OCIO, else "
                        "ocio://default)")
    p.add_argument("--half-float", action="store_true",
                   help="write the EXR's AOVs as half float (16 bit; the usual beauty "
                        "format) instead of 32-bit float")
    p.add_argument("--layout-cache", default=None, metavar="DIR|off", help=LAYOUT_CACHE_HELP)
    add_device_option(p)


def add_device_option(p: argparse.ArgumentParser) -> None:
    from ..render.options import DEVICE_HELP

    p.add_argument("--device", default=None, metavar="SPEC", help=DEVICE_HELP)


def render_options(args: argparse.Namespace) -> Any:
    """The render options asked for, refused before any work if invalid or too large for
    this machine's memory."""
    from ..render.budget import check_render_fits
    from ..render.options import RenderOptions

    options = RenderOptions(
        resolution=args.resolution, texture_size=args.texture_size, aovs=args.aovs,
        light_samples=args.light_samples, shadow_sampling=args.shadow_sampling,
        interleave_period=args.interleave_period, light_sequence=args.light_sequence,
        roughness=args.roughness, rho_s=args.rho_s, ior=args.ior,
        transmission=not args.no_transmission,
        albedo_split=args.albedo_split, variance_grid=args.variance_grid,
        scattering=not args.no_scattering, blur=args.blur, single_profile=args.single_profile,
        camera=args.camera, write_uvs=not args.no_write_uvs, device=args.device,
        texture_outputs=args.texture_outputs,
        half_float=args.half_float, layout_cache=_layout_cache(args.layout_cache))
    check_render_fits(options.texture_size, options.resolution)
    return options


def _period(periods: tuple[int, ...]) -> Any:
    """--interleave-period's parser: 'auto' as 0, else one of ``periods``."""
    def parse(text: str) -> int:
        if text.strip().lower() == "auto":
            return 0
        try:
            value = int(text)
        except ValueError:
            value = -1
        if value not in periods:
            raise argparse.ArgumentTypeError(
                f"expected auto or one of {', '.join(map(str, periods))}, got {text!r}")
        return value

    return parse


def _layout_cache(value: str | None) -> str | None:
    """--layout-cache as the folder it names (None: off); the cache folders' size limits
    from the environment are checked here too, before the command renders."""
    from ..render import cache
    from ..render.diffusion.tile_store import layout_folder

    cache.limit_bytes()
    folder = layout_folder(value)
    return None if folder is None else str(folder)


def ocio_source(args: argparse.Namespace) -> str:
    """The OCIO config asked for (``--ocio``, ``$OCIO``, else OCIO's default), loaded
    once here so that a bad one is refused before any work."""
    from ..imageio import ocio_config

    source = args.ocio or os.environ.get("OCIO") or "ocio://default"
    ocio_config(source)
    return source
