"""skinpipe's caches: one folder, its size limits, and how every entry is named,
written, checked and let go.

What each cache saves is in docs/render.md ("Caches"); a cache stays only where that is
worth its code. Every one follows the same rules:

- An entry is named by a hash of everything that made it (the inputs' bytes, the
  options, the source of the code that makes it, the libraries' versions, the device),
  and carries a header that is checked before the entry is used: the format, the full
  key, and a checksum of its content (the layout store's files: the key, the level,
  and each array's zip CRC-32). An entry that fails is removed and made again, with a
  one-line :class:`CacheWarning`; nothing is read blind or mapped unchecked.
- Readers bound what they read: a JSON entry must be a regular file (not a link, a
  device or a pipe) of at most :data:`MAX_JSON_BYTES`.
- Every folder skinpipe makes for a cache holds a marker file (:data:`MARKER`), and
  eviction removes only entries whose names skinpipe gives (:data:`ENTRY`), never
  anything else in the folder: a cache pointed at a folder of the user's loses them
  nothing.
- A folder that cannot be used (a file where the folder should be, no permission, a
  read-only home) means working without that cache, with a warning naming it.
- Writes go to a temporary name and are renamed whole (processes may write one key at
  once).
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import fcntl
import hashlib
import inspect
import json
import os
import re
import shutil
import stat
import tempfile
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from functools import lru_cache
from pathlib import Path
from typing import Any, TypeVar

from ..errors import InputError
from ..fileio import atomic_write_text

T = TypeVar("T")

FORMAT = "skinpipe-cache-1"
"""The header's format name; a change of layout is a new name, and old entries go."""
MARKER = ".skinpipe-cache"
"""A file in every folder skinpipe made for a cache."""
ENTRY = re.compile(r"^[a-z][a-z0-9-]*-[0-9a-f]{32}(\.json)?$")
"""The names skinpipe gives its entries (a JSON file, or a folder of one layout)."""
MAX_JSON_BYTES = 64 << 20
"""The largest JSON entry read (a mesh's UV charts, the largest, take about 4 bytes a
triangle)."""
LIMIT_ENV = "SKINPIPE_KEPT_CACHE_MB"
"""Environment variable: the most one kind's folder of kept results may hold, in MB (10^6
bytes); :data:`DEFAULT_LIMIT_MB` where unset."""
DEFAULT_LIMIT_MB = 256.0
STALE_TMP_S = 3600.0
"""A temporary file this old was left by a killed process."""


class CacheWarning(UserWarning):
    """A cache entry or folder that could not be used: skinpipe works without it."""


_WARNED: set[str] = set()
_WARN_LOCK = threading.Lock()


def warn(text: str) -> None:
    """``text`` as a :class:`CacheWarning`, once per process."""
    with _WARN_LOCK:
        if text in _WARNED:
            return
        _WARNED.add(text)
    warnings.warn(text, CacheWarning, stacklevel=2)


def cache_root() -> Path:
    """skinpipe's cache folder: ``$XDG_CACHE_HOME/skinpipe``, else ``~/.cache/skinpipe``."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "skinpipe"


def settle_cache_root() -> Path:
    """The cache folder this process uses: :func:`cache_root` where it can be used; else
    (a file in its place, a home that cannot be written) a private folder, removed at
    the process's end, made the process's ``XDG_CACHE_HOME`` so that the libraries that
    keep caches there (pyopencl's invoker cache among them) work too, with a warning."""
    root = cache_root()
    if usable_folder(root, "this process keeps its caches in a temporary folder") is None:
        private = tempfile.mkdtemp(prefix="skinpipe-private-cache-")
        atexit.register(shutil.rmtree, private, ignore_errors=True)
        os.environ["XDG_CACHE_HOME"] = private
        root = cache_root()
    return root


def usable_folder(folder: Path, what: str) -> Path | None:
    """``folder``, made and marked as a cache folder, if this process can write in it;
    else None, with a warning naming it and ``what`` goes without it."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        marker = folder / MARKER
        if not marker.is_file():
            marker.touch()
        if not os.access(folder, os.W_OK | os.X_OK):
            raise PermissionError(errno.EACCES, "not writable", str(folder))
        return folder
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        warn(f"cache folder {folder} cannot be used ({reason}); {what}")
        return None


def kind_folder(kind: str) -> Path | None:
    """The folder of one kind of kept result, or None (see :func:`usable_folder`)."""
    return usable_folder(cache_root() / kind, f"{kind} are made each time")


def entry_name(name: str, key: Any) -> str:
    """The name of the entry ``name`` made from ``key`` (anything JSON writes)."""
    text = json.dumps(key, sort_keys=True, separators=(",", ":"))
    return f"{name}-{hashlib.blake2b(text.encode(), digest_size=16).hexdigest()}"


def _digest(payload: Any) -> str:
    text = json.dumps(payload, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()


def write_json_entry(path: Path, key: Any, payload: dict[str, Any]) -> None:
    """``payload`` at ``path`` with its header (format, key, checksum), atomically."""
    doc = {"format": FORMAT, "key": key, "sha256": _digest(payload), "payload": payload}
    atomic_write_text(path, json.dumps(doc, separators=(",", ":"), allow_nan=False))


def bounded_read(path: Path, limit: int) -> bytes:
    """The bytes of ``path``, a regular file of at most ``limit`` bytes (checked on the
    open file, so a link swapped in between is not followed); ValueError otherwise
    (OSError for a link: ``O_NOFOLLOW``)."""
    # non-blocking: opening a FIFO for reading would wait for a writer
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise ValueError("not a regular file")
        if st.st_size > limit:
            raise ValueError(f"{st.st_size} bytes, more than {limit}")
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(limit + 1)
    finally:
        os.close(fd)
    if len(data) > limit:
        raise ValueError(f"more than {limit} bytes")
    return data


def reject(path: Path, why: str) -> None:
    """Remove the entry ``path`` (a file or link of skinpipe's naming only) and say so."""
    gone = "left in place"
    if ENTRY.match(path.name):
        with contextlib.suppress(OSError):
            path.unlink()
            gone = "removed"
    warn(f"cache entry {path} cannot be used ({why}); {gone}, made again")


def read_json_entry(path: Path, key: Any) -> dict[str, Any] | None:
    """The payload kept at ``path`` for ``key``, or None: missing, or failing its checks
    (then removed, with a warning)."""
    try:
        data = bounded_read(path, MAX_JSON_BYTES)
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        reject(path, str(exc) if isinstance(exc, ValueError) else exc.strerror or str(exc))
        return None
    try:
        try:
            doc = json.loads(data)
        except (ValueError, RecursionError):
            raise ValueError("not JSON: truncated or overwritten") from None
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise ValueError("not an entry of this skinpipe")
        if doc.get("key") != key:
            raise ValueError("its key is not its name's")
        payload = doc.get("payload")
        if not isinstance(payload, dict) or doc.get("sha256") != _digest(payload):
            raise ValueError("its checksum does not match its content")
    except (ValueError, TypeError) as exc:
        reject(path, str(exc) or type(exc).__name__)
        return None
    with contextlib.suppress(OSError):
        os.utime(path)  # most recently used: the last to go
    return payload


def kept(kind: str, name: str, key: Any, read: Callable[[dict[str, Any]], T],
         make: Callable[[], tuple[T, dict[str, Any]]]) -> T:
    """The result of ``key`` (anything JSON writes, naming every input): ``read`` of the
    payload kept for it where there is one that passes its checks and that ``read``
    takes (it raises ValueError, KeyError or TypeError to refuse it), else the result of
    ``make()``, which also gives the payload to keep."""
    folder = kind_folder(kind)
    path = None if folder is None else folder / f"{entry_name(name, key)}.json"
    payload = None if path is None else read_json_entry(path, key)
    if payload is not None:
        try:
            return read(payload)
        except (ValueError, KeyError, TypeError) as exc:
            reject(path, f"its content does not fit: {exc}")  # type: ignore[arg-type]
    result, made = make()
    if path is not None:
        limit = limit_bytes()
        with contextlib.suppress(OSError, ValueError):
            write_json_entry(path, key, made)
            evict(path.parent, limit, keep=path)
    return result


def limit_bytes() -> float:
    """The most a kind's folder of kept results may hold, in bytes (:data:`LIMIT_ENV`);
    a value that is not a number >= 0 is refused with the variable named."""
    raw = os.environ.get(LIMIT_ENV, "").strip()
    if not raw:
        return DEFAULT_LIMIT_MB * 1e6
    try:
        mb = float(raw)
    except ValueError:
        mb = -1.0
    if not mb >= 0:  # NaN too
        raise InputError(f"${LIMIT_ENV} must be a number of MB >= 0, got {raw!r}")
    return mb * 1e6


def entry_size(path: Path) -> int:
    """Bytes of an entry: a file's, or the files' directly in an entry folder."""
    st = path.lstat()
    if not stat.S_ISDIR(st.st_mode):
        return st.st_size
    total = 0
    with os.scandir(path) as it:
        for item in it:
            with contextlib.suppress(OSError):
                total += item.stat(follow_symlinks=False).st_size
    return total


def remove_entry(path: Path, files: re.Pattern[str] | None = None) -> None:
    """Remove an entry: a file (or link) of skinpipe's naming, or a folder of skinpipe's
    naming that holds the marker, by removing the files in it that match ``files`` (and
    the marker and temporaries), then the folder if it is empty: never a tree."""
    if not ENTRY.match(path.name):
        return
    st = path.lstat()
    if not stat.S_ISDIR(st.st_mode):
        path.unlink()
        return
    if not (path / MARKER).is_file():
        return
    with os.scandir(path) as it:
        names = [item.name for item in it if not item.is_dir(follow_symlinks=False)]
    for name in names:
        if name == MARKER or name.startswith(".") or (files is not None and files.match(name)):
            with contextlib.suppress(OSError):
                (path / name).unlink()
    with contextlib.suppress(OSError):
        path.rmdir()


def evict(folder: Path, limit: float, keep: Path | None = None,
          files: re.Pattern[str] | None = None) -> list[Path]:
    """Remove the least recently used entries of ``folder`` while its entries hold more
    than ``limit`` bytes, never ``keep``; and temporary files a killed process left.
    Only a folder that holds the marker is touched, and in it only entries named as
    skinpipe names them (:data:`ENTRY`): whatever else is there stays. The entries
    removed."""
    if not (folder / MARKER).is_file():
        return []
    now = time.time()
    entries = []
    with contextlib.suppress(OSError), os.scandir(folder) as it:
        for item in it:
            with contextlib.suppress(OSError):
                st = item.stat(follow_symlinks=False)
                if item.name.startswith(".") and item.name.endswith(".tmp") and \
                        not stat.S_ISDIR(st.st_mode):
                    if now - st.st_mtime > STALE_TMP_S:
                        os.unlink(item.path)
                    continue
                if ENTRY.match(item.name):
                    path = Path(item.path)
                    entries.append((st.st_mtime, entry_size(path), path))
    total = sum(size for _, size, _ in entries)
    removed = []
    for _, size, path in sorted(entries, key=lambda e: e[0]):
        if total <= limit:
            break
        if keep is not None and path == keep:
            continue
        with contextlib.suppress(OSError):
            remove_entry(path, files)
            total -= size
            removed.append(path)
    return removed


@lru_cache(maxsize=64)
def source_of(*functions: Callable[..., Any]) -> str:
    """A hash of the functions' source, for a key: a result kept by other code (an
    edited function) is not read back."""
    h = hashlib.blake2b(digest_size=16)
    for function in functions:
        h.update(inspect.getsource(function).encode())
    return h.hexdigest()


# ------------------------------------------------------------------ trees of files


class GuardedTree:
    """A folder that another library fills and reads (PoCL's compiled kernels,
    pyopencl's built programs), which skinpipe cannot check file by file as the
    library reads it: a damaged file there (garbage, a truncated kernel library) can
    kill the process inside the library. So the tree is checked whole before a process
    first uses it, against a manifest (each file's size and SHA-256) that a process
    writes at its exit when no other process uses the tree.

    At :meth:`open`, with no other process using the tree, files the manifest does not
    vouch for are removed, with a warning; with another one using it (and so perhaps
    writing it), a tree that holds such files is left alone and this process uses a
    folder of its own, emptied at exit. A tree that cannot be used at all gives way to
    such a folder too. ``transient``: names of files the library rewrites in place
    (their content is not vouched for)."""

    def __init__(self, folder: Path, what: str, transient: tuple[str, ...] = ()) -> None:
        self.folder = folder
        self.what = what
        self.transient = transient
        self.path: Path | None = None
        self._lock_fd: int | None = None

    @property
    def _manifest(self) -> Path:
        return self.folder.parent / f".{self.folder.name}.manifest.json"

    def open(self) -> Path:
        """The folder to use: the tree, checked, or a private one."""
        if self.path is not None:
            return self.path
        root = usable_folder(self.folder.parent, f"{self.what} are built each time")
        if root is not None:
            try:
                self.folder.mkdir(exist_ok=True)
                if not self.folder.is_dir() or self.folder.is_symlink():
                    raise NotADirectoryError(errno.ENOTDIR, "not a folder", str(self.folder))
                self._lock_fd = os.open(self.folder.parent / f".{self.folder.name}.lock",
                                        os.O_RDWR | os.O_CREAT, 0o666)
                self.path = self._checked()
            except OSError as exc:
                warn(f"cache folder {self.folder} cannot be used "
                     f"({exc.strerror or type(exc).__name__}); {self.what} are built each "
                     "time")
        if self.path is None:
            self.path = Path(tempfile.mkdtemp(prefix="skinpipe-private-cache-"))
        return self.path

    def _checked(self) -> Path | None:
        assert self._lock_fd is not None
        alone = _try_lock(self._lock_fd, fcntl.LOCK_EX)
        untrusted = self._untrusted()
        if untrusted and not alone:
            fcntl.flock(self._lock_fd, fcntl.LOCK_SH)
            warn(f"cache folder {self.folder} holds files no manifest vouches for and "
                 f"another process is using it; this process uses a folder of its own")
            return None
        if untrusted:
            # a program's files go together (PoCL keeps one folder a program, two down)
            units = {self.folder.joinpath(*p.relative_to(self.folder).parts[:2])
                     if len(p.relative_to(self.folder).parts) > 2 else p for p in untrusted}
            for unit in units:
                with contextlib.suppress(OSError):
                    if unit.is_dir() and not unit.is_symlink():
                        shutil.rmtree(unit)
                    else:
                        unit.unlink()
            warn(f"cache folder {self.folder}: removed {len(untrusted)} file(s) no "
                 f"manifest vouches for (damaged or left by a process that did not end); "
                 f"{self.what} are built again")
        fcntl.flock(self._lock_fd, fcntl.LOCK_SH)  # as long as this process runs
        return self.folder

    def _files(self) -> Iterator[Path]:
        for base, dirs, names in os.walk(self.folder, followlinks=False):
            dirs.sort()
            for name in sorted(names):
                yield Path(base, name)

    def _untrusted(self) -> list[Path]:
        try:
            manifest = json.loads(bounded_read(self._manifest, MAX_JSON_BYTES))
            known = manifest["files"] if manifest.get("format") == FORMAT else {}
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            known = {}
        out = []
        for path in self._files():
            rel = path.relative_to(self.folder).as_posix()
            if path.name in self.transient and not path.is_symlink():
                continue
            want = known.get(rel)
            if not isinstance(want, list) or not self._matches(path, want):
                out.append(path)
        return out

    @staticmethod
    def _matches(path: Path, want: list[Any]) -> bool:
        try:
            st = path.lstat()
            if not stat.S_ISREG(st.st_mode) or st.st_size != want[0]:
                return False
            return _sha256(path) == want[1]
        except (OSError, IndexError):
            return False

    def close(self) -> None:
        """At the process's end: the manifest of the tree as it is, if this process used
        it and no other process does; then the lock goes. A private folder is removed."""
        private = self.path is not None and self.path != self.folder
        if private:
            shutil.rmtree(self.path, ignore_errors=True)  # type: ignore[arg-type]
        if self._lock_fd is None:
            return
        try:
            if not private and _try_lock(self._lock_fd, fcntl.LOCK_EX):
                files = {p.relative_to(self.folder).as_posix(): [p.lstat().st_size,
                                                                _sha256(p)]
                         for p in self._files()
                         if p.name not in self.transient and p.is_file()
                         and not p.is_symlink()}
                atomic_write_text(self._manifest, json.dumps(
                    {"format": FORMAT, "files": files}, separators=(",", ":")))
        except OSError:
            pass
        finally:
            os.close(self._lock_fd)
            self._lock_fd = None


def _try_lock(fd: int, kind: int) -> bool:
    try:
        fcntl.flock(fd, kind | fcntl.LOCK_NB)
        return True
    except BlockingIOError:
        return False


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
