"""The memory a render asks for, refused before it starts when the machine lacks it."""

from __future__ import annotations

import pytest

from skinpipe.errors import InputError
from skinpipe.render.budget import available_bytes, check_render_fits, render_bytes


def test_the_estimate_grows_with_texels_and_pixels():
    base = render_bytes(1024, (768, 768))
    assert render_bytes(2048, (768, 768)) - base == 165 * (2048**2 - 1024**2)
    assert render_bytes(1024, (1536, 768)) - base == 205 * 768 * 768
    # the demo face at texture 4096 measured 2.7 GB when it made its layout
    assert 2.5e9 < render_bytes(4096, (768, 768)) < 3.6e9


def test_a_render_larger_than_memory_is_refused_naming_both_figures(monkeypatch):
    monkeypatch.delenv("SKINPIPE_MEMORY_CHECK", raising=False)
    with pytest.raises(InputError, match=r"texture 16384 .* 42\.0 GiB.* 8\.0 GiB available"):
        check_render_fits(16384, (1024, 1024), available=8 << 30)
    assert check_render_fits(1024, (1024, 1024), available=8 << 30) > 0


def test_the_check_can_be_turned_off(monkeypatch):
    monkeypatch.setenv("SKINPIPE_MEMORY_CHECK", "off")
    assert check_render_fits(16384, (16384, 16384), available=1 << 30) > 60 << 30


def test_this_machine_reports_its_memory():
    have = available_bytes()
    assert have is None or have > 0
