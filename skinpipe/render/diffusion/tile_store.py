"""The seam layout's chart tiles kept on disk between renders.

A skin mesh's chart tiles (:class:`~.chart_tiles.TileLevel`, one per pyramid level and
margin) depend on its geometry, UVs and texture size only, never on the lights, the
camera or the fits' weights, and they are most of a first render's work at large
textures. A look-development loop renders the same asset again and again under other
lights, and a farm renders its frames in separate processes, so the tiles are kept on
disk (skinpipe's cache rules, :mod:`..cache`): one layout a folder
``layout-<key>`` (the key: a hash of the mesh and texture maps' key, the scene's
geometry, the skin mesh's place in it, the source of the modules that make the tiles,
the libraries whose arithmetic they use and the OpenCL device that computed their
margin points), one uncompressed ``.npz`` per level and margin, each array's data
64-byte aligned so that a render maps it rather than reads it.

Each file carries a header member (the format, the full key, its level and margin),
checked before anything is mapped, and each array's zip CRC-32, checked as it is
mapped: a file that fails (another layout's file, damage, a link) is removed with a
warning and the tiles are made again. The least recently used layouts go when the
folder passes its limit (:data:`LIMIT_ENV`), and only folders the store made.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import mmap
import os
import re
import secrets
import stat
import struct
import threading
import time
import zipfile
import zlib
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from functools import lru_cache
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import IO, Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from ...errors import InputError
from ..cache import FORMAT, MARKER, STALE_TMP_S, evict, usable_folder, warn
from ..options import LAYOUT_CACHE_ENV
from .chart_tiles import SeamReads, TileLevel

LIMIT_ENV = "SKINPIPE_LAYOUT_CACHE_GB"
"""Environment variable: the most the store's folder may hold, in GB (10^9 bytes)."""
DEFAULT_LIMIT_GB = 8.0
"""The demo face's tiles take 0.10 GB at texture 1024, 0.27 GB at 2048, 0.80 GB at 4096."""
_SOURCES = ("skinpipe.render.diffusion.chart_tiles", "skinpipe.render.diffusion.margins",
            "skinpipe.render.diffusion.layout", "skinpipe.render.surface.texture_maps",
            "skinpipe.render.light.raytrace", "skinpipe.render.sorting",
            "skinpipe.render.device.programs", "skinpipe.render.diffusion.tile_store")
"""The modules whose code decides the tiles' content (a changed line is a new key)."""
_LIBRARIES = ("numpy", "scipy", "embreex")
_FILE = re.compile(r"^L(\d+)_M(\d+)\.npz$")
_DERIVED = "grid_"
"""The prefix of the arrays a level's grid derived from the tiles' texel sizes (stored
with the tiles, in their place)."""
Made = TypeVar("Made")
ALIGN = 64
"""Each stored array's data starts at a multiple of this many bytes in its file (numpy's
own header alignment within a .npy), so that it maps into memory as an aligned array."""
_PAD_ID = 0xD935
"""The zip extra field's id for the local headers' padding (as Android's zipalign)."""


def layout_folder(value: str | None = None) -> Path | None:
    """The folder a CLI render keeps layouts in: ``value`` (``--layout-cache``), else
    ``$SKINPIPE_LAYOUT_CACHE``, else ``layouts`` in skinpipe's cache folder; None where
    the one that decides says ``off``. The size limit (:func:`limit_bytes`) is checked
    here too, so that a bad one stops the command before it renders."""
    from ..cache import cache_root

    chosen = (value if value is not None else os.environ.get(LAYOUT_CACHE_ENV, "")).strip()
    if chosen.lower() == "off":
        return None
    limit_bytes()
    return Path(chosen) if chosen else cache_root() / "layouts"


def limit_bytes() -> int:
    """The store's size limit from :data:`LIMIT_ENV` (a positive number of GB)."""
    raw = os.environ.get(LIMIT_ENV)
    try:
        gb = float(raw) if raw else DEFAULT_LIMIT_GB
    except ValueError:
        gb = -1.0
    if not gb > 0:
        raise InputError(f"${LIMIT_ENV} must be a positive number of GB, got {raw!r}")
    return int(gb * 1e9)


@lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """A hash of the source of the modules that make the tiles and the versions of the
    libraries whose arithmetic they use."""
    h = hashlib.blake2b(digest_size=16)
    for name in _SOURCES:
        spec = importlib.util.find_spec(name)
        assert spec is not None and spec.origin is not None, name
        h.update(name.encode())
        h.update(Path(spec.origin).read_bytes())
    for lib in _LIBRARIES:
        try:
            h.update(f"{lib}={version(lib)}".encode())
        except PackageNotFoundError:
            h.update(f"{lib}=?".encode())
    return h.hexdigest()


def device_identity(device: Any) -> str:
    """The OpenCL device (a :class:`~..device.choice.Device`) that computes the margin
    points: platform, device, driver."""
    dev = device.cl_device
    return f"{dev.platform.name}|{dev.name}|{dev.driver_version}"


class TileStore:
    """One layout's tiles in ``folder/layout-<key>/L<level>_M<margin>.npz``. ``notes``
    says what was read, written, removed or could not be (for the render's log)."""

    def __init__(self, folder: Path, layout_key: str, device: Any,
                 limit: int | None = None) -> None:
        self.root = Path(folder)
        self.key = hashlib.blake2b(
            f"{layout_key}|{code_fingerprint()}|{device_identity(device)}".encode(),
            digest_size=16).hexdigest()
        self.entry = self.root / f"layout-{self.key}"
        self.limit = limit_bytes() if limit is None else limit
        self.notes: list[str] = []
        self.loaded: list[tuple[int, int]] = []
        self.saved: list[tuple[int, int]] = []
        self.read_s = self.write_s = 0.0
        self._lock = threading.Lock()
        self._unwritable = usable_folder(self.root, "seam layouts are made each time") is None
        self._writer: ThreadPoolExecutor | None = None
        self._pending: list[Future[None]] = []

    def _note(self, text: str) -> None:
        with self._lock:
            if text not in self.notes:
                self.notes.append(text)

    def stored(self) -> list[tuple[int, int]]:
        """The (level, margin) pairs this layout has on disk."""
        if self._unwritable:
            return []
        try:
            names = [p.name for p in self.entry.iterdir()]
        except OSError:
            return []
        return sorted((int(m[1]), int(m[2])) for m in map(_FILE.match, names) if m)

    def serving(self, level: int, margin: int) -> int | None:
        """The narrowest stored margin of level ``level`` of at least ``margin`` (a wider
        one holds what a narrower would), None where there is none."""
        fits = [m for (k, m) in self.stored() if k == level and m >= margin]
        return min(fits) if fits else None

    def load(self, level: int, margin: int,
             make: Callable[[TileLevel, dict[str, NDArray[Any]]], Made]) -> Made | None:
        """``make`` of level ``level``'s stored tiles with the narrowest margin of at
        least ``margin`` (a wider one holds what a narrower would) and the arrays stored
        with them (:meth:`save`'s ``derived``), or None. A file that does not read back
        whole, or whose arrays ``make`` refuses (ValueError, KeyError), is removed."""
        served = self.serving(level, margin)
        if served is None:
            return None
        path = self.entry / f"L{level}_M{served}.npz"
        start = time.perf_counter()
        try:
            made = make(*_read_tiles(path, self.key, level, served))
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            try:
                path.unlink(missing_ok=True)
                gone = "removed"
            except OSError:  # another user's file in a shared folder
                gone = "left in place"
            why = str(exc) or type(exc).__name__
            self._note(f"tile store: {path} cannot be used ({why}); {gone}, tiles made again")
            warn(f"cache entry {path} cannot be used ({why}); {gone}, made again")
            return None
        with self._lock:
            self.read_s += time.perf_counter() - start
            self.loaded.append((level, served))
        try:
            os.utime(self.entry)  # most recently used: the last to go
        except OSError:
            pass
        return made

    def save(self, tiles: TileLevel, derived: dict[str, NDArray[Any]]) -> None:
        """Write ``tiles`` and the arrays ``derived`` from their texel sizes (a
        ``LevelGrid``'s, which :meth:`load` gives back in their place) on the store's
        writer thread, off the layout's path: a first render at texture 4096 writes
        0.8 GB in about 1 s. :meth:`flush` waits for the writes."""
        if self._unwritable:
            return
        arrays = _tile_arrays(tiles, derived, self.key)
        with self._lock:
            if self._writer is None:
                self._writer = ThreadPoolExecutor(1, thread_name_prefix="skinpipe-tiles")
            self._pending.append(self._writer.submit(self._write, tiles.level,
                                                     tiles.margin, arrays))

    def flush(self) -> None:
        """Wait for every write :meth:`save` started (a failed write is a note); the
        writer's thread ends with them."""
        with self._lock:
            writer, self._writer = self._writer, None
            pending, self._pending = self._pending, []
        if writer is not None:
            writer.shutdown(wait=True)
        for done in pending:
            if done.exception() is not None:
                self._note(f"tile store: a write failed ({done.exception()!r})")

    def _write(self, level: int, margin: int, arrays: dict[str, Any]) -> None:
        """``arrays`` to a temporary name, renamed; then the folder kept under its limit."""
        if self._unwritable:
            return
        path = self.entry / f"L{level}_M{margin}.npz"
        start = time.perf_counter()
        tmp: Path | None = None
        try:
            self.entry.mkdir(parents=True, exist_ok=True)
            (self.entry / MARKER).touch()  # the store made this folder: eviction may go
            _remove_stale_temporaries(self.entry)
            # the umask's mode (mkstemp's 0600 would keep the file from a farm's other
            # users sharing the folder), a name of its own per writer
            tmp = self.entry / f".{path.name}.{os.getpid()}.{secrets.token_hex(6)}.tmp"
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            with os.fdopen(fd, "wb") as f:
                write_aligned_npz(f, arrays)
            os.replace(tmp, path)
            tmp = None
        except OSError as exc:
            self._unwritable = True
            self._note(f"tile store: cannot write {path} ({exc}); the tiles are made again "
                       "next time")
            return
        finally:
            if tmp is not None:
                tmp.unlink(missing_ok=True)
        with self._lock:
            self.write_s += time.perf_counter() - start
            self.saved.append((level, margin))
            self._evict()

    def _evict(self) -> None:
        """Remove the least recently used other layouts (and stale temporary files)
        while the folder holds more than the limit: only layout folders the store made
        (:func:`..cache.evict`), and in them only its files."""
        for folder in evict(self.root, self.limit, keep=self.entry, files=_FILE):
            self.notes.append(f"tile store: removed {folder.name} (least recently used) "
                              f"to stay under {self.limit / 1e9:.1f} GB")

    def summary(self) -> dict[str, Any]:
        """What this render did with the store, for render.json."""
        return {"folder": str(self.entry), "loaded": [list(km) for km in self.loaded],
                "saved": [list(km) for km in self.saved],
                "read_s": round(self.read_s, 3), "write_s": round(self.write_s, 3),
                "notes": list(self.notes)}


def _remove_stale_temporaries(folder: Path) -> None:
    """Temporary files a killed writer left in a layout's folder."""
    now = time.time()
    for tmp in folder.glob(".*.tmp"):
        try:
            if now - tmp.lstat().st_mtime > STALE_TMP_S:
                tmp.unlink()
        except OSError:
            continue


def _header(key: str, level: int, margin: int) -> NDArray[np.uint8]:
    """The header member: what the file is for, as JSON bytes."""
    doc = {"format": FORMAT, "key": key, "level": level, "margin": margin}
    return np.frombuffer(json.dumps(doc, sort_keys=True).encode(), np.uint8)


def _tile_arrays(tiles: TileLevel, derived: dict[str, NDArray[Any]], key: str
                 ) -> dict[str, Any]:
    return {"header": _header(key, tiles.level, tiles.margin),
            "shape": np.asarray(tiles.shape, np.int64), "shift": tiles.shift,
            "owner": tiles.owner, "count": tiles.count, "rows": tiles.reads.rows,
            "xy": tiles.reads.xy, **{_DERIVED + k: v for k, v in derived.items()}}


def write_aligned_npz(f: IO[bytes], arrays: dict[str, Any]) -> None:
    """``arrays`` as an uncompressed ``.npz`` (``np.load`` reads it as any other) to the
    seekable file ``f``, each member's array data starting at a multiple of
    :data:`ALIGN` bytes in the file: a padding record in the extra field of each local
    header (``np.savez`` leaves members wherever the last one ended)."""
    with zipfile.ZipFile(f, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, value in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            # the local header: 30 bytes, the name, the padding record (4 bytes and the
            # pad) and the 20-byte zip64 record zipfile adds when it is forced
            fixed = 30 + len(info.filename.encode()) + 4 + 20
            pad = -(f.tell() + fixed) % ALIGN
            info.extra = struct.pack("<HH", _PAD_ID, pad) + bytes(pad)
            with zf.open(info, "w", force_zip64=True) as member:
                write_npy(member, np.asanyarray(value))


def write_npy(f: IO[bytes], array: NDArray[Any]) -> None:
    """``array`` in the ``.npy`` format to ``f``, as ``np.lib.format.write_array`` writes
    it; a C-contiguous array's bytes in one write from its own memory (write_array
    copies them into a new 16 MiB bytes object at a time for a file object that is not
    a real file, such as a zip member)."""
    if not array.flags.c_contiguous or array.dtype.hasobject:
        np.lib.format.write_array(f, array, allow_pickle=False)
        return
    np.lib.format.write_array_header_1_0(f, np.lib.format.header_data_from_array_1_0(array))
    f.write(memoryview(array.reshape(-1).view(np.uint8)))


class _StoreMapping(mmap.mmap):
    """A store file mapped copy-on-write by :func:`mapped_npz` (its own type, so that
    :func:`drop_resident_pages` takes the pages of these mappings only, never those of
    memory a program writes); ``address``: where its first byte is."""

    address = 0


_CRC_CHUNK = 4 << 20
"""Bytes a member's CRC-32 reads at a time."""


def _crc32(f: IO[bytes], start: int, size: int, chunk: bytearray) -> int:
    """The CRC-32 of ``size`` bytes of ``f`` from ``start``, read a chunk at a time
    through the page cache rather than over the mapping: a CRC over the mapping made
    every page of the file part of the render's memory (the demo face's tiles at texture
    4096: 0.77 GB through its diffusion), where its kernels read only some of them."""
    f.seek(start)
    view, crc, left = memoryview(chunk), 0, size
    while left > 0:
        got = f.readinto(view[:min(left, len(chunk))])
        if not got:
            raise ValueError(f"the file ends {left} bytes early")
        crc = zlib.crc32(view[:got], crc)
        left -= got
    return crc


def mapped_npz(path: Path, names: tuple[str, ...] | None = None
               ) -> dict[str, NDArray[Any]]:
    """The arrays ``names`` (None: every one) of an uncompressed ``.npz``, each a
    read-only view of the file mapped copy-on-write (``np.load`` copies each member
    twice into new memory: 1.3 s for the demo face's finest level at texture 4096, this
    0.25 s), after the member's CRC-32 (read from the file, not the mapping) equals the
    zip's: the mapping's pages become memory of the process only as they are read. An
    array whose data is not aligned in the file (a file :func:`write_aligned_npz` did
    not write) is copied. ValueError, KeyError or OSError where the file is not such an
    .npz or a CRC differs."""
    if not stat.S_ISREG(os.lstat(path).st_mode):
        raise ValueError("not a regular file")
    with zipfile.ZipFile(path) as z:
        infos = {info.filename: info for info in z.infolist()}
    if names is None:
        names = tuple(n[:-4] for n in infos if n.endswith(".npy"))
    out: dict[str, NDArray[Any]] = {}
    chunk = bytearray(_CRC_CHUNK)
    with open(os.open(path, os.O_RDONLY | os.O_NOFOLLOW), "rb") as f:
        whole = _StoreMapping(f.fileno(), 0, access=mmap.ACCESS_COPY)
        whole.address = np.frombuffer(whole, np.uint8).ctypes.data
        for name in names:
            info = infos[f"{name}.npy"]
            if info.compress_type != zipfile.ZIP_STORED:
                raise ValueError(f"{name}: a compressed member")
            f.seek(info.header_offset)
            local = f.read(30)
            if len(local) != 30 or local[:4] != b"PK\x03\x04":
                raise ValueError(f"{name}: no local header at {info.header_offset}")
            name_len, extra_len = struct.unpack("<HH", local[26:30])
            start = info.header_offset + 30 + name_len + extra_len
            if start + info.file_size > len(whole):
                raise ValueError(f"{name}: past the file's end")
            if _crc32(f, start, info.file_size, chunk) != info.CRC:
                raise ValueError(f"{name}: its CRC-32 differs from the zip's")
            f.seek(start)
            major, _ = np.lib.format.read_magic(f)
            read_header = {1: np.lib.format.read_array_header_1_0,
                           2: np.lib.format.read_array_header_2_0}.get(major)
            if read_header is None:
                raise ValueError(f"{name}: .npy format version {major}")
            shape, fortran, dtype = read_header(f)
            data = f.tell() - start
            if dtype.hasobject or \
                    data + int(np.prod(shape)) * dtype.itemsize != info.file_size:
                raise ValueError(f"{name}: its header does not describe its bytes")
            array = np.ndarray(shape, dtype, buffer=whole, offset=start + data,
                               order="F" if fortran else "C")
            if not array.flags.aligned:
                array = array.copy()
            # read-only: drop_resident_pages would take a write back to the file's bytes
            array.flags.writeable = False
            out[name] = array
    return out


def drop_resident_pages(arrays: Iterable[NDArray[Any]]) -> None:
    """Take the pages of the store files that ``arrays`` view (:func:`mapped_npz`; the
    pages that hold each array's bytes) out of this process's memory
    (``madvise(MADV_DONTNEED)``): they stay in the system's page cache, and a kernel
    that reads them again maps them back from there (a minor fault, no disk read), so a
    level's tiles are the render's memory only while its kernels read them. The
    mappings are read-only: a page shared with a neighbouring array comes back the same.
    Arrays of other memory, or where the call is missing, are left alone."""
    if not hasattr(mmap, "MADV_DONTNEED"):
        return
    for array in arrays:
        base: Any = array
        while isinstance(base, np.ndarray):
            base = base.base
        if not isinstance(base, _StoreMapping) or not array.size:
            continue
        # the bytes the view spans, whatever its strides
        reach = [(n - 1) * step for n, step in zip(array.shape, array.strides, strict=True)]
        start = array.ctypes.data - base.address + sum(r for r in reach if r < 0)
        end = min(array.ctypes.data - base.address + sum(r for r in reach if r > 0)
                  + array.itemsize, len(base))
        first = start - start % mmap.PAGESIZE
        base.madvise(mmap.MADV_DONTNEED, first, end - first)


CHECK_CHUNK = 1 << 21
"""Values :func:`extremes` and :func:`nondecreasing` read at a time."""


def _chunks(array: NDArray[Any], overlap: int = 0) -> Iterator[NDArray[Any]]:
    """A C-contiguous ``array``'s values, flat, :data:`CHECK_CHUNK` at a time (each
    chunk repeating the ``overlap`` last values of the one before), the pages of a store
    mapping let go after each (:func:`drop_resident_pages`)."""
    flat = array.reshape(-1)
    for s in range(0, max(flat.size - overlap, 1), CHECK_CHUNK):
        part = flat[s:s + CHECK_CHUNK + overlap]
        yield part
        drop_resident_pages([part])


def extremes(array: NDArray[Any]) -> tuple[Any, Any]:
    """(min, max) of a non-empty C-contiguous ``array``, read a chunk at a time
    (:func:`_chunks`): a check of stored tiles holds one chunk of their file in memory,
    not the whole array (a level-0 blur index at texture 4096: 80 MB, beside the
    irradiance's rays)."""
    lows, highs = zip(*((part.min(), part.max()) for part in _chunks(array)), strict=True)
    return min(lows), max(highs)


def nondecreasing(array: NDArray[Any]) -> bool:
    """Whether a C-contiguous ``array`` never decreases, read a chunk at a time
    (:func:`_chunks`)."""
    return all(not bool((np.diff(part) < 0).any()) for part in _chunks(array, overlap=1))


def _read_tiles(path: Path, key: str, level: int, margin: int
                ) -> tuple[TileLevel, dict[str, NDArray[Any]]]:
    """A stored level and the arrays derived with it, mapped from the file
    (:func:`mapped_npz`, each member's CRC checked) once its header says it is this
    layout's level and margin; the tiles checked against each other."""
    header = mapped_npz(path, ("header",))["header"]
    if header.dtype != np.uint8 or header.ndim != 1 or header.size > 4096:
        raise ValueError("no header")
    doc = json.loads(header.tobytes())
    if doc != json.loads(_header(key, level, margin).tobytes()):
        raise ValueError("another layout's file" if doc.get("key") != key else
                         "another level's file")
    a = mapped_npz(path)
    h, w = (int(x) for x in a["shape"])
    n = h * w
    flat = ("owner", "count")
    rows, xy = a["rows"], a["xy"]
    if any(a[name].shape not in ((n,), (h, w)) for name in flat) or a["shift"].ndim != 2 \
            or rows.shape != (n + 1,) or rows.dtype != np.int32 or xy.dtype != np.float32 \
            or xy.shape[1:] != (2,) or int(rows[0]) != 0 or int(rows[-1]) != xy.shape[0] \
            or not nondecreasing(rows):
        raise ValueError("arrays of inconsistent shapes")
    derived = {k[len(_DERIVED):]: v for k, v in a.items() if k.startswith(_DERIVED)}
    return TileLevel(level, margin, (h, w), a["shift"], a["owner"], a["count"],
                     SeamReads((h, w), level, rows, xy), None, None), derived
