"""``skinpipe batch``: many subjects through the stages on Dask distributed."""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
from pathlib import Path
from typing import Any

from ..errors import EXIT_CHECK_FAILED, EXIT_OK, InputError
from ..render.options import DEVICE_ENV, DEVICE_HELP
from .common import HelpFormatter, _eprint, add_force_option


def _stages(text: str) -> tuple[str, ...]:
    from ..workflow.batch import STAGES

    stages = tuple(s.strip() for s in text.split(",") if s.strip())
    bad = [s for s in stages if s not in STAGES]
    if bad or not stages:
        raise argparse.ArgumentTypeError(f"stages from {','.join(STAGES)}, got {text!r}")
    return stages


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "batch",
        help="run many subjects through ingest/fit/author/render on Dask distributed",
        description=(
            "Run every subject of BATCH.json (docs/batch.md) as a Dask distributed graph: "
            "one task per subject and stage, one per region for the fits. Each task is "
            "keyed by a hash of its inputs and options and writes OUT_ROOT/<subject>/"
            "<stage>/ atomically with a done.json: re-running a finished batch does no "
            "work, changing one subject's capture re-runs only that subject. A failing "
            "subject is reported and the others go on. Writes OUT_ROOT/batch.json."
        ),
        epilog="Exit codes: 0 every subject done, 1 a subject failed, 2 bad input.",
        formatter_class=HelpFormatter,
    )
    p.add_argument("batch", type=Path, metavar="BATCH.json", help="the subjects to run")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--scheduler", metavar="tcp://HOST:8786",
                       help="address of a running Dask scheduler (your cluster)")
    where.add_argument("--local-workers", type=int, default=2, metavar="N",
                       help="without --scheduler: worker processes of a LocalCluster here")
    p.add_argument("--stages", type=_stages, default=("ingest", "fit", "author", "render"),
                   metavar="A,B", help="stages to run; those before the last one run too "
                                       "(no work when their outputs are current)")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="OUT_ROOT",
                   help="output root, one directory per subject")
    p.add_argument("--dashboard", nargs="?", const="127.0.0.1:8787", default=None,
                   metavar="HOST:PORT",
                   help="serve the local cluster's Dask dashboard there (127.0.0.1:8787 "
                        "when given alone; port 0 picks a free one) and print its address; "
                        "needs bokeh: pip install 'skinpipe[dashboard]'. A cluster of your "
                        "own serves its dashboard from its scheduler")
    p.add_argument("--device", default=None, metavar="SPEC",
                   help=f"OpenCL device of the local workers ({DEVICE_HELP}); workers of "
                        f"your own cluster read ${DEVICE_ENV} from their environment")
    add_force_option(p)
    p.set_defaults(handler=cmd_batch)


def _bar(done: int, total: int, res: dict[str, Any]) -> None:
    width = 30
    fill = int(width * done / max(total, 1))
    unit = res["unit"] if res["stage"] == "fit" else ""
    line = (f"[{'#' * fill}{'.' * (width - fill)}] {done}/{total} {res['subject']} "
            f"{res['stage']} {unit} {res['status']} {res['seconds']:.1f}s")
    _eprint(line)
    if res["status"] == "failed":
        _eprint(f"  error: {res.get('error', '').splitlines()[0]}")


def local_cluster(workers: int, dashboard: str | None) -> Any:
    """A LocalCluster of ``workers`` processes (one thread each), with its dashboard at
    ``dashboard`` (HOST:PORT) or none; InputError when the dashboard's bokeh is missing."""
    import importlib.util

    from distributed import LocalCluster

    if dashboard and importlib.util.find_spec("bokeh") is None:
        raise InputError("the Dask dashboard needs bokeh, which is not installed: "
                         "pip install 'skinpipe[dashboard]' (or leave out --dashboard)")
    # Workers' own log lines below CRITICAL are the shutdown's (heartbeats to a closed
    # scheduler after Ctrl-C); a task's failure is reported by the batch itself.
    return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                        dashboard_address=dashboard or None, silence_logs=logging.CRITICAL)


def _stop_local_workers() -> None:
    """Kill this process's children (the local cluster's nannies and workers) at once:
    after Ctrl-C their tasks are abandoned, and closing them politely waits for the
    task running in each (seconds)."""
    import psutil

    def is_worker(child: Any) -> bool:
        # multiprocessing's resource tracker cleans up after the others: leave it be
        with contextlib.suppress(psutil.Error):
            return "resource_tracker" not in " ".join(child.cmdline())
        return False

    children = [c for c in psutil.Process().children(recursive=True) if is_worker(c)]
    for child in children:
        with contextlib.suppress(psutil.Error):
            child.kill()
    psutil.wait_procs(children, timeout=5)


def cmd_batch(args: argparse.Namespace) -> int:
    from distributed import Client

    from ..fileio import atomic_write_json, check_output_file, record_outputs
    from ..workflow.batch import (
        batch_document,
        ignore_interrupts,
        read_batch,
        remove_temporaries,
        run_batch,
        summary_table,
    )

    subjects = read_batch(args.batch)
    # the client's folder, whatever folder the workers run in (they get absolute paths)
    args.output = Path(os.path.abspath(args.output))
    check_output_file(args.output / "batch.json", [args.batch], args.force)
    root_existed = args.output.exists()
    if args.scheduler is None and not 1 <= args.local_workers <= 256:
        raise InputError(f"--local-workers must be 1-256, got {args.local_workers}")
    cluster = None
    if args.device:  # worker processes inherit it (each chooses its device in its process)
        os.environ[DEVICE_ENV] = args.device
    if args.scheduler:
        if args.dashboard:
            raise InputError("--dashboard serves a local cluster's dashboard; a scheduler "
                             "of your own serves its own (dask scheduler --dashboard-address)")
        client = Client(args.scheduler, timeout="30s")
    else:
        cluster = local_cluster(args.local_workers, args.dashboard)
        client = Client(cluster)
        client.register_plugin(ignore_interrupts())
        if args.dashboard:
            _eprint(f"batch: Dask dashboard at {client.dashboard_link}")
    interrupted = False
    try:
        _eprint(f"batch: {len(subjects)} subject(s), stages {','.join(args.stages)}, "
                f"{len(client.scheduler_info().get('workers', {}))} worker(s)")
        result = run_batch(client, subjects, args.output, args.stages, progress=_bar)
    except KeyboardInterrupt:
        interrupted = True
        # shutdown chatter: the killed workers' closed streams, in Dask's and asyncio's logs
        for name in ("distributed", "asyncio", "tornado"):
            logging.getLogger(name).setLevel(logging.CRITICAL)
        raise
    finally:
        if interrupted and cluster is not None:
            _stop_local_workers()
        client.close()
        if cluster is not None:
            with contextlib.suppress(Exception) if interrupted else contextlib.nullcontext():
                cluster.close()
        if interrupted:  # the stopped workers' task temporaries, once they are gone
            remove_temporaries(args.output)
            if not root_existed:
                with contextlib.suppress(OSError):
                    args.output.rmdir()
    doc = batch_document(result, args.output, args.stages)
    atomic_write_json(args.output / "batch.json", doc)
    record_outputs(args.output, ["batch.json"], "batch")
    print(summary_table(result))
    print(f"wrote {args.output / 'batch.json'} ({result.seconds:.1f} s, "
          f"{result.workers} workers; tasks: "
          + ", ".join(f"{n} {s}" for s, n in sorted(doc["tasks"].items())) + ")")
    if result.failed:
        for subject in result.failed:
            for t in result.tasks:
                if t["subject"] == subject and t["status"] == "failed":
                    print(f"FAILED {subject} {t['stage']} {t['unit']}: "
                          f"{t.get('error', '').splitlines()[0]}", file=sys.stderr)
        return EXIT_CHECK_FAILED
    return EXIT_OK
