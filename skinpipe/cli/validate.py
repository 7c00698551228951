"""``skinpipe validate``: USD's validators and skinpipe's rules, for CI."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..errors import EXIT_BAD_INPUT, EXIT_CHECK_FAILED, EXIT_OK, InputError
from .common import HelpFormatter, _eprint, add_force_option


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "validate",
        help="check USD assets with USD's validators and skinpipe's rules (for CI)",
        description=(
            "Run OpenUSD's built-in validators (pxr.UsdValidation) and skinpipe's named "
            "rules (registered with the same registry; 'skinpipe validate --list-rules' "
            "documents them) on each file. Prints problems with their sites, then "
            "'Success!' or 'Failed!' like usdchecker. Exit 0 when every file passes, 1 when "
            "a check fails, 2 when a file cannot be read. Text files nested too deep for "
            "USD's parser are refused before parsing."
        ),
        formatter_class=HelpFormatter,
    )
    p.add_argument("assets", nargs="*", type=Path, metavar="ASSET.usd")
    p.add_argument("--strict", action="store_true",
                   help="warnings fail too, and findings this USD build cannot check "
                        "(reported as not-applicable, with the reason)")
    p.add_argument("--json", action="store_true", help="print a JSON report instead")
    p.add_argument("--junit", type=Path, default=None, metavar="FILE",
                   help="also write a JUnit XML report")
    p.add_argument("--skinpipe-only", action="store_true",
                   help="run only skinpipe's rules, not USD's built-in validators")
    p.add_argument("--list-rules", action="store_true", help="list skinpipe's rules and exit")
    add_force_option(p)
    p.set_defaults(handler=cmd_validate)


def _inputs(assets: list[Path]) -> list[Path]:
    """The files validating ``assets`` reads (the files alone where USD cannot read them:
    the report says why)."""
    from ..usd.io import usd_inputs

    reads: list[Path] = []
    for asset in assets:
        try:
            reads += usd_inputs(asset)
        except InputError:
            reads.append(asset)
    return reads


def cmd_validate(args: argparse.Namespace) -> int:
    from ..fileio import atomic_write_text, check_output_file, record_outputs
    from ..usd.schema import plugin_path_note
    from ..usd.validate import RULES, junit_xml, validate_files

    if args.list_rules:
        for r in RULES:
            print(f"{r.name}\n    {r.doc}")
        return EXIT_OK
    if not args.assets:
        raise InputError("no ASSET.usd given")
    if args.junit:
        check_output_file(args.junit, _inputs(args.assets), args.force)
    reports = validate_files(args.assets, include_builtin=not args.skinpipe_only)
    note = plugin_path_note()
    if note:
        _eprint(note)
    if args.junit:
        atomic_write_text(args.junit, junit_xml(reports, args.strict))
        record_outputs(args.junit.parent, [args.junit.name], "validate")
    unreadable = any(r.unreadable is not None for r in reports)
    failed = any(r.failed(args.strict) for r in reports)
    if args.json:
        print(json.dumps([{"file": r.path, "unreadable": r.unreadable,
                           "seconds": round(r.seconds, 4),
                           "result": "Failed" if r.failed(args.strict) else "Success",
                           "problems": [p.__dict__ | {"sites": list(p.sites)}
                                        for p in r.problems]} for r in reports], indent=2))
    else:
        for r in reports:
            if r.unreadable is not None:
                _eprint(f"{r.path}: cannot read: {r.unreadable}")
            for prob in r.problems:
                print(f"{r.path}: [{prob.rule}] {prob.severity}: {prob.message} "
                      f"({', '.join(prob.sites)})")
        print("Failed!" if failed else "Success!")
    if unreadable:
        return EXIT_BAD_INPUT
    return EXIT_CHECK_FAILED if failed else EXIT_OK
