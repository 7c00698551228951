"""Ray queries against closed-form answers (a plate across rays of given lengths), ray
origins against the published listing."""

from __future__ import annotations

import numpy as np
import pytest

from skinpipe.errors import InputError
from skinpipe.render.light.raytrace import CHUNK_RAYS, OFFSET_ROWS, RayScene, offset_ray_origin


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


def test_first_hits_end_where_asked() -> None:
    """intersect with lengths per ray or one for all: a plate at z = 10 is hit, at
    distance 10 and its barycentrics, by the rays that reach it and by no other; the
    caller's lengths are not changed."""
    plate = np.array([[-50.0, -50.0, 10.0], [50.0, -50.0, 10.0], [50.0, 50.0, 10.0]])
    rays = RayScene([(plate, np.array([[0, 1, 2]]))], threads=2)
    n = CHUNK_RAYS + 100
    origins = np.tile(np.float32([10.0, -10.0, 0.0]), (n, 1))
    up = np.tile(np.float32([0.0, 0.0, 1.0]), (n, 1))
    far = np.random.default_rng(3).uniform(5.0, 15.0, n).astype(np.float32)
    kept = far.copy()
    whole = rays.intersect(origins, up)
    prim, u, v, t = rays.intersect(origins, up, far)
    np.testing.assert_array_equal(prim >= 0, far > 10.0)
    reach = far > 10.0
    for got, full in zip((u, v, t), whole[1:], strict=True):
        np.testing.assert_array_equal(got[reach], full[reach])
    np.testing.assert_allclose(t[reach], 10.0)
    np.testing.assert_array_equal(far, kept)
    assert (rays.intersect(origins[:3], up[:3], 9.0)[0] < 0).all()
    assert (rays.intersect(origins[:3], up[:3], 11.0)[0] >= 0).all()


def offset_by_listing(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Wächter & Binder's listing 6-1, written out per coordinate over whole arrays."""
    of_i = (np.float32(256.0) * n).astype(np.int32)
    p_i = (p.view(np.int32) + np.where(p < 0, -of_i, of_i)).view(np.float32)
    return np.where(np.abs(p) < np.float32(1 / 32), p + np.float32(1 / 65536) * n, p_i)


def hard_origins(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Points whose magnitudes span 1e-4 to 1e4, with zeros of both signs (the listing's
    near-zero branch), and unit normals: float32 (n, 3) each."""
    rng = np.random.default_rng(seed)
    p = (rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-4, 5, (n, 1))).astype(np.float32)
    p[::11, 1] = 0.0
    p[::13, 2] = -0.0
    nrm = rng.normal(size=(n, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return p, nrm


def test_ray_origins_in_chunks_equal_the_listing_bit_for_bit() -> None:
    p, nrm = hard_origins(2 * OFFSET_ROWS + 123, 4)  # chunk borders, a short last chunk
    np.testing.assert_array_equal(offset_ray_origin(p, nrm).view(np.int32),
                                  offset_by_listing(p, nrm).view(np.int32))
    with pytest.raises(InputError, match="points and normals must agree"):
        offset_ray_origin(p, nrm[:-1])
