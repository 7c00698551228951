"""Texture-space diffusion (d'Eon, Luebke & Enderton 2007; the paper's section 3): each
term of the sum of Gaussians blurs the irradiance as a normalised convolution on its
pyramid level, with per-texel sigma from the stretch maps, and the terms are added per
texel with the region-blended weights."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pyopencl as cl
from numpy.typing import NDArray

from ...errors import InputError
from ..device.choice import Device, or_default
from ..device.memory import (
    host_buffer,
    host_output,
    read_output,
)
from .blur_switch import prefers_direct
from .direct_blur import direct_kernels, fir_weight_table
from .inputs import BlurStats, _check_irradiance, _check_terms
from .layout import (
    DIRECT_TEXEL_QUANTILE,
    ChartLayout,
    DiffusionLayout,
    LevelGrid,
    _fill_level,
    _job_sigma_mm,
    _release_level,
    pyramid_kernels,
)
from .recursive_blur import (
    QUANT_STEPS_PER_OCTAVE,
    TABLE_MIN_SIGMA,
)
from .surface_terms import SurfaceLight, surface_light

FloatImage = NDArray[np.float32]
TERM_BUFFER_TEXTURES = 4
"""Blurred terms kept at once before they are added up, in full-resolution textures
(64 MiB each at 2048^2): each further batch reads and writes the result once more."""
TERM_BUFFER_MAX_BYTES = 256 << 20
"""...but at most this many bytes of them (or one term, if larger): at texture 4096 four
textures are 1 GiB; at 512 MiB the demo scene's render peaked at 6.71 GB instead of
7.38 GB, the same image, the diffusion as fast (two textures: 9.15 s against 9.19 s);
at 256 MiB, with the seam reads as positions and one level's atlas at a time, 4.25-4.30
GB instead of 4.42-4.58 GB, the diffusion 4.6-5.0 s against 4.2-5.5 s (three renders
each, in turns) and the image bit for bit: each batch adds its terms in turn to what the
last left, so the cap changes no sum."""
_TERM_ALIGN = 4096
"""Byte alignment of each term in the term buffer (a sub-buffer's origin must be aligned
to the device's base address alignment, at most 4 KiB)."""


def _term_batches(sizes: list[int], budget: int) -> list[dict[int, tuple[int, int]]]:
    """Consecutive jobs grouped so that each group's blurred textures (``sizes`` bytes,
    0 for one that reads the irradiance itself) fit ``budget`` bytes side by side: per
    group, job -> (start, end) byte range in the term buffer."""
    batches: list[dict[int, tuple[int, int]]] = [{}]
    used = 0
    for j, size in enumerate(sizes):
        span = -(-size // _TERM_ALIGN) * _TERM_ALIGN
        if batches[-1] and used + span > budget:
            batches.append({})
            used = 0
        batches[-1][j] = (used, used + max(size, 16))
        used += span
    return batches


def _direct_sigmas(layout: DiffusionLayout, grid: LevelGrid, variance: float
                   ) -> list[Any] | None:
    """Per axis the sigma (texels) of the direct blur of a term of ``variance`` mm^2 on
    ``grid``'s level where :func:`_blur_job` runs that one (narrow: its one pass is
    cheaper), else None (the recursive blur): a float each on a level of one texel
    size, else one per step of the level's texel sizes (:class:`TexelSteps`)."""
    sigma_mm = _job_sigma_mm(layout, variance, grid.level)
    if grid.uniform:
        su, sv = (sg / t for sg, t in zip(sigma_mm, grid.typical, strict=True))
        return [su, sv] if prefers_direct(layout.device, su, sv) else None
    steps = grid.texel_steps()
    if steps is None:
        return None
    # per-texel sigma (level texels) on each axis's log2 grid; the widest at its smallest
    # texel sets the radius
    sigmas = [sg / 2.0 ** (q / QUANT_STEPS_PER_OCTAVE)
              for sg, q in zip(sigma_mm, (steps.u, steps.v), strict=True)]
    return sigmas if prefers_direct(layout.device, float(sigmas[0][0]),
                                    float(sigmas[1][0]), per_texel=True) else None


def _blur_job(layout: DiffusionLayout, grid: LevelGrid, src: Any, tmp: Any, dst: Any,
              variance: float, stats: BlurStats) -> None:
    """Enqueue the blur of one term (``variance`` mm^2) of one level's tile atlas
    (``src``) into ``dst``: sigma per axis less what the tile level and its B-spline read
    add; the direct kernel for narrow blurs (:func:`_direct_sigmas`: ``tmp`` unused),
    else the recursive one (per texel where the layout's texel sizes vary; ``dst`` may
    be ``src``)."""
    iir = layout.iir
    lh, lw = grid.shape
    direct = _direct_sigmas(layout, grid, variance)
    if direct is not None:
        if grid.uniform:
            direct_kernels(layout.device).blur(src, dst, lh, lw, *direct)
        else:
            steps = grid.texel_steps()
            assert steps is not None
            direct_kernels(layout.device).blur_per_texel(
                src, dst, lh, lw, fir_weight_table(direct[0]), fir_weight_table(direct[1]),
                steps.index_u, steps.index_v, grid.row_bands(*grid.texel_arrays()))
            note = (f"level {grid.level}: {steps.smaller} texel sizes below the "
                    f"{DIRECT_TEXEL_QUANTILE:g} quantile blurred as that size")
            if steps.smaller and note not in stats.skipped:
                stats.skipped.append(note)
        stats.passes += 1
        return
    sigma_mm = _job_sigma_mm(layout, variance, grid.level)
    if grid.uniform:
        su, sv = (sg / t for sg, t in zip(sigma_mm, grid.typical, strict=True))
        iir.blur(src, tmp, dst, lh, lw, iir.coefficients(su), iir.coefficients(sv))
    else:
        lo_u, hi_u, lo_v, hi_v, index_u, index_v = grid.index()
        coefs = [iir.coefficients(sg / 2.0 ** (np.arange(lo, hi + 1) / QUANT_STEPS_PER_OCTAVE))
                 for sg, lo, hi in ((sigma_mm[0], lo_u, hi_u), (sigma_mm[1], lo_v, hi_v))]
        qu, qv = grid.index_arrays()
        bands_u, bands_v = grid.row_bands(qu), grid.row_bands(qv)
        iir.blur(src, tmp, dst, lh, lw, coefs[0], coefs[1], index_u, index_v,
                 None if bands_u is None or bands_v is None else (bands_u, bands_v))
    stats.passes += 2


def _alone_into(layout: DiffusionLayout, grids: dict[int, LevelGrid],
                jobs: list[tuple[float, int]], batches: list[dict[int, tuple[int, int]]]
                ) -> dict[int, str]:
    """The jobs whose blurred term needs no room in the term buffer, and the work buffer
    it goes to instead: a job alone in its batch (a level-0 term fills the buffer alone)
    is added up before anything else is blurred, so one pass of the direct kernel
    writes it to ``tmp`` (free once the level's fill is done), the recursive blur of
    its level's last job over ``source`` (no later job reads it; where the device fills
    it, not the host). The demo face at texture 4096: its three level-0 terms then take
    no third 0.32 GB buffer beside ``tmp`` and ``source``."""
    last_at_level = {k: j for j, (_, k) in enumerate(jobs)}  # jobs come level by level
    into: dict[int, str] = {}
    for batch in batches:
        if len(batch) != 1:
            continue
        (j,) = batch
        variance, k = jobs[j]
        if variance == 0.0:
            continue
        if _direct_sigmas(layout, grids[k], variance) is not None:
            into[j] = "tmp"
        elif last_at_level[k] == j and grids[k].seam_buffers() is not None:
            into[j] = "source"
    return into


def _term_buffer(layout: DiffusionLayout, grids: dict[int, LevelGrid],
                 jobs: list[tuple[float, int]], batches: list[dict[int, tuple[int, int]]],
                 into: dict[int, str], tmp: Any, tmp_bytes: int) -> tuple[Any, int]:
    """(buffer, byte offset) of the blurred terms that go to no work buffer
    (:func:`_alone_into`): the room in ``tmp`` (``tmp_bytes``) past what the fills and
    recursive blurs of those terms' levels use there, where they fit (a term there is
    added up before a later fill or blur of a larger level writes over it: the queue is
    in order), else the layout's own from 0 (OpenCL makes no sub-buffer of a
    sub-buffer: the terms' are made from the buffer at the offset). The demo face at
    texture 4096: its six coarse terms (0.19 GB) beside level 1's 0.09 GB in tmp's 0.32
    GB."""
    rest = [j for batch in batches for j in batch if j not in into]
    need = max((end for batch in batches for j, (_, end) in batch.items() if j not in into),
               default=16)
    used = max((grids[jobs[j][1]].shape[0] * grids[jobs[j][1]].shape[1] * 16
                for j in rest if jobs[j][0] > 0), default=0)
    at = -(-used // _TERM_ALIGN) * _TERM_ALIGN
    if at + need <= tmp_bytes:
        return tmp, at
    return layout.buffer("terms", need), 0


def diffuse(
    irradiance: NDArray[Any],
    mm_per_texel_u: NDArray[Any],
    mm_per_texel_v: NDArray[Any],
    coverage: NDArray[Any],
    variances_mm2: NDArray[Any],
    term_weights: NDArray[Any],
    region_weights: NDArray[Any] | None = None,
    charts: ChartLayout | None = None,
    device: Device | None = None,
) -> tuple[NDArray[np.float32], BlurStats]:
    """Diffused irradiance sum_i w_i(texel) (G(v_i) * E) for RGB irradiance (H, W, 3).

    ``variances_mm2`` (K,) ascending, shared by all regions; ``term_weights`` (R, K, 3)
    each region's weight per term and channel; ``region_weights`` (H, W, R) how much of
    each region a texel is (None: one region everywhere), read as half floats
    (:data:`~.texture_maps.REGION_WEIGHT_DTYPE`) scaled to sum to 1 at each texel
    (:func:`unit_region_weights`). A texel's weights are the
    region-blended ones, so borders between regions blend smoothly. ``charts``: the UV
    layout's charts and the surface across their seams (:class:`ChartLayout`).
    ``device``: where it runs (None: :func:`~..device.choice.or_default`). The
    layout is made for this call; :class:`DiffusionLayout` and :func:`diffuse_prepared`
    keep it.
    """
    layout = DiffusionLayout(or_default(device), mm_per_texel_u, mm_per_texel_v, coverage,
                             region_weights, charts)
    return diffuse_prepared(layout, irradiance, variances_mm2, term_weights)


def diffuse_prepared(
    layout: DiffusionLayout,
    irradiance: NDArray[Any],
    variances_mm2: NDArray[Any],
    term_weights: NDArray[Any],
) -> tuple[NDArray[np.float32], BlurStats]:
    """:func:`diffuse` on a prepared layout.

    Each term is blurred from the irradiance (:func:`_blur_job`: the direct kernel when
    narrow, else the recursive one), with per-texel sigma from the stretch maps, as a
    normalised convolution of (E cov, cov) (chart borders neither darken nor leak), on
    the coarsest pyramid level where it is still LEVEL_MIN_SIGMA_TEXELS wide (the
    variance the tent splat and the B-spline read add is taken off the blur). Every level is an
    atlas of chart tiles whose margins hold the surface across the charts' seams, as
    wide as the level's widest blur reaches (:mod:`.chart_tiles`), so light crosses
    seams. The blurred terms are kept TERM_BUFFER_TEXTURES at a time (at most
    TERM_BUFFER_MAX_BYTES) and added up in one pass per batch, each texel reading its
    own chart's tiles. On a CPU device the
    irradiance is read and the result written where they are, in host memory. Terms
    with zero weight on every texel are skipped; one narrower than a quarter texel
    everywhere is the unblurred irradiance.
    """
    h, w = layout.height, layout.width
    e = _check_irradiance(irradiance)
    if e.shape[:2] != (h, w):
        raise InputError(f"irradiance must be ({h}, {w}, 3) like its layout, got {e.shape}")
    v, tw, used, stats = _check_terms((h, w), variances_mm2, term_weights,
                                      layout.region_shape, layout.present)
    if not layout.any_covered or not used.any():
        if not layout.any_covered:
            stats.skipped.append("diffusion: no covered texel")
        return np.zeros((h, w, 3), np.float32), stats
    iir, device = layout.iir, layout.device

    jobs, job_weights = _blur_jobs(layout, v, tw, used, stats)
    # each level's tile atlas, its margin as wide as its widest blur reaches, filled
    # with this irradiance (host memory, read in place on a CPU device)
    grids = {k: layout.grid(k, margin)
             for k, margin in sorted(layout.level_margins(v[used]).items())}
    e_buf = host_buffer(device, e)
    stats.tile_texels = {k: g.shape[0] * g.shape[1] for k, g in grids.items()}
    nbytes = max((g.shape[0] * g.shape[1] * 16 for g in grids.values()), default=16)
    tmp = layout.buffer("tmp", nbytes)
    # one level's atlas at a time, filled before its first job: the jobs come level by
    # level (a wider term never on a finer level), and the in-order queue fills the
    # next level only after this one's blurs (every level's at once held 0.47 GB at
    # texture 4096, one 0.32 GB)
    source_buf = layout.buffer("source", nbytes)
    sizes = [0 if var == 0.0 else grids[k].shape[0] * grids[k].shape[1] * 16
             for var, k in jobs]
    batches = _term_batches(sizes, min(TERM_BUFFER_TEXTURES * max(nbytes, h * w * 16),
                                       max(TERM_BUFFER_MAX_BYTES, nbytes)))
    tw4 = np.zeros((len(jobs), tw.shape[0], 4), np.float32)
    tw4[..., :3] = np.stack(job_weights)
    mf = cl.mem_flags
    tw_buf = cl.Buffer(iir.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=tw4)
    levels = sorted(grids)
    shift = np.concatenate([grids[k].tiles.shift for k in levels] or
                           [np.zeros((1, 2), np.float32)]).astype(np.float32)
    shift_buf = cl.Buffer(iir.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=shift)
    shift_at = {k: n * layout.charts.n_charts for n, k in enumerate(levels)}
    into = _alone_into(layout, grids, jobs, batches)
    terms, terms_at = _term_buffer(layout, grids, jobs, batches, into, tmp, nbytes)
    out = np.empty((h, w, 3), np.float32)
    out_buf = host_output(device, out)  # every batch adds its terms there
    blurred_texels = _blur_and_add(layout, grids, jobs, batches, into, terms, terms_at,
                                   e_buf, tmp, source_buf, shift_at, tw_buf, shift_buf,
                                   out_buf, stats)
    read_output(device, out_buf, out)
    out_buf.release()  # the array is the host's alone before it is written here
    # a recursive blur rings a little below zero beside a hard edge (-1.4e-4 of the
    # lit level on the demo face); light is not negative
    np.maximum(out, 0.0, out=out)
    stats.full_blurs = blurred_texels / (h * w)
    return out, stats


def diffuse_on_surface(layout: DiffusionLayout, irradiance: NDArray[Any],
                       variances_mm2: NDArray[Any], term_weights: NDArray[Any],
                       texels: bool = False
                       ) -> tuple[NDArray[np.float32], SurfaceLight | None,
                                  NDArray[np.float32] | None, BlurStats]:
    """:func:`diffuse_prepared` of the terms the layout blurs in its tiles, and the
    light of those it sums on the surface (:meth:`DiffusionLayout.surface_levels`,
    :mod:`.surface_terms`; None if none), which the texture leaves out. With ``texels``
    (and a layout prepared with ``texels_on_surface``) also the texture with the
    surface's light added at its texels (None where there is none)."""
    v = np.asarray(variances_mm2, np.float64).ravel()
    tw = np.asarray(term_weights, np.float32)
    levels = layout.surface_levels(v)
    wide = [k for k, lv in enumerate(levels) if lv is not None]
    narrow = [k for k, lv in enumerate(levels) if lv is None]
    surface = None
    if wide:
        assert layout.surface is not None
        # each block size reads the irradiance blurred by (h / 2)^2 in the tiles: a hard
        # edge on a block's border aliases otherwise
        pre = {}
        for lv in sorted({int(levels[k] or 0) for k in wide}):
            vs = layout.pre_variance(lv)
            pre[lv] = (vs, diffuse_prepared(layout, irradiance, np.array([vs]),
                                            np.ones((tw.shape[0], 1, 3), np.float32))[0])
        surface = surface_light(layout.device, layout.surface, _check_irradiance(irradiance),
                                v[wide], [int(levels[k] or 0) for k in wide], tw[:, wide],
                                pre)
    if narrow:
        out, stats = diffuse_prepared(layout, irradiance, v[narrow], tw[:, narrow])
    else:
        out, stats = np.zeros((layout.height, layout.width, 3), np.float32), BlurStats()
    stats.passes += len(wide)
    stats.surface_terms = [(float(v[k]), int(levels[k] or 0)) for k in wide]
    full = None
    if texels and surface is not None:
        assert layout.surface is not None
        full = out + surface.at_texels(layout.device, layout.surface, out.shape)
    return out, surface, full, stats


def _blur_jobs(layout: DiffusionLayout, v: NDArray[Any], tw: NDArray[Any],
               used: NDArray[Any], stats: BlurStats
               ) -> tuple[list[tuple[float, int]], list[NDArray[np.float32]]]:
    """One job per distinct (variance, level) and its weights: equal variances share a
    blur, and their weights add (accumulation is linear in them); sub-texel terms share
    the unblurred irradiance (variance 0)."""
    jobs: list[tuple[float, int]] = []
    job_weights: list[NDArray[np.float32]] = []
    for i in range(v.size):
        if not used[i]:
            stats.skipped.append(f"term {i} (v = {v[i]:.4g} mm^2): zero weight everywhere")
            continue
        job = (float(v[i]), layout.term_level(float(v[i])))
        if math.sqrt(v[i]) / layout.finest_mm < TABLE_MIN_SIGMA:
            stats.skipped.append(f"term {i} (v = {v[i]:.4g} mm^2): narrower than a quarter "
                                 "texel, the unblurred irradiance")
            job = (0.0, 0)
        if job in jobs:
            if job[0] > 0:
                stats.skipped.append(f"term {i}: same variance as term {i - 1}, pass shared")
            job_weights[jobs.index(job)] += tw[:, i]
        else:
            jobs.append(job)
            job_weights.append(tw[:, i].copy())
    return jobs, job_weights


def _blur_and_add(layout: DiffusionLayout, grids: dict[int, Any], jobs: list[tuple[float, int]],
                  batches: list[dict[int, tuple[int, int]]], into: dict[int, str], terms: Any,
                  terms_at: int, e_buf: Any, tmp: Any, source_buf: Any,
                  shift_at: dict[int, int], tw_buf: Any, shift_buf: Any, out_buf: Any,
                  stats: BlurStats) -> float:
    """Blur every batch's jobs (filling each level's atlas before its first) and add the
    batch's terms into ``out_buf``; the texels blurred, for the stats."""
    h, w = layout.height, layout.width
    queue, ctx, mf = layout.iir.queue, layout.iir.ctx, cl.mem_flags
    kernels = pyramid_kernels(layout.device, layout.n_regions, layout.by_triangle)
    source, source_level = None, -1
    blurred_texels = 0.0
    for b, batch in enumerate(batches):
        table = np.zeros((len(batch), 6), np.int32)
        batch_terms = terms
        for n, (j, (start, end)) in enumerate(batch.items()):
            variance, k = jobs[j]
            if variance == 0.0:
                table[n] = (0, j, 1, 1, -1, 0)
                continue
            grid = grids[k]
            lh, lw = grid.shape
            table[n] = ((0 if j in into else terms_at + start) // 16, j, lw, lh, k,
                        shift_at[k])
            if k != source_level:
                source, source_level = _fill_level(layout, grid, e_buf, tmp, source_buf), k
                _release_level(queue, grid)  # the fill is done with the splat and reads
            work = {"tmp": tmp, "source": source}[into[j]] if j in into else \
                terms.get_sub_region(terms_at + start, end - start)
            _blur_job(layout, grid, source, tmp, work, variance, stats)
            _release_level(queue, grid)  # the next job may read other steps
            if j in into:
                batch_terms = work
            stats.levels.append(k)
            blurred_texels += lh * lw
        kernels["accumulate_terms"](
            queue, (w, h), None, batch_terms, e_buf,
            cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=table.reshape(-1)),
            out_buf, layout.cover_buf, *layout.region_args, tw_buf, layout.chart_buf, shift_buf,
            np.int32(w), np.int32(h), np.int32(len(batch)), np.int32(b > 0))
    return blurred_texels
