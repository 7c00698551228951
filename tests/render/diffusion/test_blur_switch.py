"""The direct/recursive blur switch: the crossover rule, measured on each device, cached
on disk, fixed by the environment."""

from __future__ import annotations

import pytest

from skinpipe.errors import InputError
from skinpipe.render.device import programs
from skinpipe.render.device.choice import open_device
from skinpipe.render.diffusion import blur_switch
from skinpipe.render.diffusion.blur_switch import (
    FIR_MAX_RADIUS_TUNED,
    SWITCH_ENV,
    DirectLimits,
    _crossover,
    fixed_limits,
    prefers_direct,
)
from skinpipe.render.diffusion.direct_blur import FIR_MAX_RADIUS_PER_TEXEL


def test_crossover_reference_values() -> None:
    # direct: 5 + 1.5 r ms; recursive 29 ms -> r = 16
    assert _crossover((4, 10, 16), (11.0, 20.0, 29.0), 29.0, 32) == 16
    assert _crossover((4, 10, 16), (11.0, 20.0, 29.0), 5.0, 32) == 0
    assert _crossover((4, 10, 16), (11.0, 20.0, 29.0), 500.0, 32) == 32
    assert _crossover((4, 10, 16), (9.0, 9.0, 9.0), 10.0, 11) == 11  # flat: it always wins


def test_fixed_switch_and_bad_values() -> None:
    assert fixed_limits("8,6") == DirectLimits(8, 6, "fixed")
    for bad in ("8", "a,b", "-1,3", f"{FIR_MAX_RADIUS_TUNED + 1},3"):
        with pytest.raises(InputError, match=SWITCH_ENV):
            fixed_limits(bad)


def test_prefers_direct_follows_the_limits() -> None:
    narrow = DirectLimits(3, 3, "fixed")
    assert prefers_direct(open_device(), 1.0, 1.0, limits=narrow)  # radius 3
    assert not prefers_direct(open_device(), 2.0, 1.0, limits=narrow)  # radius 7


@pytest.mark.usefixtures("cl_device")
def test_measured_on_each_device_and_cached(monkeypatch: pytest.MonkeyPatch,
                                            tmp_path: object) -> None:
    monkeypatch.delenv(SWITCH_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    blur_switch.direct_limit.cache_clear()
    try:
        # each kind measured when first asked, and only that kind
        tex, source, seconds = blur_switch.direct_limit(open_device(), per_texel=True)
        assert source == "measured" and seconds > 0
        assert 0 <= tex <= FIR_MAX_RADIUS_PER_TEXEL
        assert blur_switch.known_limit(open_device(), per_texel=False) is None
        one, source, _ = blur_switch.direct_limit(open_device(), per_texel=False)
        assert source == "measured" and 0 <= one <= FIR_MAX_RADIUS_TUNED
        blur_switch.direct_limit.cache_clear()
        assert blur_switch.direct_limit(open_device(), per_texel=True)[:2] == (tex, "cache")
        assert blur_switch.direct_limit(open_device(), per_texel=False)[:2] == (one, "cache")
    finally:
        blur_switch.direct_limit.cache_clear()


def test_measuring_one_kind_times_only_its_kernels(cl_device: object) -> None:
    before = programs.LEDGER.copy()
    limits = blur_switch.measure_direct_limits(open_device(), 256, one_sigma=False)
    assert limits.max_radius is None and limits.max_radius_per_texel is not None
    launched = programs.LEDGER.since(before)["kernel_launches"]
    assert "fir_band" not in launched and any(k.startswith("fir_band_texel") for k in launched)
