"""Issue 20's must-hold through the ingest study: simulated captures with every effect on
(coarse pixels, a Gaussian projector footprint, a black level under a dark surround, a
12.8 mm field the red tail leaves, a P3 camera), ingested and measured against the
simulator's observed truth."""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor

import pytest

from skinpipe.capture.study import (
    MUST_HOLD,
    IngestCase,
    must_hold,
    run_case,
    run_seed,
    standard_cases,
    summarise,
)


def _must_hold_cases() -> list[IngestCase]:
    return [c for c in standard_cases() if c.group == "must-hold"]


def _check(summaries: dict) -> None:
    result = must_hold(summaries)
    failed = {k: v for k, v in result.items() if not v["holds"]}
    assert not failed, (failed, summaries)


@pytest.mark.slow  # 23-28 s on 2 cores: the default run reached 10.9 min in slow periods
def test_must_hold_on_one_seed() -> None:
    """One seed of the six regions per must-hold case (the three cases side by side):
    worst channel <= 1.5% without hair (measured 0.27-0.70%), <= 3% with three strands
    at least 3 px from the entry point (0.25-0.73%), the merged flux within 0.3% (0.2%),
    and every region with a strand over its entry point refused by name."""
    cases = _must_hold_cases()
    with ProcessPoolExecutor(max_workers=min(len(cases), os.cpu_count() or 1)) as pool:
        rows = list(pool.map(run_seed, cases, [0] * len(cases)))
    summaries = {(c.group, c.name): summarise(r) for c, r in zip(cases, rows, strict=True)}
    _check(summaries)
    over = next(r for c, r in zip(cases, rows, strict=True) if "over" in c.name)
    assert all(f"'{r['region']}': hair covers" in r["refused"] for r in over)


@pytest.mark.slow
@pytest.mark.timeout(1800)  # 8-11 min on two cores: past the suite's 600 s per test
def test_must_hold_over_thirty_seeds() -> None:
    """The issue's own numbers: 30 seeds x 6 regions per must-hold case (about 8 minutes
    on two cores)."""
    summaries = {}
    for case in _must_hold_cases():
        summaries[(case.group, case.name)] = summarise(
            run_case(case, range(30), workers=os.cpu_count() or 1))
    _check(summaries)


def test_must_hold_fails_where_a_limit_is_missed() -> None:
    """The check itself: a worst channel just over the limit, a flux error over 0.3%, a
    refused clean region or an accepted strand over the entry point each fail it."""
    def rows(error: float, flux: float = 0.001, refused: str | None = None) -> list[dict]:
        return [{"refused": refused, "seconds": 1.0, "error_max": error,
                 "flux_error": [flux, 0.0, 0.0], "entry_error_px": 0.01}]

    def summaries(no_hair: list, hair: list, over: list) -> dict:
        return {("must-hold", "no hair"): summarise(no_hair),
                ("must-hold", "hair >= 3 px"): summarise(hair),
                ("must-hold", "strand over the entry point"): summarise(over)}

    refused = rows(0.0, refused="region 'x': hair covers 90% of the core")
    good = summaries(rows(0.01), rows(0.02), refused)
    assert all(v["holds"] for v in must_hold(good).values())
    bad = [summaries(rows(MUST_HOLD["no hair"] * 1.01), rows(0.02), refused),
           summaries(rows(0.01), rows(MUST_HOLD["hair >= 3 px"] * 1.01), refused),
           summaries(rows(0.01, flux=0.0031), rows(0.02), refused),
           summaries(rows(0.01) + refused, rows(0.02), refused),
           summaries(rows(0.01), rows(0.02), refused + rows(0.01))]
    for case in bad:
        assert not all(v["holds"] for v in must_hold(case).values()), case
