"""The seam layout's tiles kept on disk (skinpipe.render.diffusion.tile_store): read back they give
the diffusion the tiles made in the process gave, bit for bit; a damaged file or a folder
that cannot be written costs a remake, a full folder its least recently used layouts,
never a render."""

from __future__ import annotations

import json
import mmap
import os
import re
import threading
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from skinpipe.cli import main
from skinpipe.profile.reference_data import DEON_2007_SKIN
from skinpipe.render.cache import MARKER, CacheWarning
from skinpipe.render.diffusion import tile_store
from skinpipe.render.diffusion.diffuse import diffuse_prepared
from skinpipe.render.diffusion.layout import LEVEL_ARRAYS, DiffusionLayout, LevelGrid
from skinpipe.render.diffusion.tile_store import TileStore
from skinpipe.render.options import RenderOptions
from skinpipe.render.renderer import Renderer
from skinpipe.usd.io import open_stage_guarded

from ..opencl_device import DEVICE
from ..test_renderer import SMALL
from .test_chart_tiles import _layout

SIZE = 256
HANG_S = 600.0
"""How long a test waits for another thread before it gives up: a guard against a hang,
not a time limit (a loaded machine takes what it takes)."""


@pytest.fixture(scope="module")
def patch_layout():
    """The two-chart patch's maps and charts at texture 256 (a seam with real margins)."""
    return _layout(SIZE)


def _diffused(patch_layout, store: TileStore | None) -> tuple[np.ndarray, DiffusionLayout]:
    maps, charts = patch_layout
    layout = DiffusionLayout(DEVICE, maps.mm_per_texel_u, maps.mm_per_texel_v, maps.coverage,
                             None, charts, store)
    rng = np.random.default_rng(3)
    light = (rng.random((SIZE, SIZE, 3)) * (maps.coverage > 0)[..., None]).astype(np.float32)
    out, _ = diffuse_prepared(layout, light, DEON_2007_SKIN.variances_mm2,
                              DEON_2007_SKIN.weights)
    if store is not None:
        store.flush()
    return out, layout


def test_stored_tiles_read_back_give_the_same_diffusion(patch_layout, tmp_path: Path) -> None:
    """Made and saved by one layout, read by a second (another process's): the same
    tiles, arrays and reads, the same blur indices and steps derived from the texel
    sizes (stored in their place), and the same diffused light bit for bit."""
    reference, made = _diffused(patch_layout, None)
    first = TileStore(tmp_path, "patch", DEVICE)
    out1, _ = _diffused(patch_layout, first)
    second = TileStore(tmp_path, "patch", DEVICE)
    out2, layout2 = _diffused(patch_layout, second)
    assert first.saved and not first.loaded
    assert sorted(second.loaded) == sorted(first.saved) and not second.saved
    np.testing.assert_array_equal(out1, reference)
    np.testing.assert_array_equal(out2, reference)
    for key, grid in made._grids.items():
        a, b = grid.tiles, layout2._grids[key].tiles
        assert a.shape == b.shape
        for name in ("shift", "owner", "count"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        for name in ("rows", "xy"):
            np.testing.assert_array_equal(getattr(a.reads, name), getattr(b.reads, name))
        made_derived, read_derived = grid.derived(), layout2._grids[key].derived()
        assert set(made_derived) == set(read_derived) == set(LEVEL_ARRAYS)
        for name in LEVEL_ARRAYS:
            np.testing.assert_array_equal(made_derived[name], read_derived[name],
                                          err_msg=name)
            assert made_derived[name].dtype == read_derived[name].dtype, name


def test_a_wider_stored_margin_serves_a_narrower_one(patch_layout, tmp_path: Path) -> None:
    _, layout = _diffused(patch_layout, None)
    store = TileStore(tmp_path, "patch", DEVICE)
    level, margin = next(iter(layout._grids))
    # LevelGrid dropped the texel sizes: the store takes tiles straight from tile_level
    from skinpipe.render.diffusion.chart_tiles import tile_level

    maps, charts = patch_layout
    tiles = tile_level(charts.chart, charts.n_charts, maps.mm_per_texel_u,
                       maps.mm_per_texel_v, level, margin + 2, charts.geometry,
                       charts.coverage)
    store.save(tiles, LevelGrid(DEVICE, tiles).derived())
    store.flush()
    assert store.load(level, margin, partial(LevelGrid, DEVICE)).tiles.margin == margin + 2
    assert store.load(level, margin + 3, partial(LevelGrid, DEVICE)) is None
    assert store.load(level + 1, margin, partial(LevelGrid, DEVICE)) is None


def test_a_damaged_file_is_removed_and_the_tiles_made_again(patch_layout,
                                                            tmp_path: Path) -> None:
    reference, _ = _diffused(patch_layout, TileStore(tmp_path, "patch", DEVICE))
    files = sorted(TileStore(tmp_path, "patch", DEVICE).entry.glob("*.npz"))
    damaged = files[0]
    data = bytearray(damaged.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte inside an array: the zip's CRC
    damaged.write_bytes(bytes(data))
    files[1].write_bytes(files[1].read_bytes()[:1000])  # a truncated one
    store = TileStore(tmp_path, "patch", DEVICE)
    out, _ = _diffused(patch_layout, store)
    np.testing.assert_array_equal(out, reference)
    assert sum("cannot be used" in n for n in store.notes) == 2, store.notes
    assert len(store.saved) == 2  # both made again and written again


def test_an_old_format_or_reads_past_their_end_are_made_again(patch_layout,
                                                                 tmp_path: Path) -> None:
    """Files whose zip reads back but whose reads do not hold together are removed and
    their tiles made again: one in the sparse-matrix format the store used before
    (indptr, indices, data), one whose texel rows would read past the reads' end (the
    device kernel would read out of bounds)."""
    reference, _ = _diffused(patch_layout, TileStore(tmp_path, "patch", DEVICE))
    files = sorted(TileStore(tmp_path, "patch", DEVICE).entry.glob("*.npz"))
    assert len(files) >= 2
    for path, how in zip(files, ("old format", "past the end"), strict=False):
        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files}
        rows = arrays.pop("rows")
        if how == "old format":
            arrays.pop("xy")
            arrays |= {"indptr": rows, "indices": np.zeros(int(rows[-1]), np.int32),
                       "data": np.zeros(int(rows[-1]), np.float32)}
        else:
            rows[1] = rows[-1] + 1000  # a texel's reads beyond the last read
            arrays["rows"] = rows
        with path.open("wb") as f:
            np.savez(f, **arrays)
    store = TileStore(tmp_path, "patch", DEVICE)
    out, _ = _diffused(patch_layout, store)
    np.testing.assert_array_equal(out, reference)
    assert sum("cannot be used" in n for n in store.notes) == 2, store.notes
    assert len(store.saved) == 2


def test_a_folder_that_cannot_be_written_costs_only_the_store(patch_layout,
                                                               tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the store's folder should be")
    with pytest.warns(CacheWarning, match="not-a-folder cannot be used"):
        store = TileStore(blocker, "patch", DEVICE)
    reference, _ = _diffused(patch_layout, None)
    out, _ = _diffused(patch_layout, store)
    np.testing.assert_array_equal(out, reference)
    assert not store.saved and not store.loaded
    assert blocker.read_text().startswith("a file")  # nothing of the user's touched


def test_the_least_recently_used_layouts_go_past_the_limit(patch_layout,
                                                           tmp_path: Path) -> None:
    """Another layout the store made goes (with a killed writer's temporary file in it);
    the user's own folders beside it stay, one named like a layout among them."""
    old = tmp_path / f"layout-{'0' * 32}"
    old.mkdir()
    (old / MARKER).touch()
    (old / "L0_M5.npz").write_bytes(b"x" * 5000)
    tmp = old / ".L0_M5.npz.abc.tmp"
    tmp.write_bytes(b"x" * 10)
    os.utime(old, (1.0, 1.0))  # long unused
    scans = tmp_path / "my-scans"
    scans.mkdir()
    (scans / "head.ply").write_bytes(b"y" * 5000)
    lookalike = tmp_path / f"layout-{'2' * 32}"  # no marker: the store did not make it
    lookalike.mkdir()
    (lookalike / "L0_M5.npz").write_bytes(b"z" * 5000)
    os.utime(lookalike, (1.0, 1.0))
    store = TileStore(tmp_path, "patch", DEVICE, limit=1)  # smaller than anything: evict all else
    _diffused(patch_layout, store)
    assert not old.exists()
    assert (scans / "head.ply").is_file() and (lookalike / "L0_M5.npz").is_file()
    assert store.entry.is_dir() and any(store.entry.glob("*.npz"))  # its own entry stays
    assert any("least recently used" in n for n in store.notes)


def test_the_key_holds_the_layout_and_the_code(tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    a, b = TileStore(tmp_path, "mesh a", DEVICE), TileStore(tmp_path, "mesh b", DEVICE)
    assert a.key != b.key
    monkeypatch.setattr(tile_store, "code_fingerprint", lambda: "another build")
    assert TileStore(tmp_path, "mesh a", DEVICE).key != a.key


def test_a_second_renderer_reads_the_first_ones_tiles(lit_patch: Path,
                                                      tmp_path: Path) -> None:
    from dataclasses import replace

    options = replace(SMALL, layout_cache=str(tmp_path / "layouts"))
    images = []
    for expect in ("saved", "loaded"):
        renderer = Renderer(open_stage_guarded(lit_patch), options)
        frame, log = renderer.render()
        renderer.close()
        images.append(frame)
        assert log.measures["tile_store"][expect], log.measures["tile_store"]
    for aov, image in images[0].items():
        np.testing.assert_array_equal(images[1][aov], image, err_msg=aov)


def test_the_cli_keeps_the_tiles_where_asked_or_nowhere(lit_patch: Path,
                                                        tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch
                                                        ) -> None:
    args = ["render", str(lit_patch), "--resolution", "32x32", "--texture-size", "64",
            "--light-samples", "1"]
    monkeypatch.setenv("SKINPIPE_LAYOUT_CACHE", str(tmp_path / "env"))
    assert main([*args, "-o", str(tmp_path / "a")]) == 0
    assert any((tmp_path / "env").glob("*/*.npz"))
    assert main([*args, "-o", str(tmp_path / "b"), "--layout-cache", "off"]) == 0
    doc = json.loads((tmp_path / "b" / "render.json").read_text())
    assert "tile_store" not in doc["frames"][0]["measures"]
    monkeypatch.setenv("SKINPIPE_LAYOUT_CACHE", "off")
    assert main([*args, "-o", str(tmp_path / "c")]) == 0
    assert "tile_store" not in json.loads(
        (tmp_path / "c" / "render.json").read_text())["frames"][0]["measures"]
    assert main([*args, "-o", str(tmp_path / "d"), "--layout-cache", str(tmp_path / "x")]) == 0
    assert any((tmp_path / "x").glob("*/*.npz"))


def test_a_bad_size_limit_is_named(lit_patch: Path, tmp_path: Path,
                                   monkeypatch: pytest.MonkeyPatch,
                                   capsys: pytest.CaptureFixture[str]) -> None:
    """A bad limit stops the command before it renders (exit 2, the variable named, no
    output), not on the layout's thread after the shadow rays; with the store off it
    does not matter."""
    from skinpipe.errors import EXIT_BAD_INPUT, InputError

    monkeypatch.setenv(tile_store.LIMIT_ENV, "lots")
    with pytest.raises(InputError, match=r"SKINPIPE_LAYOUT_CACHE_GB.*lots"):
        tile_store.limit_bytes()
    args = ["render", str(lit_patch), "--resolution", "32x32", "--texture-size", "64",
            "--light-samples", "1"]
    from skinpipe.render import renderer

    def no_render(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("rendered before the limit was checked")

    with monkeypatch.context() as m:
        m.setattr(renderer.Renderer, "render", no_render)
        assert main([*args, "-o", str(tmp_path / "bad")]) == EXIT_BAD_INPUT
    assert "SKINPIPE_LAYOUT_CACHE_GB" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
    assert main([*args, "-o", str(tmp_path / "off"), "--layout-cache", "off"]) == 0
    assert RenderOptions().layout_cache is None  # the library writes nothing unasked


def test_prepare_makes_the_blurs_device_buffers_beside_the_irradiance(patch_layout) -> None:
    """The layout's task (beside the irradiance) makes every buffer the diffusion's fills
    and blurs read, so the diffusion after the irradiance does not; the light is the same
    as a layout that makes them on first use."""
    maps, charts = patch_layout
    layout = DiffusionLayout(DEVICE, maps.mm_per_texel_u, maps.mm_per_texel_v, maps.coverage,
                             None, charts)
    layout.prepare(DEON_2007_SKIN.variances_mm2)
    assert layout._grids
    for grid in layout._grids.values():
        assert grid._splat is not None and grid._seams is not None
        if not grid.uniform:
            assert grid._index is not None and grid._texel is not False
    reference, _ = _diffused(patch_layout, None)
    rng = np.random.default_rng(3)
    light = (rng.random((SIZE, SIZE, 3)) * (maps.coverage > 0)[..., None]).astype(np.float32)
    out, _ = diffuse_prepared(layout, light, DEON_2007_SKIN.variances_mm2,
                              DEON_2007_SKIN.weights)
    np.testing.assert_array_equal(out, reference)


def test_two_writers_of_one_layout_leave_one_whole_file(patch_layout, tmp_path: Path) -> None:
    """Farm nodes rendering the same asset at once write the same key: each renames a
    whole file into place, the last one stays, nothing temporary is left behind."""
    from skinpipe.render.diffusion.chart_tiles import tile_level

    maps, charts = patch_layout
    tiles = tile_level(charts.chart, charts.n_charts, maps.mm_per_texel_u,
                       maps.mm_per_texel_v, 0, 6, charts.geometry, charts.coverage)
    derived = LevelGrid(DEVICE, tiles).derived()
    stores = [TileStore(tmp_path, "patch", DEVICE) for _ in range(4)]
    for store in stores:
        store.save(tiles, derived)  # each on its own writer thread, all at once
    for store in stores:
        store.flush()
        assert store.saved == [(0, 6)] and not store.notes
    entry = stores[0].entry
    assert [p.name for p in entry.iterdir() if p.name != MARKER] == ["L0_M6.npz"]
    umask = os.umask(0)
    os.umask(umask)
    # readable as the umask allows (mkstemp's 0600 would shut out a farm's other users)
    assert (entry / "L0_M6.npz").stat().st_mode & 0o777 == 0o666 & ~umask
    back = TileStore(tmp_path, "patch", DEVICE).load(0, 6, partial(LevelGrid, DEVICE)).tiles
    np.testing.assert_array_equal(back.owner, tiles.owner)
    np.testing.assert_array_equal(back.reads.rows, tiles.reads.rows)
    np.testing.assert_array_equal(back.reads.xy, tiles.reads.xy)


@pytest.mark.parametrize("array", [
    np.arange(10, dtype=np.int32), np.zeros((3, 4), np.float32), np.zeros((0, 2), np.uint16),
    np.full((), 3.5), np.arange(12.0).reshape(3, 4).T, np.arange(6, dtype=">i4")],
    ids=["int32", "2d", "empty", "0d", "fortran", "big-endian"])
def test_write_npy_writes_numpys_bytes(array: np.ndarray) -> None:
    """write_npy gives the bytes numpy's own np.lib.format.write_array gives, for C- and
    Fortran-ordered, empty, 0-d and big-endian arrays."""
    import io

    ours, numpys = io.BytesIO(), io.BytesIO()
    tile_store.write_npy(ours, array)
    np.lib.format.write_array(numpys, array, allow_pickle=False)
    assert ours.getvalue() == numpys.getvalue()


def test_aligned_npz_is_an_npz_whose_arrays_map_in_place(tmp_path: Path) -> None:
    """write_aligned_npz: numpy's np.load and zipfile's own CRC check read it; each
    member's array data starts at a multiple of ALIGN bytes in the file (from the zip's
    local headers and numpy's .npy header); mapped_npz gives the same arrays as views
    of the mapping (read-only: dropping its pages must not lose a write), np.savez's
    unaligned file the same arrays copied, and a flipped byte a ValueError naming its member."""
    import struct
    import zipfile

    rng = np.random.default_rng(1)
    arrays = {"xy": rng.random((1001, 2)).astype(np.float32),
              "rows": np.arange(13, dtype=np.int32), "none": np.zeros((0, 2), np.float32),
              "shape": np.array([4, 5], np.int64), "f": np.asfortranarray(rng.random((3, 7)))}
    path = tmp_path / "a.npz"
    with path.open("wb") as f:
        tile_store.write_aligned_npz(f, arrays)
    with np.load(path) as z:
        for name, want in arrays.items():
            np.testing.assert_array_equal(z[name], want)
            assert z[name].dtype == want.dtype
    with zipfile.ZipFile(path) as z, path.open("rb") as f:
        assert z.testzip() is None
        for info in z.infolist():
            f.seek(info.header_offset + 26)
            name_len, extra_len = struct.unpack("<HH", f.read(4))
            f.seek(info.header_offset + 30 + name_len + extra_len)
            np.lib.format.read_magic(f)
            np.lib.format.read_array_header_1_0(f)
            assert f.tell() % tile_store.ALIGN == 0, info.filename
    mapped = tile_store.mapped_npz(path, tuple(arrays))
    for name, want in arrays.items():
        np.testing.assert_array_equal(mapped[name], want)
        assert type(mapped[name]) is np.ndarray and mapped[name].flags.aligned
        assert mapped[name].ctypes.data % tile_store.ALIGN == 0 or not mapped[name].size
    with pytest.raises(ValueError, match="read-only"):
        mapped["xy"][0, 0] = -1.0
    plain = tmp_path / "plain.npz"
    np.savez(plain, **arrays)
    for name, got in tile_store.mapped_npz(plain, tuple(arrays)).items():
        np.testing.assert_array_equal(got, arrays[name])
        assert got.flags.aligned
    data = bytearray(path.read_bytes())
    data[data.find(arrays["xy"].tobytes()[:64]) + 4000] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="xy: its CRC-32 differs"):
        tile_store.mapped_npz(path, tuple(arrays))


def test_stored_blur_indices_past_their_steps_are_refused(patch_layout,
                                                           tmp_path: Path) -> None:
    """A level's blur indices, stored with its tiles in place of their texel sizes, are
    read by the device as they are: LevelGrid refuses indices past their steps (a
    kernel would read beyond its table) or of another shape, and the store removes a
    file whose arrays are refused (the tiles are made again)."""
    from skinpipe.render.diffusion.chart_tiles import tile_level

    maps, charts = patch_layout
    tiles = tile_level(charts.chart, charts.n_charts, maps.mm_per_texel_u,
                       maps.mm_per_texel_v, 0, 6, charts.geometry, charts.coverage)
    derived = LevelGrid(DEVICE, tiles).derived()
    h, w = tiles.shape
    # the flat patch has one texel size: a varying level's arrays, written out here
    varying = {**derived, "uniform": np.zeros(1, np.int8),
               "index_bounds": np.array([10, 13, 20, 21], np.int64),
               "index_u": np.zeros((h, w), np.int32), "index_v": np.ones((w, h), np.int32),
               "steps_u": np.arange(10, 14, dtype=np.int32),
               "steps_v": np.arange(20, 22, dtype=np.int32),
               "texel_u": np.full((h, w), 3, np.uint16), "texel_v": np.ones((h, w), np.uint16),
               "smaller": np.array([7], np.int64)}
    grid = LevelGrid(DEVICE, tiles, varying)
    assert not grid.uniform and grid.index()[:4] == (10, 13, 20, 21)
    assert grid.texel_steps().smaller == 7
    for name, bad in (("index_u", np.full((h, w), 4, np.int32)),
                      ("index_v", np.zeros((h, w), np.int32) if h != w else
                       np.zeros((h, w + 1), np.int32)),
                      ("texel_u", np.full((h, w), 4, np.uint16)),
                      ("texel_v", np.ones((h, w), np.int32))):
        with pytest.raises(ValueError, match="level grid"):
            LevelGrid(DEVICE, tiles, {**varying, name: bad})
    store = TileStore(tmp_path, "patch", DEVICE)
    store.save(tiles, derived)
    store.flush()

    def refuse(*_: object) -> None:
        raise ValueError("refused")

    assert store.load(0, 6, refuse) is None
    assert store.stored() == [] and any("cannot be used (refused)" in n
                                        for n in store.notes)


def _resident_bytes(path: Path) -> int:
    """Resident bytes of this process's mappings of ``path`` (/proc/self/smaps)."""
    total, inside = 0, False
    for line in Path("/proc/self/smaps").read_text().splitlines():
        if re.match(r"^[0-9a-f]+-[0-9a-f]+ ", line):
            inside = line.rstrip().endswith(str(path))
        elif inside and line.startswith("Rss:"):
            total += int(line.split()[1]) * 1024
    return total


@pytest.mark.skipif(not Path("/proc/self/smaps").exists() or
                    not hasattr(mmap, "MADV_DONTNEED"), reason="Linux's smaps and madvise")
def test_dropped_pages_leave_memory_not_values(tmp_path: Path) -> None:
    """mapped_npz's CRC reads the file, not the mapping: no page of it is resident until
    read; drop_resident_pages takes the read pages out of the process's memory (smaps'
    Rss of the file) and the arrays read the same after it. Arrays of other memory
    (numpy's own, an anonymous mapping as device_buffer's) keep their values: dropping
    an anonymous page would zero it."""
    rng = np.random.default_rng(3)
    arrays = {"big": rng.random(2 << 20).astype(np.float32), "small": np.arange(7)}
    path = tmp_path / "t.npz"
    with path.open("wb") as f:
        tile_store.write_aligned_npz(f, arrays)
    mapped = tile_store.mapped_npz(path)
    assert _resident_bytes(path) < 1 << 20
    assert float(mapped["big"].sum(dtype=np.float64)) == pytest.approx(
        float(arrays["big"].sum(dtype=np.float64)))
    assert _resident_bytes(path) >= arrays["big"].nbytes
    tile_store.drop_resident_pages([mapped["small"]])  # its own pages, not big's
    assert _resident_bytes(path) >= arrays["big"].nbytes
    tile_store.drop_resident_pages([mapped["big"][::2], mapped["small"]])
    assert _resident_bytes(path) < 1 << 20
    np.testing.assert_array_equal(mapped["big"], arrays["big"])
    np.testing.assert_array_equal(mapped["small"], arrays["small"])
    anon = mmap.mmap(-1, 1 << 16)
    held = np.frombuffer(anon, np.uint8)
    held[:] = 7
    own = np.full(1 << 16, 5, np.uint8)
    tile_store.drop_resident_pages([held, own])
    assert (held == 7).all() and (own == 5).all()


@pytest.mark.skipif(not Path("/proc/self/smaps").exists() or
                    not hasattr(mmap, "MADV_DONTNEED"), reason="Linux's smaps and madvise")
def test_checks_of_mapped_arrays_read_them_a_chunk_at_a_time(tmp_path: Path,
                                                            monkeypatch: pytest.MonkeyPatch
                                                            ) -> None:
    """extremes and nondecreasing give numpy's answers over chunks (a chunk's edge
    included: a decrease across it is found) and leave at most a chunk of a mapped
    array resident (reading them whole left all 20 MB); other arrays are read as they
    are."""
    monkeypatch.setattr(tile_store, "CHECK_CHUNK", 1 << 16)
    rng = np.random.default_rng(5)
    rows = np.cumsum(rng.integers(0, 3, 3 << 20)).astype(np.int32)
    index = rng.integers(-7, 900, (1500, 1300)).astype(np.int32)
    path = tmp_path / "c.npz"
    with path.open("wb") as f:
        tile_store.write_aligned_npz(f, {"rows": rows, "index": index})
    mapped = tile_store.mapped_npz(path)
    assert tile_store.extremes(mapped["index"]) == (index.min(), index.max())
    assert tile_store.nondecreasing(mapped["rows"])
    # a chunk, and what the kernel maps around a read beyond the arrays' own pages (its
    # page cache's large folios: up to 2 MiB), not the arrays' 20 MB
    assert _resident_bytes(path) < (rows.nbytes + index.nbytes) // 4
    for at in (1 << 16, (1 << 16) - 1, 5, rows.size - 1):  # at, beside a chunk's edge
        bad = rows.copy()
        bad[at] = bad[at - 1] - 1
        assert not tile_store.nondecreasing(bad), at
    assert tile_store.extremes(np.array([[3.5, -1.0]])) == (-1.0, 3.5)
    assert tile_store.nondecreasing(np.arange(3)) and tile_store.nondecreasing(np.zeros(1))


def test_stored_tiles_read_a_band_at_a_time_give_the_same_diffusion(
        patch_layout, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The kernels that read a stored level's mapped arrays (the fill's splat and reads
    across the seams, the recursive and the direct per-texel blurs) run a band of rows at
    a time, each band's pages let go after it: the same diffused light bit for bit as the
    tiles made in the process."""
    import skinpipe.render.diffusion.layout as layout_module

    reference, _ = _diffused(patch_layout, None)
    _diffused(patch_layout, TileStore(tmp_path, "patch", DEVICE))  # made and saved
    dropped: list[int] = []
    drop = layout_module.drop_resident_pages

    def counted(arrays: list[np.ndarray]) -> None:
        dropped.append(len(arrays))
        drop(arrays)

    monkeypatch.setattr(layout_module, "drop_resident_pages", counted)
    monkeypatch.setattr(layout_module, "TILE_BAND_BYTES", 4096)
    store = TileStore(tmp_path, "patch", DEVICE)
    out, layout = _diffused(patch_layout, store)
    assert store.loaded and all(grid.stored for grid in layout._grids.values())
    np.testing.assert_array_equal(out, reference)
    levels = len(layout._grids)
    assert len(dropped) > 10 * levels  # bands, not a drop a kernel


def _render_twice(lit_patch: Path, tmp_path: Path, spoil: bool, stored: bool = True
                  ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], Any, list[bool]]:
    """The lit patch rendered into a tile store, then as a render's last frame from it
    (``spoil``: every stored file damaged first): both frames, the second's log, and
    whether its maps had let their surface go when its irradiance cast its rays
    (``stored`` False: no tile store, each render makes its tiles)."""
    from dataclasses import replace

    from skinpipe.render import renderer as renderer_module

    options = replace(SMALL, layout_cache=str(tmp_path / "layouts") if stored else None)
    first = Renderer(open_stage_guarded(lit_patch), options)
    want, _ = first.render()
    first.close()
    if spoil:
        for f in (tmp_path / "layouts").rglob("*.npz"):
            f.write_bytes(f.read_bytes()[:100])
    second = Renderer(open_stage_guarded(lit_patch), options)
    second.last_frame = True
    texs: list[Any] = []
    let_go: list[bool] = []
    irradiance, cast = Renderer.irradiance, renderer_module.irradiance_texture
    prepare, arrive = DiffusionLayout.prepare, renderer_module._BothArrived.arrive
    rays_began = threading.Event()

    def prepare_after_the_rays(layout: DiffusionLayout, *args: Any, **kwargs: Any) -> None:
        rays_began.wait(HANG_S)  # the maps must go before the layout is done
        prepare(layout, *args, **kwargs)

    def layout_goes_on_after_the_release(both: Any, party: str) -> None:
        # the layout goes on only once the maps went (a tiny texture's rows are taken
        # at once): it must have taken what it reads of them before it said so
        arrive(both, party)
        deadline = time.monotonic() + HANG_S
        while party == "layout" and (not texs or texs[0].maps.position is not None) \
                and time.monotonic() < deadline:
            time.sleep(0.005)

    def keep_tex(self: Renderer, log: Any, scene: Any, tex: Any, *rest: Any) -> Any:
        texs.append(tex)
        return irradiance(self, log, scene, tex, *rest)

    def rays(*args: Any, **kwargs: Any) -> Any:
        # the layout's thread says at once that the store holds its tiles: wait for it
        deadline = time.monotonic() + HANG_S
        while texs[0].maps.position is not None and time.monotonic() < deadline:
            time.sleep(0.005)
        let_go.append(texs[0].maps.position is None and texs[0].maps.normal is None)
        rays_began.set()
        return cast(*args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(DiffusionLayout, "prepare", prepare_after_the_rays)
        mp.setattr(renderer_module._BothArrived, "arrive", layout_goes_on_after_the_release)
        mp.setattr(Renderer, "irradiance", keep_tex)
        mp.setattr(renderer_module, "irradiance_texture", rays)
        got, log = second.render()
    second.close()
    return want, got, log, let_go


def test_a_last_frame_from_stored_tiles_lets_the_maps_go_before_the_rays(
        lit_patch: Path, tmp_path: Path) -> None:
    """Where the tile store holds a layout's tiles, a render's last frame lets the
    position and normal maps go once the irradiance has its texels' rows, before its
    rays, not when the layout is done: the same images bit for bit."""
    want, got, log, let_go = _render_twice(lit_patch, tmp_path, spoil=False)
    assert let_go == [True]
    assert log.measures["tile_store"]["loaded"] and not log.measures["tile_store"]["saved"]
    for aov, image in want.items():
        np.testing.assert_array_equal(got[aov], image, err_msg=aov)


def test_a_last_frame_that_makes_its_tiles_lets_the_maps_go_before_the_rays(
        lit_patch: Path, tmp_path: Path) -> None:
    """Without a tile store, the layout made in the process: a render's last frame lets
    the position and normal maps go once the irradiance has its texels' rows, before its
    rays (the layout makes its surface and texel sizes from the triangles): the same
    images bit for bit as a frame that keeps them."""
    want, got, _, let_go = _render_twice(lit_patch, tmp_path, spoil=False, stored=False)
    assert let_go == [True]
    assert not (tmp_path / "layouts").exists()
    for aov, image in want.items():
        np.testing.assert_array_equal(got[aov], image, err_msg=aov)


def test_a_stored_level_that_does_not_read_back_after_the_maps_went_is_made_again(
        lit_patch: Path, tmp_path: Path) -> None:
    """The maps went before the rays because the store listed the tiles; the files then
    do not read back: the layout makes the tiles from maps rasterised again, and the
    images are the same bit for bit."""
    want, got, log, let_go = _render_twice(lit_patch, tmp_path, spoil=True)
    assert let_go == [True]
    notes = log.measures["tile_store"]["notes"]
    assert any("cannot be used" in n for n in notes), notes
    assert log.measures["tile_store"]["saved"]
    for aov, image in want.items():
        np.testing.assert_array_equal(got[aov], image, err_msg=aov)
