"""The ``skinpipe`` command line: a thin layer over the stage functions.

Results go to stdout, diagnostics and progress to stderr. Exit codes: 0 success,
1 a check failed, 2 bad input or usage.

One module per verb (``pipeline/cli/<verb>.py``: ``add_parser`` and its handler), as
pip's ``cli/`` and ``commands/``; the library never imports this package."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from .. import __version__
from ..errors import EXIT_BAD_INPUT, EXIT_CHECK_FAILED, InputError, SkinpipeError
from . import (
    author,
    batch,
    demo,
    env,
    fit,
    ingest,
    inspect,
    paint_albedo,
    render,
    report,
    run,
    shot,
    simulate,
    validate,
)
from .common import Handler, _eprint


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="skinpipe",
        description=(
            "Measured skin scattering to production assets: ingest bracketed captures of a "
            "lit skin point, fit sum-of-Gaussians diffusion profiles, author USD assets, "
            "render faces with texture-space diffusion. "
            "Radii in mm, variances in mm^2. Run 'skinpipe VERB --help' for each verb."
        ),
        epilog="Exit codes: 0 success, 1 a check failed, 2 bad input or usage.",
    )
    parser.add_argument("--version", action="version", version=f"skinpipe {__version__}")
    sub = parser.add_subparsers(dest="verb", metavar="VERB", required=True)
    for add in _VERBS:
        add(sub)
    return parser


_VERBS: list[Callable[[argparse._SubParsersAction], None]] = [
    demo.add_parser,
    ingest.add_parser,
    fit.add_parser,
    author.add_parser,
    validate.add_parser,
    inspect.add_parser,
    paint_albedo.add_parser,
    shot.add_parser,
    render.add_parser,
    run.add_parser,
    batch.add_parser,
    report.add_parser,
    simulate.add_parser,
    env.add_parser,
]


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: 0 for --help, 2 for usage errors
        return int(exc.code or 0)
    handler: Handler = args.handler
    try:
        return handler(args)
    except InputError as exc:
        _eprint(f"skinpipe {args.verb}: error: {exc}")
        return EXIT_BAD_INPUT
    except SkinpipeError as exc:
        _eprint(f"skinpipe {args.verb}: failed: {exc}")
        return EXIT_CHECK_FAILED
    except KeyboardInterrupt:
        _eprint(f"skinpipe {args.verb}: interrupted; no partial output was kept")
        return 130


if __name__ == "__main__":
    sys.exit(main())
