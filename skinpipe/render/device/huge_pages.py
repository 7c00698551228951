"""Whether a render's large buffers ask for transparent huge pages on this machine.

A render at texture 4096 writes about 3.5 GB of memory it has not touched before, and
the kernel zeroes each new page as it is first written. With ``madvise(MADV_HUGEPAGE)``
(numpy's default for its arrays of 4 MB and more, and :func:`~.opencl.device_buffer`'s)
it zeroes 2 MiB at a time: on bare metal no dearer than 4 KiB pages, and the transposed
blur passes miss the TLB less. In a virtual machine whose balloon reports free memory
to the host (``VIRTIO_BALLOON_F_REPORTING``, as Firecracker's does), free memory in
large blocks goes back to the host, which has to back it again when touched; a huge
page is such a block, while 4 KiB pages come first from what the guest still holds. On
the benchmark host (such a VM) 2 GB of new memory took 4.2-4.8 s with huge pages
against 0.8-1.0 s without, and a 4096 render's system time was 6.9-10.0 s against
4.0-4.8 s (docs/benchmarks.md).

A short probe cannot tell the two apart (32 MB came faster with huge pages on that
host too: the guest still held that much), so the reporting balloon is looked for in
sysfs instead (:func:`huge_pages_choice`); :data:`HUGE_PAGES_ENV` fixes the choice.
"""

from __future__ import annotations

import importlib
import mmap
import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from ...errors import InputError

HUGE_PAGES_ENV = "SKINPIPE_HUGE_PAGES"
"""``on`` or ``off``: large buffers ask for transparent huge pages or not, whatever the
machine (e.g. so that every node of a farm does the same)."""

VIRTIO_BALLOON_DEVICE = 5
"""The virtio device id of a memory balloon."""

VIRTIO_BALLOON_F_REPORTING = 5
"""The balloon's feature bit: the guest reports free pages to the host."""


@dataclass(frozen=True)
class HugePages:
    """The choice and why: "fixed" (:data:`HUGE_PAGES_ENV`), "free page reporting" (a
    balloon that reports free memory), "default" (none) or "unsupported" (no
    ``MADV_HUGEPAGE`` here)."""

    use: bool
    reason: str


def reports_free_pages(devices: Path = Path("/sys/bus/virtio/devices")) -> bool:
    """Whether a virtio balloon with free page reporting is bound here (its ``device``
    id :data:`VIRTIO_BALLOON_DEVICE`, bit :data:`VIRTIO_BALLOON_F_REPORTING` of its
    ``features``, a string of 0/1 from bit 0)."""
    try:
        entries = list(devices.iterdir())
    except OSError:
        return False
    for entry in entries:
        try:
            device = int((entry / "device").read_text().strip(), 16)
            features = (entry / "features").read_text().strip()
        except (OSError, ValueError):
            continue
        if device == VIRTIO_BALLOON_DEVICE and len(features) > VIRTIO_BALLOON_F_REPORTING \
                and features[VIRTIO_BALLOON_F_REPORTING] == "1":
            return True
    return False


@lru_cache(maxsize=1)
def huge_pages_choice() -> HugePages:
    """Whether large buffers should ask for huge pages here: :data:`HUGE_PAGES_ENV` if
    set, else not where free pages are reported to a host (:func:`reports_free_pages`),
    else yes."""
    fixed = os.environ.get(HUGE_PAGES_ENV, "").strip().lower()
    if fixed:
        if fixed not in ("on", "off"):
            raise InputError(f"${HUGE_PAGES_ENV} must be 'on' or 'off', got {fixed!r}")
        return HugePages(fixed == "on", "fixed")
    if not hasattr(mmap, "MADV_HUGEPAGE"):
        return HugePages(False, "unsupported")
    if reports_free_pages():
        return HugePages(False, "free page reporting")
    return HugePages(True, "default")


def apply_to_numpy(use: bool) -> bool:
    """Ask numpy to advise huge pages for its large arrays or not (its
    ``_set_madvise_hugepage``, where this numpy has it); whether it could."""
    for module in ("numpy._core.multiarray", "numpy.core.multiarray"):
        try:
            switch = importlib.import_module(module)._set_madvise_hugepage
        except (ImportError, AttributeError):
            continue
        switch(use)
        return True
    return False
