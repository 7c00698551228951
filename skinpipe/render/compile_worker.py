"""A second process that compiles part of a render's kernels into the disk caches.

PoCL compiles one program or kernel at a time per process (its compiler is behind one
lock), so a cold first render's compilations form one chain however many threads ask
for them. A render that starts a :class:`~.opencl.Prewarm` hands the later part of its
plan to this process (``python -m skinpipe.render.compile_worker SPECS``), which builds
and compiles them on the same device into the same caches (pyopencl's binaries and
PoCL's kernels, both written by rename) while the render's own thread compiles the
first part; the render then loads them from the caches. Nothing it does is needed for
a correct render: if it fails or is killed, the render compiles what it needs itself.

``SPECS`` is JSON: a list of ``[module, function, args]``, each a step of the plan
(:class:`~.opencl.PlannedStep`).
"""

from __future__ import annotations

import json
import sys

WORKER_NICENESS = 10
"""The worker runs below the render's priority: the render's own work (Embree's rays,
numpy) comes first, the compilations fill what it leaves."""


def main(argv: list[str]) -> int:
    import os

    from .opencl import PlannedStep, Prewarm

    if hasattr(os, "nice"):
        os.nice(WORKER_NICENESS)

    steps = [PlannedStep(m, f, tuple(a)) for m, f, a in json.loads(argv[0])]
    Prewarm(steps).wait()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
