"""The ``skinpipe`` command line: a thin layer over the stage functions.

Results go to stdout, diagnostics and progress to stderr. Exit codes: 0 success,
1 a check failed, 2 bad input or usage.

One module per verb (``skinpipe/cli/<verb>.py``: ``add_parser`` and its handler), as
pip's ``cli/`` and ``commands/``; the library never imports this package."""

from __future__ import annotations

import argparse
import errno
import os
import sys
import traceback
import warnings
from collections.abc import Callable, Sequence
from typing import Any

from .. import __version__, interrupts
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
    _one_line_warnings(args.verb)
    previous = interrupts.install()
    try:
        return _handle(handler, args)
    finally:
        interrupts.restore(previous)
        _quiesce()


def console_main() -> int:
    """The ``skinpipe`` command: :func:`main`, then SIGINT ignored while the process
    ends, since the verb is done (whole or not) and a Ctrl-C now would only turn its
    exit code into a signal."""
    code = main()
    interrupts.ignore()
    return code


def _quiesce() -> None:
    """Before the process ends: no native work left running on other threads."""
    programs = sys.modules.get("skinpipe.render.device.programs")
    if programs is not None:
        programs.stop_prewarm()


def _handle(handler: Handler, args: argparse.Namespace) -> int:
    """The verb's exit code; every error it raises as one line on stderr."""
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
    except OSError as exc:  # where the outputs go: read-only, full, unreachable
        _eprint(f"skinpipe {args.verb}: error: {_os_error(exc)}; no partial output was kept")
        return EXIT_BAD_INPUT
    except Exception as exc:  # a bug: one line, the traceback only when asked for
        if os.environ.get("SKINPIPE_DEBUG"):
            traceback.print_exc()
        _eprint(f"skinpipe {args.verb}: internal error: {type(exc).__name__}: "
                f"{str(exc).strip().splitlines()[0] if str(exc).strip() else ''} "
                "(please report it; SKINPIPE_DEBUG=1 shows the traceback)")
        return EXIT_CHECK_FAILED


def _one_line_warnings(verb: str) -> None:
    """Warnings (a cache that cannot be used, a fit's note) as one line on stderr each,
    named by the verb, as the CLI's other diagnostics are."""
    def show(message: Warning | str, category: type[Warning], filename: str, lineno: int,
             file: Any = None, line: str | None = None) -> None:
        _eprint(f"skinpipe {verb}: warning: {message}")

    warnings.showwarning = show


def _os_error(exc: OSError) -> str:
    """``file: reason`` for an OSError, with what to do for the common output faults."""
    where = exc.filename or ""
    reason = exc.strerror or str(exc) or type(exc).__name__
    hint = {errno.ENOSPC: " (the disk is full)", errno.EROFS: " (read-only file system)",
            errno.EACCES: " (no permission)", errno.ENOTDIR: " (a parent is a file)",
            errno.EDQUOT: " (disk quota exceeded)"}.get(exc.errno or 0, "")
    return f"{where}: {reason}{hint}" if where else f"{reason}{hint}"


if __name__ == "__main__":
    sys.exit(main())
