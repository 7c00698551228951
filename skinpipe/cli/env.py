"""``skinpipe env``: the plugin path line and the OpenCL device."""

from __future__ import annotations

import argparse

from ..errors import EXIT_OK
from .common import _eprint, add_device_option


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "env",
        help="print the PXR_PLUGINPATH_NAME line and the OpenCL device skinpipe uses",
        description="Print the shell line that makes usdview or a DCC see skinpipe's USD "
                    "schema and usdview plugin (add it to your shell profile or launcher), "
                    "then every OpenCL device found, probed with a kernel that uses what "
                    "skinpipe's kernels use: the one chosen, and why each other one was "
                    "not (one line each, on stderr as comments).",
    )
    add_device_option(p)
    p.set_defaults(handler=cmd_env)


def cmd_env(args: argparse.Namespace) -> int:
    from ..render.device.choice import choose_device, device_spec
    from ..render.device.runtimes import SETUP
    from ..usd.schema import pxr_plugin_path_line

    print(pxr_plugin_path_line())
    choice = choose_device(args.device or device_spec(), probe_all=True)
    _eprint(f"# OpenCL device ('{choice.spec}'): {choice.candidate.label} "
            f"[{choice.candidate.runtime}]"
            + ("" if choice.nontemporal_stores else " (without streaming stores)"))
    for cand, reason in choice.tried:
        if cand != choice.candidate:
            _eprint(f"#   not used: {cand.label} [{cand.runtime}]: {reason}")
    for note in SETUP.notes:
        _eprint(f"#   note: {note}")
    return EXIT_OK
