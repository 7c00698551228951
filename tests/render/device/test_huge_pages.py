"""The choice of transparent huge pages for large buffers (skinpipe/render/device/huge_pages.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from skinpipe.errors import InputError
from skinpipe.render.device import huge_pages
from skinpipe.render.device.huge_pages import HUGE_PAGES_ENV, apply_to_numpy, reports_free_pages


def _virtio(root: Path, name: str, device: str, features: str) -> None:
    (root / name).mkdir(parents=True)
    (root / name / "device").write_text(device + "\n")
    (root / name / "features").write_text(features + "\n")


def test_a_balloon_that_reports_free_pages_is_found_in_sysfs(tmp_path: Path) -> None:
    # Firecracker's balloon as this host shows it: bits 1, 2 and 5 (reporting) set
    _virtio(tmp_path, "virtio0", "0x0002", "0110010" + "0" * 57)  # a disk: bit 5 is another
    assert not reports_free_pages(tmp_path)
    _virtio(tmp_path, "virtio1", "0x0005", "0110000" + "0" * 57)  # a balloon, no reporting
    assert not reports_free_pages(tmp_path)
    _virtio(tmp_path, "virtio3", "not hex", "0110010")  # unreadable entries are passed over
    (tmp_path / "virtio4").mkdir()
    _virtio(tmp_path, "virtio5", "0x0005", "01")  # too few feature bits
    assert not reports_free_pages(tmp_path)
    _virtio(tmp_path, "virtio2", "0x0005", "0110010" + "0" * 57)
    assert reports_free_pages(tmp_path)
    assert not reports_free_pages(tmp_path / "missing")


def test_the_environment_fixes_the_choice(monkeypatch: pytest.MonkeyPatch) -> None:
    for value, use in (("on", True), ("OFF", False)):
        monkeypatch.setenv(HUGE_PAGES_ENV, value)
        huge_pages.huge_pages_choice.cache_clear()
        assert huge_pages.huge_pages_choice() == huge_pages.HugePages(use, "fixed")
    monkeypatch.setenv(HUGE_PAGES_ENV, "maybe")
    huge_pages.huge_pages_choice.cache_clear()
    with pytest.raises(InputError, match=HUGE_PAGES_ENV):
        huge_pages.huge_pages_choice()
    monkeypatch.delenv(HUGE_PAGES_ENV)
    huge_pages.huge_pages_choice.cache_clear()
    choice = huge_pages.huge_pages_choice()
    assert choice.use == (choice.reason == "default")


def test_numpy_is_told_whether_to_advise_huge_pages() -> None:
    from numpy._core import multiarray

    before = multiarray._get_madvise_hugepage()
    try:
        assert apply_to_numpy(not before)
        assert multiarray._get_madvise_hugepage() == (not before)
    finally:
        multiarray._set_madvise_hugepage(before)
    assert np.ones(1 << 21).sum() == 1 << 21  # arrays are made either way
