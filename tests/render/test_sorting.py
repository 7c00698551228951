"""The packed integer sorts against numpy's own stable argsort and np.unique."""

from __future__ import annotations

import numpy as np
import pytest

from skinpipe.render.sorting import stable_order, unique_keys


@pytest.mark.parametrize(("n", "high"), [(1, 5), (1000, 7), (200_000, 10**12), (5000, 2**62)])
def test_packed_sorts_are_numpys_stable_sort_and_unique(n: int, high: int) -> None:
    """stable_order against np.argsort(kind="stable") and unique_keys against
    np.unique's first indices, inverse and counts: keys with many repeats, wide keys
    (the packed sort's bits run out at 2^62 with these indices: numpy's own sort),
    negative keys (numpy's own sort too), and keys nearly in order (the stable sort of
    the packed keys, where the others take the default one)."""
    rng = np.random.default_rng(n)
    nearly = np.sort(rng.integers(0, high, n))  # in order but for a few (the other sort)
    nearly[rng.integers(0, n, max(1, n // 100))] = rng.integers(0, high, max(1, n // 100))
    for keys in (rng.integers(0, high, n), rng.integers(-high, high, n), nearly):
        np.testing.assert_array_equal(stable_order(keys), np.argsort(keys, kind="stable"))
        _, first, inverse, counts = np.unique(keys, return_index=True, return_inverse=True,
                                              return_counts=True)
        for got, want in zip(unique_keys(keys), (first, inverse, counts), strict=True):
            np.testing.assert_array_equal(got, want)
    assert all(a.size == 0 for a in unique_keys(np.zeros(0, np.int64)))
