"""skinpipe's cache layer (skinpipe/render/cache.py): entries read back as made, checked
before use (damaged, foreign or hostile ones removed and made again, with a warning),
bounded in size least recently used first, and never anything of the user's touched."""

from __future__ import annotations

import fcntl
import json
import os
import time
from pathlib import Path

import pytest

from skinpipe.errors import InputError
from skinpipe.render import cache
from skinpipe.render.cache import (
    LIMIT_ENV,
    MARKER,
    CacheWarning,
    GuardedTree,
    entry_name,
    evict,
    kept,
    limit_bytes,
    read_json_entry,
    write_json_entry,
)


@pytest.fixture(autouse=True)
def _fresh_warnings() -> None:
    cache._WARNED.clear()  # each test hears its own warnings


def _made(value: int, size: int = 1000):
    def make() -> tuple[int, dict]:
        return value, {"value": value, "pad": "x" * size}
    return make


def _read(doc: dict) -> int:
    return int(doc["value"])


def _path(tmp_path: Path, key: list) -> Path:
    return tmp_path / "skinpipe" / "things" / f"{entry_name('t', key)}.json"


def test_a_kind_folder_stays_under_its_limit_least_recently_used_first(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Four results of about 1 KB under a 2.5 KB limit: each write removes the least
    recently used others, a read marks its file used, the file just written stays even
    alone past the limit, and every result is the same made or read back."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setenv(LIMIT_ENV, "0.0025")
    paths = [_path(tmp_path, [i]) for i in range(4)]
    for i in range(2):
        assert kept("things", "t", [i], _read, _made(i)) == i
        os.utime(paths[i], (time.time() - 100 + i, time.time() - 100 + i))
    assert kept("things", "t", [0], _read, _made(-1)) == 0  # read back: now the newest
    assert kept("things", "t", [2], _read, _made(2)) == 2  # 3 KB: the oldest (1) goes
    assert [p.exists() for p in paths] == [True, False, True, False]
    monkeypatch.setenv(LIMIT_ENV, "0")
    assert kept("things", "t", [3], _read, _made(3)) == 3
    assert [p.exists() for p in paths] == [False, False, False, True]
    assert kept("things", "t", [1], _read, _made(1)) == 1  # made again


def test_eviction_touches_only_what_skinpipe_made(tmp_path: Path) -> None:
    """A limit of 0 in a folder that also holds a user's files and folders (some named
    like skinpipe's entries, one a layout folder without the marker): only skinpipe's
    entries go; a folder without the marker is not touched at all; a killed writer's
    temporary file goes once an hour old, one being written stays."""
    folder = tmp_path / "shared"
    user = folder / "scan_2024"
    user.mkdir(parents=True)
    (user / "head.ply").write_bytes(b"x" * 5000)
    lookalike = folder / f"layout-{'a' * 32}"  # named like a layout, not made by skinpipe
    lookalike.mkdir()
    (lookalike / "L0_M3.npz").write_bytes(b"y" * 5000)
    (folder / "notes.json").write_text("{}")
    assert evict(folder, 0) == []  # no marker: not skinpipe's folder
    (folder / MARKER).touch()
    mine = folder / f"{entry_name('t', [1])}.json"
    write_json_entry(mine, [1], {"value": 1})
    layout = folder / f"layout-{'b' * 32}"
    layout.mkdir()
    (layout / MARKER).touch()
    (layout / "L0_M3.npz").write_bytes(b"z" * 100)
    (layout / "user.txt").write_text("not the store's")
    stale, fresh = folder / ".t-1.abc.tmp", folder / ".t-2.def.tmp"
    stale.write_text("{")
    fresh.write_text("{")
    old = time.time() - 2 * cache.STALE_TMP_S
    os.utime(stale, (old, old))
    import re
    removed = evict(folder, 0, files=re.compile(r"^L\d+_M\d+\.npz$"))
    assert sorted(p.name for p in removed) == sorted([mine.name, layout.name, lookalike.name])
    assert not mine.exists() and not (layout / "L0_M3.npz").exists()
    assert (layout / "user.txt").is_file()  # a file the store did not write stays
    assert (lookalike / "L0_M3.npz").is_file()  # no marker: nothing of it goes
    assert (user / "head.ply").is_file() and (folder / "notes.json").is_file()
    assert not stale.exists() and fresh.exists()


@pytest.mark.parametrize("damage", ["scaled", "key", "truncated", "garbage", "format",
                                    "devzero", "dangling", "fifo", "huge", "folder"])
def test_an_entry_that_fails_its_checks_is_removed_and_made_again(
        damage: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Weights scaled x3 with the key intact (checksum), another key, a truncated or
    garbage file, another format, a link to /dev/zero or to nothing, a FIFO, a file
    past the read bound, a folder: the result is made again, never read from it, a
    warning names the file, and reading it neither hangs nor runs out of memory."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    key = ["weights", 1]
    assert kept("things", "t", key, _read, _made(7)) == 7
    path = _path(tmp_path, key)
    doc = json.loads(path.read_text())
    if damage == "scaled":
        doc["payload"]["value"] *= 3
        path.write_text(json.dumps(doc))
    elif damage == "key":
        doc["key"] = ["weights", 2]
        path.write_text(json.dumps(doc))
    elif damage == "truncated":
        path.write_text(path.read_text()[:40])
    elif damage == "garbage":
        path.write_bytes(os.urandom(300))
    elif damage == "format":
        doc["format"] = "skinpipe-cache-0"
        path.write_text(json.dumps(doc))
    elif damage == "devzero":
        path.unlink()
        path.symlink_to("/dev/zero")
    elif damage == "dangling":
        path.unlink()
        path.symlink_to(tmp_path / "nowhere")
    elif damage == "fifo":
        path.unlink()
        os.mkfifo(path)
    elif damage == "huge":
        with open(path, "r+b") as f:
            f.truncate(cache.MAX_JSON_BYTES + 1)
    else:
        path.unlink()
        path.mkdir()
    with pytest.warns(CacheWarning, match=str(path.name)):
        assert kept("things", "t", key, _read, _made(8)) == 8
    if damage == "folder":  # a folder is never removed: the result is made each time
        assert path.is_dir() and kept("things", "t", key, _read, _made(9)) == 9
    else:
        assert kept("things", "t", key, _read, _made(9)) == 8  # kept again, whole


def test_a_payload_the_reader_refuses_is_made_again(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    kept("things", "t", [1], _read, lambda: (1, {"other": 1}))
    with pytest.warns(CacheWarning, match="does not fit"):
        assert kept("things", "t", [1], _read, _made(2)) == 2


@pytest.mark.parametrize("how", ["file", "read-only"])
def test_a_cache_folder_that_cannot_be_used_means_working_without_it(
        how: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A file where the cache folder should be, or a read-only one: the result is made,
    nothing raises, and one warning names the folder."""
    root = tmp_path / "cache"
    if how == "file":
        root.write_text("not a folder")
    else:
        (root / "skinpipe").mkdir(parents=True)
        (root / "skinpipe").chmod(0o500)
        if os.access(root / "skinpipe", os.W_OK):  # root ignores permissions
            pytest.skip("this user can write anywhere")
    monkeypatch.setenv("XDG_CACHE_HOME", str(root))
    with pytest.warns(CacheWarning, match="cannot be used") as got:
        assert kept("things", "t", [1], _read, _made(1)) == 1
        assert kept("things", "t", [1], _read, _made(2)) == 2
    assert len(got) == 1


def test_read_json_entry_marks_its_file_used(tmp_path: Path) -> None:
    path = tmp_path / f"{entry_name('k', [1])}.json"
    write_json_entry(path, [1], {"a": 1})
    os.utime(path, (1000, 1000))
    assert read_json_entry(path, [1]) == {"a": 1}
    assert path.stat().st_mtime > time.time() - 60


@pytest.mark.parametrize("raw", ["lots", "-1", "nan"])
def test_a_bad_limit_is_refused_naming_the_variable(raw: str,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(LIMIT_ENV, raw)
    with pytest.raises(InputError, match=LIMIT_ENV):
        limit_bytes()
    monkeypatch.delenv(LIMIT_ENV)
    assert limit_bytes() == cache.DEFAULT_LIMIT_MB * 1e6


def test_a_bad_limit_stops_the_command_before_it_renders(
        lit_patch: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Exit 2 with the variable named and nothing written, with the layout store off
    too: the kept results are written whatever the store does."""
    from skinpipe.cli import main
    from skinpipe.errors import EXIT_BAD_INPUT
    from skinpipe.render import renderer

    def no_render(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("rendered before the limit was checked")

    monkeypatch.setenv(LIMIT_ENV, "lots")
    monkeypatch.setattr(renderer.Renderer, "render", no_render)
    assert main(["render", str(lit_patch), "--resolution", "32x32", "--texture-size", "64",
                 "--layout-cache", "off", "-o", str(tmp_path / "bad")]) == EXIT_BAD_INPUT
    assert LIMIT_ENV in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


# ----------------------------------------------------------------- guarded trees


def _tree(tmp_path: Path) -> tuple[GuardedTree, Path]:
    folder = tmp_path / "root" / "kernels"
    return GuardedTree(folder, "kernels", transient=("last_accessed",)), folder


def test_a_tree_is_vouched_for_at_exit_and_checked_at_the_next_start(tmp_path: Path) -> None:
    """What a process leaves is trusted by the next; a file damaged in between (garbage,
    truncated) or added by no process takes its program's folder with it, with a
    warning; a file the library rewrites in place (transient) is not held to it."""
    tree, folder = _tree(tmp_path)
    assert tree.open() == folder
    program = folder / "NI" / "ABCDEF"
    (program / "k").mkdir(parents=True)
    (program / "program.bc").write_bytes(b"bitcode" * 100)
    (program / "k" / "k.so").write_bytes(b"\x7fELF" + b"0" * 400)
    (folder / "OK" / "GHIJ").mkdir(parents=True)
    (folder / "OK" / "GHIJ" / "program.bc").write_bytes(b"fine")
    (program / "last_accessed").write_bytes(b"")
    tree.close()
    again, _ = _tree(tmp_path)
    assert again.open() == folder and (program / "k" / "k.so").is_file()  # vouched for
    (program / "last_accessed").write_bytes(b"rewritten")
    again.close()
    third, _ = _tree(tmp_path)
    with open(program / "k" / "k.so", "r+b") as f:
        f.truncate(10)  # a truncated kernel library (SIGBUS when PoCL maps it)
    (folder / "ZZ").mkdir()
    (folder / "ZZ" / "garbage").write_bytes(os.urandom(64))
    with pytest.warns(CacheWarning, match="removed 2 file"):
        assert third.open() == folder
    assert not program.exists() and not (folder / "ZZ" / "garbage").exists()
    assert (folder / "OK" / "GHIJ" / "program.bc").is_file()
    third.close()


def test_a_tree_in_use_with_unknown_files_is_left_to_its_user(tmp_path: Path) -> None:
    """Another process holds the tree (its lock shared) and it holds files no manifest
    vouches for (perhaps being written): they stay, and this process works in a
    folder of its own, removed when it ends."""
    tree, folder = _tree(tmp_path)
    tree.open()
    tree.close()
    (folder / "new.so").write_bytes(b"being written")
    lock = os.open(tmp_path / "root" / ".kernels.lock", os.O_RDWR)
    fcntl.flock(lock, fcntl.LOCK_SH)
    try:
        other, _ = _tree(tmp_path)
        with pytest.warns(CacheWarning, match="another process"):
            private = other.open()
        assert private != folder and (folder / "new.so").is_file()
        other.close()
        assert not private.exists()
    finally:
        os.close(lock)


def test_a_tree_that_cannot_be_used_gives_way_to_a_private_one(tmp_path: Path) -> None:
    (tmp_path / "root").write_text("a file where the folder should be")
    tree = GuardedTree(tmp_path / "root" / "kernels", "kernels")
    with pytest.warns(CacheWarning, match="cannot be used"):
        private = tree.open()
    assert private.is_dir() and not private.is_relative_to(tmp_path)
    tree.close()
    assert not private.exists()
