"""Ray queries against closed-form answers: a plate across rays of given lengths."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.render.raytrace import CHUNK_RAYS, RayScene


def test_rays_end_where_asked_and_rays_of_no_length_are_not_traced() -> None:
    """Rays straight up from below a plate at z = 10: blocked exactly when they reach
    it (length > 10); a length of 0 or less, or NaN, is no ray (False, and not counted),
    in chunks with and without such rays."""
    plate = np.array([[-50.0, -50.0, 10.0], [50.0, -50.0, 10.0], [50.0, 50.0, 10.0],
                      [-50.0, 50.0, 10.0]])
    rays = RayScene([(plate, np.array([[0, 1, 2], [0, 2, 3]]))], threads=2)
    n = CHUNK_RAYS + 5000  # the second chunk holds every idle ray
    rng = np.random.default_rng(2)
    origins = np.zeros((n, 3), np.float32)
    origins[:, :2] = rng.uniform(-40.0, 40.0, (n, 2))
    up = np.tile(np.float32([0.0, 0.0, 1.0]), (n, 1))
    far = rng.uniform(0.5, 20.0, n).astype(np.float32)
    idle = np.zeros(n, bool)
    idle[CHUNK_RAYS::3] = True
    far[CHUNK_RAYS::3] = 0.0
    far[CHUNK_RAYS + 1::9] = -1.0
    far[CHUNK_RAYS + 4::9] = np.nan
    idle |= ~(far > 0)
    got = rays.occluded(origins, up, far)
    np.testing.assert_array_equal(got, ~idle & (far > 10.0))
    assert rays.stats.rays["occlusion"] == n - idle.sum()
    # the caller's lengths are read, not changed
    assert np.isnan(far[CHUNK_RAYS + 4]) and far[CHUNK_RAYS] == 0.0


@pytest.mark.parametrize("far", [None, 5.0, 0.0])
def test_one_length_for_all_rays(far: float | None) -> None:
    plate = np.array([[-50.0, -50.0, 10.0], [50.0, -50.0, 10.0], [50.0, 50.0, 10.0]])
    rays = RayScene([(plate, np.array([[0, 1, 2]]))])
    origins = np.tile(np.float32([10.0, -10.0, 0.0]), (4, 1))  # inside the triangle
    up = np.tile(np.float32([0.0, 0.0, 1.0]), (4, 1))
    np.testing.assert_array_equal(rays.occluded(origins, up, far), np.full(4, far is None))
    assert rays.stats.rays.get("occlusion", 0) == (0 if far == 0.0 else 4)
