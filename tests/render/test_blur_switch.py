"""The direct/recursive blur switch: the crossover rule, measured on each device, cached
on disk, fixed by the environment."""

from __future__ import annotations

import pytest

from pipeline.errors import InputError
from pipeline.render import blur_switch, opencl
from pipeline.render.blur_switch import (
    FIR_MAX_RADIUS_TUNED,
    SWITCH_ENV,
    DirectLimits,
    _crossover,
    fixed_limits,
    prefers_direct,
)
from pipeline.render.direct_blur import FIR_MAX_RADIUS_PER_TEXEL


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
    assert prefers_direct(1.0, 1.0, limits=narrow)  # radius 3
    assert not prefers_direct(2.0, 1.0, limits=narrow)  # radius 7


@pytest.mark.usefixtures("cl_device")
def test_measured_on_each_device_and_cached(monkeypatch: pytest.MonkeyPatch,
                                            tmp_path: object) -> None:
    monkeypatch.delenv(SWITCH_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    blur_switch.direct_limits.cache_clear()
    try:
        first = blur_switch.direct_limits()
        assert first.source == "measured" and first.seconds > 0
        assert 0 <= first.max_radius <= FIR_MAX_RADIUS_TUNED
        assert 0 <= first.max_radius_per_texel <= FIR_MAX_RADIUS_PER_TEXEL
        blur_switch.direct_limits.cache_clear()
        again = blur_switch.direct_limits()
        assert again.source == "cache"
        assert (again.max_radius, again.max_radius_per_texel) == \
            (first.max_radius, first.max_radius_per_texel)
    finally:
        blur_switch.direct_limits.cache_clear()
    assert opencl.device_choice() is not None
