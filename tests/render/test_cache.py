"""Results kept between processes: read back as made, bounded in size, least recently
used first out."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from skinpipe.errors import InputError
from skinpipe.render import cache as kept_module
from skinpipe.render.cache import LIMIT_ENV, evict, kept, kept_path, limit_bytes, read_kept


def _made(value: int, size: int = 1000):
    def make() -> tuple[int, dict]:
        return value, {"value": value, "pad": "x" * size}
    return make


def _read(doc: dict) -> int:
    return int(doc["value"])


def test_a_kind_folder_stays_under_its_limit_least_recently_used_first(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Four results of about 1 KB under a 2.5 KB limit: each write removes the least
    recently used others, a read marks its file used, the file just written stays even
    alone past the limit, and every result is the same made or read back."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setenv(LIMIT_ENV, "0.0025")
    paths = [kept_path("things", "t", [i]) for i in range(4)]
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


def test_evict_removes_stale_temporary_files_and_keeps_fresh_ones(tmp_path: Path) -> None:
    """A killed writer's hidden temporary file goes once an hour old; one being written
    now stays; folders and a missing folder are left alone."""
    stale, fresh = tmp_path / ".t-1.abc.json", tmp_path / ".t-2.def.json"
    stale.write_text("{")
    fresh.write_text("{")
    old = time.time() - 2 * kept_module._STALE_TMP_S
    os.utime(stale, (old, old))
    (tmp_path / "sub").mkdir()
    assert evict(tmp_path, 1e9) == []
    assert not stale.exists() and fresh.exists() and (tmp_path / "sub").is_dir()
    assert evict(tmp_path, 0) == [] and fresh.exists()  # another writer's, whatever the limit
    assert evict(tmp_path / "missing", 0) == []


def test_read_kept_marks_its_file_used(tmp_path: Path) -> None:
    path = tmp_path / "k.json"
    path.write_text('{"key": 1}')
    os.utime(path, (1000, 1000))
    assert read_kept(path) == {"key": 1}
    assert path.stat().st_mtime > time.time() - 60
    path.write_text("[1]")  # not an object: not read, not marked
    os.utime(path, (1000, 1000))
    assert read_kept(path) is None and path.stat().st_mtime == 1000


@pytest.mark.parametrize("raw", ["lots", "-1", "nan"])
def test_a_bad_limit_is_refused_naming_the_variable(raw: str,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(LIMIT_ENV, raw)
    with pytest.raises(InputError, match=LIMIT_ENV):
        limit_bytes()
    monkeypatch.delenv(LIMIT_ENV)
    assert limit_bytes() == kept_module.DEFAULT_LIMIT_MB * 1e6


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
