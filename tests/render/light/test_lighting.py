"""Lighting: Fresnel, Beckmann and Torrance-Sparrow references; light sampling against
closed-form irradiance."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from skinpipe.errors import InputError
from skinpipe.render.cache import write_json_entry
from skinpipe.render.device.choice import open_device
from skinpipe.render.light import irradiance
from skinpipe.render.light.boundary import transmission_lookup
from skinpipe.render.light.irradiance import (
    IrradianceResult,
    filter_interleaved,
    irradiance_texture,
    penumbra_at,
    penumbra_texels,
    ray_origins,
    refine_penumbrae,
    sum_axis1,
    visibility_plane,
    visibility_planes,
)
from skinpipe.render.light.raytrace import OFFSET_ROWS, RayScene, morton_order, offset_ray_origin
from skinpipe.render.light.samples import (
    LightSampler,
    complement_sets,
    grid_shape,
    interleave_period,
    interleaved_strata,
    light_sample_set,
    sample_plan,
    scrambled_sobol,
    sobol_points,
)
from skinpipe.render.light.specular import beckmann_ndf, fresnel_schlick
from skinpipe.render.options import INTERLEAVE_PERIODS
from skinpipe.render.scene import Light
from skinpipe.render.surface.texture_maps import texels_in_blocks

from .test_raytrace import hard_origins, offset_by_listing

# every test here runs on each OpenCL device that passes the probe (conftest)
pytestmark = pytest.mark.usefixtures("cl_device")


def test_fresnel_schlick_reference_values() -> None:
    # F0 = ((1.4 - 1) / (1.4 + 1))^2 = 0.02778 for skin (eta 1.4); 1 at grazing
    np.testing.assert_allclose(fresnel_schlick(1.0), 0.0277778, rtol=1e-5)
    np.testing.assert_allclose(fresnel_schlick(0.0), 1.0)
    assert np.all(np.isfinite(fresnel_schlick(np.array([np.nan, -2.0, 5.0]))[1:]))


def test_beckmann_is_normalised_over_the_hemisphere() -> None:
    theta = (np.arange(4000) + 0.5) / 4000 * (math.pi / 2)
    d_theta = math.pi / 2 / 4000
    for m in (0.2, 0.35, 0.6):
        total = (beckmann_ndf(np.cos(theta), m) * np.cos(theta) * np.sin(theta)).sum() \
            * d_theta * 2 * math.pi
        assert abs(total - 1.0) < 2e-3, m


def _floor() -> RayScene:
    pts = np.array([[-1e3, -1e3, -1.0], [1e3, -1e3, -1.0], [0.0, 1e3, -1.0]])
    return RayScene([(pts, np.array([[0, 1, 2]]))])


@pytest.mark.parametrize("sequence", ["stratified", "sobol"])
def test_sphere_light_irradiance_matches_the_closed_form(sequence: str) -> None:
    # a sphere of radius R at distance D straight above: E = L pi (R / D)^2
    matrix = np.eye(4)
    matrix[3, :3] = [0.0, 0.0, 10.0]
    light = Light("/S", "sphere", np.ones(3), matrix, radius=2.0)
    pos = np.zeros((1, 3))
    nrm = np.array([[0.0, 0.0, 1.0]])
    res = irradiance_texture(pos, nrm, [light], _floor(), samples=256,
                             sequence=sequence)
    np.testing.assert_allclose(res.entering[0], math.pi * 0.04, rtol=1e-2)


def test_dome_light_white_furnace() -> None:
    light = Light("/D", "dome", np.full(3, 0.5), np.eye(4))
    res = irradiance_texture(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), [light], _floor(),
                             samples=64)
    np.testing.assert_allclose(res.entering[0], 0.5 * math.pi, rtol=1e-5)


def test_morton_order_is_a_permutation_that_groups_neighbours() -> None:
    rng = np.random.default_rng(0)
    pts = rng.random((1000, 3))
    order = morton_order(pts)
    assert sorted(order.tolist()) == list(range(1000))
    step = np.linalg.norm(np.diff(pts[order], axis=0), axis=1).mean()
    assert step < 0.5 * np.linalg.norm(np.diff(pts, axis=0), axis=1).mean()


def test_morton_order_matches_bit_interleaving_by_hand() -> None:
    # points on the 10-bit grid itself (exact quantisation), ties kept in input order
    rng = np.random.default_rng(1)
    q = rng.integers(0, 1024, (20000, 3))
    q[0], q[1] = 0, 1023  # the grid's extent
    q[5000:5010] = q[7]  # ties
    code = np.zeros(len(q), np.int64)
    for b in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> b) & 1) << (3 * b + axis)
    expected = np.argsort(code, kind="stable")
    np.testing.assert_array_equal(morton_order(q.astype(np.float32)), expected)
    np.testing.assert_array_equal(morton_order(q.astype(np.float64)), expected)


@pytest.mark.parametrize("period", [2, 4])
def test_interleaved_strata_partition_the_grid_and_each_set_is_stratified(period: int) -> None:
    for n in (4, 8, 16, 36, 64):
        nx, ny = grid_shape(n, period)
        assert nx % period == 0 and ny % period == 0 and nx * ny >= n
        sets = interleaved_strata(n, period)
        assert sets.shape == (period**2, nx * ny // period**2)
        assert sorted(sets.ravel().tolist()) == list(range(nx * ny))
        for row in sets:
            # one stratum in every p x p block of the grid: a coarser stratification
            blocks = {((k % nx) // period, (k // nx) // period) for k in row.tolist()}
            assert len(blocks) == row.size
    assert grid_shape(10) == (4, 3) and grid_shape(10, 2) == (4, 4)


def test_interleave_period_keeps_the_reconstruction_within_a_pixel() -> None:
    """Period p where every pixel still casts each light's points (k^2 texels a pixel,
    each a p^2-th of them: p <= k), then its tent's variance, (p^2 - 1) / 6 texel^2, is
    fewer pixels^2 than period 2's at one texel a pixel, and each of the p^2 classes
    keeps a sample."""
    assert interleave_period(1.0, 16) == 2
    assert interleave_period(2.24, 16) == 2  # 5.0 texels a pixel: 5 rays at period 4
    assert interleave_period(3.99, 16) == 2  # 15.9 rays a pixel at period 4: too few
    assert interleave_period(4.0, 16) == 4 and interleave_period(4.1, 64) == 4
    assert interleave_period(8.2, 64) == 8 and interleave_period(8.2, 16) == 4
    assert interleave_period(8.2, 8) == 2  # fewer points than 16 classes
    for unknown in (0.0, float("nan"), float("inf"), -3.0):
        assert interleave_period(unknown, 16) == 2
    for k in (4.0, 5.7, 8.0, 11.3):  # the rays a pixel and light, the tent's width
        p = interleave_period(k, 64)
        assert k * k * 64 / (p * p) >= 64 and (p * p - 1) / 6 / (k * k) < 0.5
    # a period asked for: up to it, as the samples allow, whatever the texels per pixel
    assert interleave_period(1.0, 16, at_most=4) == 4
    assert interleave_period(8.2, 64, at_most=4) == 4
    assert interleave_period(1.0, 16, at_most=8) == 4 and interleave_period(1.0, 4, 8) == 2
    for p in INTERLEAVE_PERIODS:  # the bound itself, from the tent's weights
        t = p - np.abs(np.arange(1 - p, p))
        assert (t * np.arange(1 - p, p) ** 2).sum() / t.sum() == pytest.approx((p * p - 1) / 6)


def _filter_by_definition(vis: np.ndarray, traced: np.ndarray, nrm: np.ndarray,
                          min_cos: float = 0.9, period: int = 2) -> np.ndarray:
    out = vis.copy()
    lights, h, w = vis.shape
    reach = range(1 - period, period)
    for lt in range(lights):
        for y in range(h):
            for x in range(w):
                num = den = 0.0
                for dy in reach:
                    for dx in reach:
                        yy, xx = y + dy, x + dx
                        if not (0 <= yy < h and 0 <= xx < w) or traced[lt, yy, xx] <= 0:
                            continue
                        if nrm[y, x] @ nrm[yy, xx] < min_cos:
                            continue
                        t = (period - abs(dy)) * (period - abs(dx))
                        num, den = num + t * vis[lt, yy, xx], den + t
                if den > 0:
                    out[lt, y, x] = num / den
    return out


def test_sobol_sets_are_nets_and_each_interleaved_quarter_is_one() -> None:
    """Scrambled Sobol points (scipy) as light samples: 16 of them are a (0, 4, 2)-net
    in base 2 (one point in every 4 x 4, 16 x 1 and 1 x 16 cell), each interleaved
    quarter a (0, 2, 2)-net (one point per quadrant and per strip of a quarter); 10
    samples become 16."""
    rng = np.random.default_rng(3)
    grid, sets = light_sample_set(16, rng, True, "sobol")
    assert sets is not None and sets.shape == (4, 4) and sobol_points(10) == 16

    def one_per_cell(p: np.ndarray, nx: int, ny: int) -> bool:
        cells = (p[:, 0] * nx).astype(int) * ny + (p[:, 1] * ny).astype(int)
        return sorted(cells.tolist()) == list(range(nx * ny))

    assert all(one_per_cell(grid, nx, 16 // nx) for nx in (1, 2, 4, 8, 16))
    for row in sets:
        assert all(one_per_cell(grid[row], nx, 4 // nx) for nx in (1, 2, 4))
    # a seed's points are the same in every call: the adaptive pass relies on it
    again, _ = light_sample_set(16, np.random.default_rng(3), True, "sobol")
    np.testing.assert_array_equal(grid, again)
    with pytest.raises(InputError, match="unknown light sample sequence"):
        light_sample_set(16, rng, False, "halton")


def test_kept_sobol_points_are_scipys(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                       ) -> None:
    """The light samples' Sobol points, made by scipy and then read back from skinpipe's
    cache folder, are scipy's own (``qmc.Sobol``), bit for bit, and leave the generator
    in the state scipy leaves it; a kept file that does not read back, or one of other
    points, is made again; a cache folder that cannot be written keeps nothing."""
    from scipy.stats import qmc

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    for m, seed in ((16, 3), (64, 7), (1, 0)):
        scipy_rng = np.random.default_rng([seed, 11])
        want = qmc.Sobol(2, scramble=True, seed=scipy_rng).random(m)
        for _ in range(2):  # made, then read back
            rng = np.random.default_rng([seed, 11])
            np.testing.assert_array_equal(scrambled_sobol(m, rng), want)
            assert rng.bit_generator.state == scipy_rng.bit_generator.state
    kept = sorted((tmp_path / "cache" / "skinpipe" / "light-samples").glob("sobol-*.json"))
    assert len(kept) == 3
    keys = [json.loads(path.read_text())["key"] for path in kept]
    for damage in ("{", {"m": 16, "before": 0, "after": 0, "points": [2.0]}):
        for path, key in zip(kept, keys, strict=True):
            if isinstance(damage, str):
                path.write_text(damage)
            else:  # a whole entry whose points the reader refuses
                write_json_entry(path, key, damage)
        rng = np.random.default_rng([3, 11])
        want = qmc.Sobol(2, scramble=True, seed=np.random.default_rng([3, 11])).random(16)
        np.testing.assert_array_equal(scrambled_sobol(16, rng), want)
    (tmp_path / "ro").mkdir()
    (tmp_path / "ro" / "skinpipe").write_text("a file where the folder would go")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "ro"))
    np.testing.assert_array_equal(scrambled_sobol(16, np.random.default_rng([3, 11])), want)


@pytest.mark.parametrize("sequence", ["sobol", "stratified"])
def test_sample_plan_counts_the_samples_light_sample_set_makes(sequence: str) -> None:
    """The prewarm's plan of samples per point (made without the points) is what the
    samplers take from light_sample_set, for every period, interleaved or not, and a
    delta light's single sample."""
    area = Light("/L", "sphere", np.ones(3), np.eye(4), radius=2.0)
    delta = Light("/D", "distant", np.ones(3), np.eye(4), angle_deg=0.0)
    for samples in (1, 2, 3, 4, 5, 9, 10, 16, 17, 33, 64, 100):
        for interleaved in (False, True):
            for period in INTERLEAVE_PERIODS:
                grid, sets = light_sample_set(samples, np.random.default_rng(0), interleaved,
                                              sequence, period)
                want = (sets.shape[1], True) if sets is not None else (grid.shape[0], False)
                assert sample_plan(area, samples, interleaved, sequence, period) == want
                one = light_sample_set(1, np.random.default_rng(0), interleaved, sequence,
                                       period)
                assert sample_plan(delta, samples, interleaved, sequence, period) == \
                    ((one[1].shape[1], True) if one[1] is not None else (one[0].shape[0],
                                                                         False))


def test_sobol_sets_of_period_four_are_nets() -> None:
    """At period 4, 64 Sobol points make 16 sets of 4, each a (0, 2, 2)-net (one point
    per quadrant and per strip of a quarter); 16 points make 16 sets of one; 8 points
    are too few to interleave; a period other than 2, 4, 8 is refused."""
    grid, sets = light_sample_set(64, np.random.default_rng(4), True, "sobol", period=4)
    assert sets is not None and sets.shape == (16, 4)
    for row in sets:
        p = grid[row]
        for nx in (1, 2, 4):
            cells = (p[:, 0] * nx).astype(int) * (4 // nx) + (p[:, 1] * (4 // nx)).astype(int)
            assert sorted(cells.tolist()) == list(range(4))
    assert light_sample_set(16, np.random.default_rng(4), True, "sobol", 4)[1].shape == (16, 1)
    assert light_sample_set(8, np.random.default_rng(4), True, "sobol", 4)[1] is None
    with pytest.raises(InputError, match="interleaving period"):
        light_sample_set(16, np.random.default_rng(4), True, "sobol", 3)


@pytest.mark.parametrize("shape", [(1000, 3), (500, 3, 3), (7, 1)])
def test_sum_axis1_is_numpys_sum_bit_for_bit(shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(5)
    a = (rng.random(shape) * 10.0 ** rng.uniform(-8, 8, shape)).astype(np.float32)
    got = sum_axis1(a)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, a.sum(axis=1))


@pytest.mark.parametrize("period", [2, 4])
def test_filter_interleaved_matches_its_definition(period: int) -> None:
    rng = np.random.default_rng(3)
    vis = rng.random((6, 15, 11)).astype(np.float32)  # six lights: two launches
    traced = (rng.random(vis.shape) > 0.3).astype(np.float32)
    nrm = np.zeros((15, 11, 3))
    nrm[..., 2] = 1.0
    nrm[:, 6:] = [0.0, 0.6, 0.8]  # a crease: cos 0.8 < 0.9, the two sides do not mix
    nrm[0, 0] = [1.0, 0.0, 0.0]  # an isolated texel keeps its own value
    got = filter_interleaved(vis, traced, nrm, period=period)
    np.testing.assert_allclose(got, _filter_by_definition(vis, traced, nrm, period=period),
                               atol=1e-6)
    np.testing.assert_array_equal(got[:, 0, 0], vis[:, 0, 0])
    # at some texels only (any order), the same values: bit for bit at period 2; at 4
    # Intel's compiler contracts the two kernels' 49-tap sums differently (1 ulp)
    at = rng.permutation(15 * 11)[:70]
    np.testing.assert_allclose(filter_interleaved(vis, traced, nrm, at=at, period=period),
                               got.reshape(6, -1)[:, at], rtol=0 if period == 2 else 3e-7,
                               atol=0)
    assert filter_interleaved(vis, traced, nrm, at=at[:0], period=period).shape == (6, 0)
    with pytest.raises(InputError, match="flat texel indices"):
        filter_interleaved(vis, traced, nrm, at=np.array([15 * 11]))


def test_unshadowed_weights_and_colour_read_as_the_irradiance_they_make() -> None:
    # the result keeps a light's unshadowed weights and colour apart; every reading of
    # them (the traced test, the sums with a filtered visibility) is the same as from the
    # (N, 3) products, bit for bit: weights spanning float32's range down to subnormals
    # (whose products with a colour underflow to 0) and a colour with a 0 channel
    rng = np.random.default_rng(11)
    n = 4000
    weights = (rng.random(n) * 10.0 ** rng.integers(-45, 3, n)).astype(np.float32)
    weights[:500] = 0.0
    dome_weights = rng.random((n, 3)).astype(np.float32)
    dome_weights[100:300, 1:] = 0.0
    dome_weights[200:300, 0] = 0.0
    colour = np.array([3e-3, 0.0, 0.3], np.float32)
    res = IrradianceResult([], {}, {"/Key": (weights, colour),
                                    "/Dome": (dome_weights, np.ones(3, np.float32))},
                           points=n)
    key = weights[:, None] * colour
    assert res.unshadowed_irradiance("/Key").tobytes() == key.tobytes()
    assert 0 < np.count_nonzero(weights) - np.count_nonzero(key.sum(axis=1)) < n
    np.testing.assert_array_equal(res.carries_light("/Key"), key.sum(axis=1) > 0)
    np.testing.assert_array_equal(res.carries_light("/Dome"), dome_weights.sum(axis=1) > 0)
    vis = {"/Key": rng.random(n).astype(np.float32),
           "/Dome": rng.random(n).astype(np.float32)}
    want = np.zeros((n, 3), np.float32)
    for path, un in (("/Key", key), ("/Dome", dome_weights)):
        want += un * vis[path][:, None]
    assert res.entering_with(vis).tobytes() == want.tobytes()


@pytest.mark.parametrize("period", [2, 4])
def test_visibility_planes_say_what_was_traced_by_their_sign(period: int) -> None:
    # the renderer's planes (visibility_plane: negated where no ray could carry light,
    # -0.0 for 0, untouched texels -0.0) filter bit for bit as the visibility with a
    # traced plane of its own; a negative visibility beside `traced` is refused
    rng = np.random.default_rng(5)
    h, w = 13, 17
    texel = rng.permutation(h * w)[:150]
    vis_pts = rng.random((2, texel.size)).astype(np.float32)
    vis_pts[:, :20] = 0.0  # traced and dark: +0.0, not -0.0
    unshadowed = rng.random((2, texel.size, 3)).astype(np.float32)
    unshadowed[:, 140:] = 0.0  # these points' rays could carry nothing
    nrm = np.zeros((h, w, 3), np.float32)
    nrm[..., 2] = 1.0
    nrm[:, 9:] = [0.0, 0.6, 0.8]
    planes = visibility_planes(2, (h, w))
    vis, traced = np.zeros((2, h, w), np.float32), np.zeros((2, h, w), bool)
    for i in range(2):
        visibility_plane(vis_pts[i], unshadowed[i].sum(axis=1) > 0, texel, planes[i])
        np.put(vis[i], texel, vis_pts[i])
        np.put(traced[i], texel, unshadowed[i].sum(axis=1) > 0)
    assert np.signbit(planes).sum() == (~traced).sum()
    # an untraced 0 (-0.0) weighs nothing: against the definition
    np.testing.assert_allclose(filter_interleaved(planes, None, nrm, period=period),
                               _filter_by_definition(vis, traced, nrm, period=period),
                               atol=1e-6)
    for at in (None, texel):
        np.testing.assert_array_equal(
            filter_interleaved(planes, None, nrm, at=at, period=period),
            filter_interleaved(vis, traced, nrm, at=at, period=period))
    with pytest.raises(InputError, match="fraction >= 0"):
        filter_interleaved(-vis - 1, traced, nrm, period=period)


@pytest.mark.parametrize("sequence", ["stratified", "sobol"])
@pytest.mark.parametrize("period", [2, 4])
def test_complement_sets_and_each_class_make_up_every_stratum_once(sequence: str,
                                                                    period: int) -> None:
    _, sets = light_sample_set(16, np.random.default_rng(0), True, sequence, period)
    assert sets is not None
    classes, count = period**2, 16 // period**2
    others = complement_sets(sets)
    assert others.shape == (classes, 16 - count)
    for c in range(classes):
        np.testing.assert_array_equal(np.sort(np.concatenate([sets[c], others[c]])),
                                      np.arange(16))
        # the other classes' sets in turn from the next, as refine_penumbrae adds them
        np.testing.assert_array_equal(others[c, :count], sets[(c + 1) % classes])


@pytest.mark.parametrize("period", [2, 4])
def test_penumbra_at_is_penumbra_texels_at_those_texels(period: int) -> None:
    """The device's penumbra test at listed texels against the numpy definition (two
    (2p - 1)^2 filters over the plane) at the same texels: visibility exactly 0 or 1 in
    patches (where only the neighbourhood decides), in between elsewhere, values below
    0 and above 1 too (the edges' constants), texels along every border."""
    rng = np.random.default_rng(11)
    h, w = 37, 29
    vis = rng.choice(np.array([0.0, 1.0], np.float32), (h, w))
    vis[rng.random((h, w)) < 0.1] = rng.random() * 0.9 + 0.05
    vis[rng.random((h, w)) < 0.02] = 1.5
    vis[rng.random((h, w)) < 0.02] = -0.5
    vis[:12, :12] = 1.0  # a calm patch
    traced = rng.random((h, w)) > 0.25
    want = penumbra_texels(vis, traced, period).ravel()
    assert 0 < want.sum() < want.size
    at = rng.permutation(h * w)
    np.testing.assert_array_equal(penumbra_at(vis, traced, at, period), want[at])
    # untraced everywhere but one texel: only its own visibility can say
    one = np.zeros((h, w), bool)
    one[0, 0] = True
    np.testing.assert_array_equal(penumbra_at(vis, one, at, period),
                                  penumbra_texels(vis, one, period).ravel()[at])
    assert penumbra_at(vis, traced, at[:0], period).shape == (0,)
    with pytest.raises(InputError, match="flat texel indices"):
        penumbra_at(vis, traced, np.array([h * w]))
    with pytest.raises(InputError, match="planes of one shape"):
        penumbra_at(vis, traced[:, 1:], at)


def test_a_light_shadowed_everywhere_is_refined_to_no_light() -> None:
    """A plate over the whole floor: the key's interleaved pass sees it nowhere; its
    visibility is 0 (kept, for the specular lobe and the adaptive pass, and the light
    reported as adding nothing), and the adaptive pass leaves it so."""
    floor = np.array([[-50.0, -50.0, 0.0], [50.0, -50.0, 0.0], [50.0, 50.0, 0.0],
                      [-50.0, 50.0, 0.0]])
    quads = np.array([[0, 1, 2], [0, 2, 3]])
    rays = RayScene([(floor, quads), (floor * [20.0, 20.0, 0.0] + [0.0, 0.0, 10.0], quads)])
    _, key, pos, nrm, classes = _plate_over_floor()
    n = PENUMBRA_TEXELS
    first = irradiance_texture(pos, nrm, [key], rays, samples=16,
                               interleave=classes)
    assert any("adds nothing (shadowed everywhere)" in s for s in first.skipped)
    np.testing.assert_array_equal(first.visibility["/Key"], 0.0)
    assert first.unshadowed_irradiance("/Key").min() > 0
    got, refined = refine_penumbrae(first, np.ones((n, n), bool), pos, nrm, classes, [key],
                                    rays, 16)
    assert refined["/Key"].size == 0
    np.testing.assert_array_equal(got.visibility["/Key"], 0.0)
    np.testing.assert_array_equal(got.entering, 0.0)


PENUMBRA_TEXELS = 64
"""Texels of 0.5 mm along each side of :func:`_plate_over_floor`'s grid."""


def _plate_over_floor(period: int = 2, n: int = PENUMBRA_TEXELS, spacing_mm: float = 0.5
                      ) -> tuple[RayScene, Light, np.ndarray, np.ndarray, np.ndarray]:
    """A plate 10 mm over a floor hides its x < 0 half from a sphere light (radius 12 mm,
    60 mm up; a penumbra about 5 mm wide): the rays, the light, and an n x n grid of
    texels ``spacing_mm`` apart across the shadow edge at x = 0 (positions, normals,
    interleaving classes from each texel's row and column modulo ``period``)."""
    floor = np.array([[-50.0, -50.0, 0.0], [50.0, -50.0, 0.0], [50.0, 50.0, 0.0],
                      [-50.0, 50.0, 0.0]])
    plate = np.array([[-60.0, -60.0, 10.0], [0.0, -60.0, 10.0], [0.0, 60.0, 10.0],
                      [-60.0, 60.0, 10.0]])
    quads = np.array([[0, 1, 2], [0, 2, 3]])
    matrix = np.eye(4)
    matrix[3, :3] = [0.0, 0.0, 60.0]
    ys, xs = np.mgrid[0:n, 0:n]
    pos = np.stack([(xs - n / 2 + 0.5) * spacing_mm, (ys - n / 2 + 0.5) * spacing_mm,
                    0 * xs], -1)
    return (RayScene([(floor, quads), (plate, quads)]),
            Light("/Key", "sphere", np.ones(3), matrix, radius=12.0), pos.reshape(-1, 3),
            np.tile([0.0, 0.0, 1.0], (n * n, 1)),
            ((ys % period) * period + xs % period).ravel())


def test_interleaved_shadow_rays_match_full_sampling_in_a_penumbra() -> None:
    """A plate hides half a floor from a sphere light: the soft shadow from a quarter of
    the rays per texel, filtered, is as close to a 1024-sample reference as tracing all
    16 samples everywhere; texels away from the penumbra are exact."""
    rays, light, pos, nrm, classes = _plate_over_floor()
    n = PENUMBRA_TEXELS
    ref = irradiance_texture(pos, nrm, [light], rays, samples=1024)
    full = irradiance_texture(pos, nrm, [light], rays, samples=16)
    inter = irradiance_texture(pos, nrm, [light], rays, samples=16,
                               interleave=classes)
    assert inter.rays * 4 == full.rays
    traced = (inter.unshadowed_irradiance("/Key").sum(axis=1) > 0).reshape(1, n, n)
    vis = filter_interleaved(inter.visibility["/Key"].reshape(1, n, n), traced,
                             nrm.reshape(n, n, 3))
    got = inter.entering_with({"/Key": vis.ravel()})[:, 0]
    want = ref.entering[:, 0]
    rms_full = np.sqrt(np.mean((full.entering[:, 0] - want) ** 2))
    rms_inter = np.sqrt(np.mean((got - want) ** 2))
    assert 0 < rms_inter < 1.5 * rms_full
    # texels whose whole 3 x 3 neighbourhood is lit or shadowed in the reference are
    # exact (a texel beside the penumbra borrows from a neighbour in it)
    v_ref = ref.visibility["/Key"].reshape(n, n)
    calm = ~penumbra_texels(v_ref, np.ones((n, n), bool))
    assert calm.sum() > n * n / 2
    vf = vis.reshape(n, n)[calm]
    np.testing.assert_array_equal(vf, vf.round())


def test_period_four_matches_full_sampling_per_pixel_of_four_by_four_texels() -> None:
    """The same penumbra on texels 0.25 mm apart, each tracing one of the 16 samples
    (period 4: a sixteenth of the rays), filtered: at the scale of an image pixel four
    texels wide (where :func:`interleave_period` takes 4), as close to a 1024-sample
    reference as all 16 samples everywhere. Averaged over four seeds (one seed's
    16 Sobol directions leave an error that is the same shape at every texel; measured
    per pixel: 1.99e-3 against full sampling's 2.25e-3, per texel 2.86e-3 against
    2.68e-3); texels whose neighbourhood full sampling sees all lit or all shadowed are
    full sampling's exactly."""
    n, period = 128, 4
    rays, light, pos, nrm, classes = _plate_over_floor(period, n, 0.25)
    # the reference on four rows of every sixteen: whole pixels of 4 x 4 texels
    rows = np.arange(n * n).reshape(n, n)[(np.arange(n) % 16) < 4].ravel()
    want = irradiance_texture(pos[rows], nrm[rows], [light], rays,
                              samples=1024).entering[:, 0]

    def per_pixel_rms(entering: np.ndarray) -> float:
        diff = (entering[rows, 0] - want).reshape(-1, 4, n // 4, 4).mean(axis=(1, 3))
        return float(np.sqrt(np.mean(diff**2)))

    rms_full, rms_inter = [], []
    for seed in range(4):
        full = irradiance_texture(pos, nrm, [light], rays, samples=16, seed=seed)
        inter = irradiance_texture(pos, nrm, [light], rays, samples=16, seed=seed,
                                   interleave=classes, period=period)
        assert inter.rays * 16 == full.rays
        traced = (inter.unshadowed_irradiance("/Key").sum(axis=1) > 0).reshape(1, n, n)
        vis = filter_interleaved(inter.visibility["/Key"].reshape(1, n, n), traced,
                                 nrm.reshape(n, n, 3), period=period)
        rms_full.append(per_pixel_rms(full.entering))
        rms_inter.append(per_pixel_rms(inter.entering_with({"/Key": vis.ravel()})))
        v_full = full.visibility["/Key"].reshape(n, n)
        calm = ~penumbra_texels(v_full, np.ones((n, n), bool), period)
        assert calm.sum() > n * n / 2
        np.testing.assert_array_equal(vis.reshape(n, n)[calm], v_full[calm])
    assert 0 < np.mean(rms_inter) < 1.1 * np.mean(rms_full)


@pytest.mark.parametrize("sequence", ["stratified", "sobol"])
@pytest.mark.parametrize("period", [2, 4])
def test_adaptive_shadow_rays_equal_full_sampling_with_fewer_rays(sequence: str,
                                                                  period: int) -> None:
    """The same penumbra: after the interleaved pass, the texels whose neighbourhood
    disagrees trace the other classes' strata (three quarters at period 2, fifteen
    sixteenths at 4), and then every texel's visibility is full sampling's (the same
    strata: each light's own random numbers), outside the penumbra exactly 0 or 1, for
    well under half of full sampling's rays."""
    rays, key, pos, nrm, classes = _plate_over_floor(period)
    lights = [key, Light("/Fill", "dome", np.full(3, 0.2), np.eye(4))]
    n = PENUMBRA_TEXELS
    full = irradiance_texture(pos, nrm, lights, rays, samples=16,
                                 sequence=sequence)
    inter = irradiance_texture(pos, nrm, lights, rays, samples=16,
                               interleave=classes, sequence=sequence, period=period)
    covered = np.ones((n, n), bool)
    got, refined = refine_penumbrae(inter, covered, pos, nrm, classes, lights, rays, 16,
                                    sequence=sequence, period=period)
    assert got.interleaved == frozenset()
    for path in ("/Key", "/Fill"):
        np.testing.assert_allclose(got.visibility[path], full.visibility[path], atol=2e-6)
    # outside the penumbra the unshadowed light is from the texel's share of the
    # strata (a smooth integrand: 0.1% here from four strata, 1.1% from one)
    np.testing.assert_allclose(got.entering, full.entering, rtol=5e-3 if period == 2 else 1.5e-2,
                               atol=1e-6)
    # every floor texel sees the plate somewhere in the dome: all of them are refined;
    # the key's penumbra is a band
    assert refined["/Fill"].size == n * n and 0 < refined["/Key"].size < 0.4 * n * n
    key_only = irradiance_texture(pos, nrm, lights[:1], rays, samples=16,
                                 sequence=sequence)
    key_inter = irradiance_texture(pos, nrm, lights[:1], rays, samples=16,
                                   interleave=classes, sequence=sequence, period=period)
    key_got, _ = refine_penumbrae(key_inter, covered, pos, nrm, classes, lights[:1], rays, 16,
                                  sequence=sequence, period=period)
    assert key_got.rays < 0.5 * key_only.rays
    # outside the refined texels the neighbourhood agreed: visible or blocked
    key = got.visibility["/Key"].reshape(n, n)
    vis1 = inter.visibility["/Key"].reshape(n, n)
    calm = ~penumbra_texels(vis1, covered, period)
    np.testing.assert_array_equal(key[calm], key[calm].round())
    assert calm.sum() == n * n - refined["/Key"].size


def test_points_in_blocks_cast_as_they_come_give_each_point_the_same_light() -> None:
    """The renderer passes the texels in blocks (texels_in_blocks) and casts their rays
    in that order (``coherent``): each point's light, interleaved and refined, is what
    the same point gets in row order sorted along a Morton curve, bit for bit."""
    rays, key, pos, nrm, classes = _plate_over_floor()
    lights = [key, Light("/Fill", "dome", np.full(3, 0.2), np.eye(4))]
    n = PENUMBRA_TEXELS
    covered = np.ones((n, n), bool)
    texel = texels_in_blocks(covered, block=4)
    assert not np.array_equal(texel, np.arange(n * n))
    rows = irradiance_texture(pos, nrm, lights, rays, samples=16, interleave=classes)
    rows, rows_refined = refine_penumbrae(rows, covered, pos, nrm, classes, lights, rays, 16)
    blocks = irradiance_texture(pos[texel], nrm[texel], lights, rays, samples=16,
                                interleave=classes[texel], coherent=True)
    blocks, refined = refine_penumbrae(blocks, covered, pos[texel], nrm[texel],
                                       classes[texel], lights, rays, 16, texel=texel,
                                       coherent=True)
    assert blocks.rays == rows.rays
    np.testing.assert_array_equal(blocks.entering, rows.entering[texel])
    for path in ("/Key", "/Fill"):
        np.testing.assert_array_equal(blocks.visibility[path], rows.visibility[path][texel])
        np.testing.assert_array_equal(np.sort(texel[refined[path]]), rows_refined[path])


def _visible_fraction(point: np.ndarray, samples: int = 400) -> float:
    """The cosine-weighted fraction of :func:`_plate_over_floor`'s sphere light a floor
    point sees past the plate, by a midpoint rule over the cone the sphere subtends
    (samples x samples directions) and the plate's half-plane tested in closed form:
    neither skinpipe's samplers nor Embree."""
    centre, radius, plate_z = np.array([0.0, 0.0, 60.0]), 12.0, 10.0
    to_c = centre - point
    axis = to_c / np.linalg.norm(to_c)
    cos_max = math.sqrt(1.0 - (radius / np.linalg.norm(to_c)) ** 2)
    u, v = np.meshgrid((np.arange(samples) + 0.5) / samples, (np.arange(samples) + 0.5) / samples)
    cos_t = 1.0 - u * (1.0 - cos_max)
    sin_t, phi = np.sqrt(1.0 - cos_t**2), 2.0 * math.pi * v
    t = np.cross(axis, [0.0, 1.0, 0.0])
    t /= np.linalg.norm(t)
    b = np.cross(axis, t)
    d = ((sin_t * np.cos(phi))[..., None] * t + (sin_t * np.sin(phi))[..., None] * b
         + cos_t[..., None] * axis)
    cos_floor = np.maximum(d[..., 2], 0.0)
    s = (plate_z - point[2]) / d[..., 2]
    x, y = point[0] + s * d[..., 0], point[1] + s * d[..., 1]
    blocked = (x > -60.0) & (x < 0.0) & (np.abs(y) < 60.0)
    return float((cos_floor * ~blocked).sum() / cos_floor.sum())


@pytest.mark.parametrize("sequence", ["stratified", "sobol"])
@pytest.mark.parametrize(("coherent", "period"), [(False, 2), (True, 2), (True, 4)])
def test_adaptive_visibility_against_an_independent_quadrature(sequence: str,
                                                                coherent: bool,
                                                                period: int) -> None:
    """Across the soft shadow edge, adaptive visibility at 16 samples against a
    160,000-direction quadrature of the sphere light past the plate (measured: RMS
    0.0146 stratified, 0.0095 Sobol, worst 0.068 over a row of 64 texels, 10 of them in
    the penumbra); outside the penumbra exactly 0 or 1 as the quadrature says. Points
    sorted along a Morton curve, or in blocks cast as they come (the renderer's way);
    interleaving periods 2 and 4."""
    rays, key, pos, nrm, classes = _plate_over_floor(period)
    n = PENUMBRA_TEXELS
    covered = np.ones((n, n), bool)
    texel = texels_in_blocks(covered, block=8) if coherent else np.arange(n * n)
    row = np.arange(n * n).reshape(n, n)[n // 2]
    want = np.array([_visible_fraction(pos[i]) for i in row])
    first = irradiance_texture(pos[texel], nrm[texel], [key], rays, samples=16,
                               interleave=classes[texel], sequence=sequence,
                               coherent=coherent, period=period)
    got, _ = refine_penumbrae(first, covered, pos[texel], nrm[texel], classes[texel], [key],
                              rays, 16, sequence=sequence, texel=texel,
                              coherent=coherent, period=period)
    by_texel = np.empty(n * n, np.float32)
    by_texel[texel] = got.visibility["/Key"]
    vis = by_texel[row]
    assert 5 <= ((want > 0) & (want < 1)).sum() <= 20
    assert np.sqrt(np.mean((vis - want) ** 2)) < 0.025
    assert np.abs(vis - want).max() < 0.1
    clear = (want == 0) | (want == 1)
    np.testing.assert_array_equal(vis[clear], want[clear])


@pytest.mark.parametrize("kind", ["sphere", "dome"])
@pytest.mark.parametrize(("interleaved", "period"), [(False, 2), (True, 2), ("complement", 2),
                                                     (True, 4), ("complement", 4)])
def test_device_samples_equal_the_numpy_samples(kind: str, interleaved: bool | str,
                                                period: int) -> None:
    # the OpenCL sampler (sphere lights, untextured domes) computes what LightSampler.sample
    # and the boundary's transmission compute in numpy, from the same strata
    rng = np.random.default_rng(5)
    n = 5003  # the kernel's last work-item holds three points of its eight lanes
    pts = rng.normal(size=(n, 3)).astype(np.float32)
    nrm = rng.normal(size=(n, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    matrix = np.eye(4)
    matrix[3, :3] = [3.0, 40.0, 25.0]
    light = Light("/L", kind, np.ones(3), matrix, radius=4.0) if kind == "sphere" else \
        Light("/L", kind, np.full(3, 0.5), np.eye(4))
    classes = rng.integers(0, period**2, n) if interleaved else None
    sampler, numpy = (LightSampler(light, pts, nrm, 16, np.random.default_rng(1), None,
                                   classes, 1.4, device=dev,
                                   complement=interleaved == "complement", period=period)
                      for dev in (open_device(), None))
    assert sampler.device is not None and numpy.device is None
    share = 16 // period**2
    assert sampler.count == {False: 16, True: share, "complement": 16 - share}[interleaved]
    for k in range(sampler.count):
        d, dist, w = sampler.entering_sample(k)
        d_ref, dist_ref, w_ref = numpy.sample(k)
        enters = transmission_lookup(np.einsum("ij,ij->i", nrm, d_ref.astype(np.float64)),
                                     1.4)
        np.testing.assert_allclose(d, d_ref, atol=2e-6)
        np.testing.assert_allclose(w, w_ref * enters, rtol=2e-5, atol=1e-7)
        # the ray ends where it starts (length 0) where the sample carries nothing: the
        # two agree on which points those are but at grazing directions (cos ~ 0)
        lit = w_ref * enters > 0
        agree = (w > 0) == lit
        assert agree.mean() > 0.999
        np.testing.assert_allclose(dist[agree], np.where(lit, dist_ref, 0)[agree], rtol=1e-6)
        assert np.all(dist[w == 0] == 0) and np.all(dist[w > 0] > 0)
    assert np.all(np.isfinite(w)) and np.all(w >= 0)
    # a span of the points (a block of cast_samples' jobs) is those rows of the whole,
    # into arrays of its own length; the last span's work-item holds fewer than eight
    for first, count in ((0, 8), (13, 2990), (4999, 4)):
        d, dist, w = sampler.entering_sample(sampler.count - 1)
        into = (np.empty((count, 3), np.float32), np.empty(count, np.float32))
        d_s, dist_s, w_s = sampler.entering_sample(sampler.count - 1, into, (first, count))
        assert d_s is into[0] and dist_s is into[1]
        for part, whole in ((d_s, d), (dist_s, dist), (w_s, w)):
            np.testing.assert_array_equal(part, whole[first:first + count])
    with pytest.raises(InputError, match="on the device only"):
        numpy.entering_sample(0, None, (1, 3))


def test_shadow_rays_cast_in_blocks_give_the_same_sums(monkeypatch: pytest.MonkeyPatch
                                                       ) -> None:
    """cast_samples' jobs of RAY_BLOCK_POINTS points of a sample each (the device's
    samplers; a numpy one's samples whole) give every light the same sums and rays bit
    for bit as whole samples."""
    rays, key, pos, nrm, classes = _plate_over_floor()
    lights = [key, Light("/Fill", "dome", np.full(3, 0.2), np.eye(4)),
              Light("/Sun", "distant", np.full(3, 0.5), np.eye(4), angle_deg=2.0)]
    whole = irradiance_texture(pos, nrm, lights, rays, samples=16, interleave=classes)
    monkeypatch.setattr(irradiance, "RAY_BLOCK_POINTS", 1000)
    assert len(irradiance.ray_blocks(LightSampler(
        key, pos, nrm, 16, np.random.default_rng(0), device=open_device()))) == \
        -(-pos.shape[0] // 1000)
    blocks = irradiance_texture(pos, nrm, lights, rays, samples=16, interleave=classes)
    assert blocks.rays == whole.rays
    np.testing.assert_array_equal(blocks.entering, whole.entering)
    for path in ("/Key", "/Fill", "/Sun"):
        np.testing.assert_array_equal(blocks.visibility[path], whole.visibility[path])
        np.testing.assert_array_equal(blocks.unshadowed_irradiance(path),
                                      whole.unshadowed_irradiance(path))


def test_device_ray_origins_equal_the_listing_bit_for_bit() -> None:
    """ray_origins (OpenCL) against Wächter & Binder's listing written out in numpy, and
    so against offset_ray_origin: magnitudes from 1e-4 to 1e4, zeros of both signs (the
    near-zero branch's product and sum, which must not be fused), an odd count."""
    p, nrm = hard_origins(OFFSET_ROWS + 77, 8)
    got = ray_origins(p, nrm).view(np.int32)
    np.testing.assert_array_equal(got, offset_by_listing(p, nrm).view(np.int32))
    np.testing.assert_array_equal(got, offset_ray_origin(p, nrm).view(np.int32))
    assert ray_origins(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0, 3)
    with pytest.raises(InputError, match="points and normals must agree"):
        ray_origins(p, nrm[:-1])


@pytest.mark.parametrize("kind", ["sphere", "dome"])
def test_no_points_is_no_rays(kind: str) -> None:
    # a sampler over no points launches nothing (mapping an empty output buffer raised
    # clEnqueueMapBuffer INVALID_VALUE); the irradiance of no points is empty
    matrix = np.eye(4)
    matrix[3, :3] = (0.0, 0.0, 5.0)
    light = Light("/L", kind, np.ones(3), matrix, radius=1.0)
    none = np.zeros((0, 3))
    d, dist, w = LightSampler(light, none, none, 16, np.random.default_rng(0),
                              device=open_device()).entering_sample(0)
    assert d.shape == (0, 3) and dist.shape == (0,) and w.shape == (0,)
    res = irradiance_texture(none, none, [light], _floor(), 16, interleave=np.zeros(0, int))
    assert res.entering.shape == (0, 3) and res.rays == 0
