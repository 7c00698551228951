"""Steps in bands on the cores: the same values as the whole step, in band order."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from skinpipe.render import bands
from skinpipe.render.bands import band_slices, beside, in_bands


def test_band_slices_cover_every_item_once() -> None:
    for n, items in ((0, 4), (1, 4), (7, 3), (12, 4), (13, 1), (5, 100)):
        got = band_slices(n, items)
        covered = np.concatenate([np.arange(n)[s] for s in got]) if got else np.array([])
        np.testing.assert_array_equal(covered, np.arange(n))
        assert all(0 < s.stop - s.start <= items for s in got)


def test_in_bands_is_the_whole_step(monkeypatch: pytest.MonkeyPatch) -> None:
    """A masked copy and a sum made in bands equal the whole-array numpy step, on one
    thread and on several (more threads than bands too); results come in band order;
    one core: every band on the calling thread."""
    rng = np.random.default_rng(1)
    values = rng.random((301, 17, 3)).astype(np.float32)
    mask = rng.random((301, 17)) > 0.3
    want = np.where(mask[..., None], values, np.float32(0))
    for threads in (1, 2, 3, 64):
        monkeypatch.setattr(bands, "host_threads", lambda t=threads: t)
        seen: set[int] = set()
        out = np.empty_like(values)

        def band(rows: slice, out=out, seen=seen) -> int:
            seen.add(threading.get_ident())
            out[rows] = np.where(mask[rows][..., None], values[rows], np.float32(0))
            return rows.start

        starts = in_bands(band, values.shape[0], 40)
        np.testing.assert_array_equal(out, want)
        assert starts == list(range(0, 301, 40))
        if threads == 1:
            assert seen == {threading.get_ident()}


def test_at_most_band_threads_work_at_once_on_many_cores(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """On 64 cores no more than BAND_THREADS bands run at once (each thread's heap arena
    keeps its free memory), and they do run side by side."""
    monkeypatch.setattr(bands, "host_threads", lambda: 64)
    lock, now, most = threading.Lock(), [0], [0]
    gate = threading.Barrier(bands.BAND_THREADS, timeout=600)  # a hang guard

    def band(rows: slice) -> None:
        with lock:
            now[0] += 1
            most[0] = max(most[0], now[0])
        if rows.start < bands.BAND_THREADS:  # the first bands wait for each other
            gate.wait()
        with lock:
            now[0] -= 1

    in_bands(band, 40, 1)
    assert most[0] == bands.BAND_THREADS


def test_beside_runs_on_a_named_thread_of_its_own_and_hands_back_errors() -> None:
    names: list[str] = []

    def work() -> int:
        names.append(threading.current_thread().name)
        return 7

    assert beside(work, "skinpipe-test").result() == 7
    assert names[0].startswith("skinpipe-test") and names[0] != threading.current_thread().name
    with pytest.raises(ZeroDivisionError):
        beside(lambda: 1 // 0, "skinpipe-test").result()
