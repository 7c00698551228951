"""Atomic file output: write to a temporary sibling, fsync, then rename; and the
output guard that keeps a command from writing over what is not its own.

Readers (a farm job, a re-run of a batch) must never see a half-written file, and a
failed write must not truncate the previous good one. ``os.replace`` is atomic on
POSIX within one file system, hence the temporary file lives beside the target.

A command's output directory is staged whole in a temporary sibling
(:func:`staged_output_directory`) and moved in file by file only once everything is
written: a full disk, a crash or Ctrl-C leaves nothing half-way. Every directory
skinpipe writes holds a ledger (``.skinpipe-outputs.json``) of the files it wrote there;
an existing file is replaced only if a ledger lists it and the command does not read it
(``force`` overrides both), so a user's captures, sources and layers are never written
over by a mistyped ``-o``.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import socket
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, fields, is_dataclass, replace
from pathlib import Path
from typing import Any

from .errors import InputError

LEDGER_NAME = ".skinpipe-outputs.json"
_PATH_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}")


def check_path_name(name: object, what: str, source: str | Path | None = None) -> str:
    """``name`` if it can become one file or folder name (letters, digits, ``_ . -``,
    not starting with a dot, at most 128 characters); InputError naming ``what`` and
    ``source`` otherwise. Region, subject, asset and image names become paths: a name
    like ``../../x`` must not write outside the output folder."""
    if not isinstance(name, str) or not _PATH_NAME.fullmatch(name):
        raise InputError(f"{what} {name!r} cannot name a file: use letters, digits, '_', "
                         "'.' and '-' (not first), at most 128 characters", source)
    return name


@contextlib.contextmanager
def atomic_path(target: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``target``; on success fsync it and rename it over.

    The temporary name keeps the target's suffix (``suffix`` overrides it) because
    OpenImageIO and USD choose the file format from the extension. On an exception the
    temporary file is removed and ``target`` is left untouched.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(
        prefix=f".{target.stem}.", suffix=suffix if suffix is not None else target.suffix,
        dir=target.parent,
    )
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        if not tmp.exists() or tmp.stat().st_size == 0:
            raise OSError(f"{target}: nothing was written")
        with open(tmp, "rb+") as handle:
            os.fsync(handle.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, target)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def atomic_write_text(target: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``target`` atomically and return the target path."""
    with atomic_path(target) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(target)


def atomic_write_json(target: str | Path, data: Any) -> Path:
    """Write ``data`` as indented JSON atomically (NaN is refused: JSON has none)."""
    return atomic_write_text(target, json.dumps(data, indent=2, allow_nan=False) + "\n")


@contextlib.contextmanager
def atomic_directory(target: str | Path) -> Iterator[Path]:
    """Yield a temporary directory beside ``target``; on success it replaces ``target``.

    A directory of outputs (a batch stage's) appears whole or not at all: a killed
    process leaves only a ``.name.tmp-*`` sibling, which no reader trusts. An existing
    ``target`` is moved aside first and removed after the new one is in place.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=target.parent))
    try:
        yield tmp
        os.chmod(tmp, 0o755)  # mkdtemp's 0700 would hide the outputs from other users
        old = None
        if target.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=target.parent))
            os.replace(target, old / target.name)
        os.replace(tmp, target)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def stale_siblings(target: str | Path) -> list[Path]:
    """Temporaries that :func:`atomic_directory` left beside ``target`` when its process
    was killed (``.name.tmp-*``, ``.name.old-*``)."""
    target = Path(target)
    if not target.parent.is_dir():
        return []
    return sorted(p for p in target.parent.iterdir()
                  if p.name.startswith((f".{target.name}.tmp-", f".{target.name}.old-")))


def relocate_records(folder: Path, final: Path) -> None:
    """The JSON records written under ``folder`` (a temporary output folder, recursively)
    rewritten to name ``final`` instead, where they mention ``folder``."""
    for path in folder.rglob("*.json"):
        doc = json.loads(path.read_text(encoding="utf-8"))
        moved = relocate_paths(doc, str(folder), str(final))
        if moved != doc:
            atomic_write_json(path, moved)


def relocate_paths(doc: Any, old: str, new: str) -> Any:
    """``doc`` (JSON data) with every string that starts with the path ``old`` pointing
    under ``new`` instead: records written in a temporary directory name their final
    place."""
    if isinstance(doc, str):
        return new + doc[len(old):] if doc == old or doc.startswith(old + os.sep) else doc
    if isinstance(doc, list):
        return [relocate_paths(v, old, new) for v in doc]
    if isinstance(doc, dict):
        return {k: relocate_paths(v, old, new) for k, v in doc.items()}
    return doc


# --------------------------------------------------------------------- the output guard


def _ledger(directory: Path) -> dict[str, str]:
    """``{relative path: verb}`` of the files skinpipe wrote under ``directory``."""
    try:
        doc = json.loads((directory / LEDGER_NAME).read_text(encoding="utf-8"))
        return {str(k): str(v) for k, v in doc.get("files", {}).items()}
    except (OSError, ValueError, AttributeError):
        return {}


def written_by_skinpipe(path: str | Path) -> bool:
    """Whether a ledger in ``path``'s folder or any folder above lists ``path``."""
    path = Path(path).absolute()
    for folder in path.parents:
        if (folder / LEDGER_NAME).is_file() and \
                path.relative_to(folder).as_posix() in _ledger(folder):
            return True
    return False


def record_outputs(directory: str | Path, relative: list[str], verb: str) -> None:
    """Add ``relative`` (paths under ``directory``) to its ledger as written by ``verb``."""
    directory = Path(directory)
    files = _ledger(directory) | {r: verb for r in relative}
    atomic_write_json(directory / LEDGER_NAME, {
        "note": "files skinpipe wrote here; skinpipe replaces only these", "files": files})


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def check_writable_location(target: str | Path) -> Path:
    """Refuse, before any work, a ``target`` whose nearest existing folder is a file or
    cannot be written (read-only file system, no permission)."""
    target = Path(target)
    folder = target.absolute().parent
    while not folder.exists():
        folder = folder.parent
    if not folder.is_dir():
        raise InputError(f"cannot write {target}: {folder} is a file, not a folder", folder)
    if not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(f"cannot write {target}: {folder} is not writable "
                         "(read-only file system or no permission)", folder)
    return target


def check_output_file(target: str | Path, reads: list[Path] | tuple[Path, ...] = (),
                      force: bool = False) -> Path:
    """Refuse, before any work, to write ``target`` over a folder, over a file the command
    reads (its inputs and every layer and texture they bring) or over a file skinpipe did
    not write; ``force`` allows the last two."""
    target = Path(target)
    check_writable_location(target)
    if target.is_dir():
        raise InputError("is a folder: give a file name", target)
    if target.exists() and not force:
        if any(_same_file(target, r) for r in reads):
            raise InputError("is an input of this command: refusing to write over it "
                             "(choose another output or pass --force)", target)
        if not written_by_skinpipe(target):
            raise InputError("exists and skinpipe did not write it: refusing to replace it "
                             "(choose another output or pass --force)", target)
    return target


@dataclass
class StagedOutput:
    """A command's output directory while it is written: ``path`` (a temporary sibling of
    ``target``) now, ``target`` once committed."""

    path: Path
    target: Path

    def final(self, doc: Any) -> Any:
        """``doc`` (JSON data, a path, or a dataclass of paths) with staged paths pointing
        into ``target``."""
        if is_dataclass(doc) and not isinstance(doc, type):
            return replace(doc, **{f.name: self.final(getattr(doc, f.name))
                                   for f in fields(doc)})
        if isinstance(doc, Path):
            return Path(relocate_paths(str(doc), str(self.path), str(self.target)))
        return relocate_paths(doc, str(self.path), str(self.target))


def _host_tag() -> str:
    return re.sub(r"[^A-Za-z0-9_-]", "_", socket.gethostname())[:64] or "host"


def _stage_prefix(target: Path) -> str:
    """A stage's name says which host and process made it, so that a later run can tell
    one a killed process left (and only such one) from one still being written."""
    return f".{target.name}.tmp-{_host_tag()}-{os.getpid()}-"


def remove_abandoned_stages(target: Path) -> list[Path]:
    """Remove the stages beside ``target`` that a process of this host left when it was
    killed (kill -9, power loss): its name carries this host and a process id no longer
    running. Stages of other hosts (a farm's shared folder) and of live processes stay."""
    pattern = re.compile(re.escape(f".{target.name}.tmp-") + r"(?P<host>[A-Za-z0-9_-]+)-"
                         r"(?P<pid>\d+)-[A-Za-z0-9_]+$")
    host = _host_tag()
    removed = []
    for path in target.parent.iterdir() if target.parent.is_dir() else []:
        match = pattern.match(path.name)
        if match is None or match["host"] != host or not path.is_dir() or path.is_symlink():
            continue
        try:
            os.kill(int(match["pid"]), 0)
            continue  # alive (or another user's): not ours to touch
        except ProcessLookupError:
            pass
        except OSError:
            continue
        shutil.rmtree(path, ignore_errors=True)
        removed.append(path)
    return removed


@contextlib.contextmanager
def staged_output_directory(target: str | Path, verb: str,
                            reads: list[Path] | tuple[Path, ...] = (), force: bool = False,
                            expect: tuple[str, ...] | list[str] = ()) -> Iterator[StagedOutput]:
    """Stage a command's outputs and move them into ``target`` only when all are written.

    Checked before the work: ``target`` is (or can be) a folder, and the files it is
    expected to write (``expect``, relative names) may be replaced (:func:`check_output_file`).
    Checked again at the commit, for every staged file, before any is moved. JSON records
    written in the stage are relocated to name their final place. Files already in
    ``target`` that the command does not write are left alone; the ledger records the
    new ones. On an exception (full disk, Ctrl-C) the stage is removed and ``target`` is
    as it was."""
    target = Path(target)
    check_writable_location(target)
    if target.exists() and not target.is_dir():
        raise InputError("is a file: give a folder for the outputs", target)
    for name in expect:
        check_output_file(target / name, reads, force)
    created = [p for p in (target.absolute(), *target.absolute().parents) if not p.exists()]
    target.parent.mkdir(parents=True, exist_ok=True)
    remove_abandoned_stages(target)
    stage = Path(tempfile.mkdtemp(prefix=_stage_prefix(target), dir=target.parent)).absolute()
    ok = False
    try:
        staged = StagedOutput(stage, target)
        yield staged
        files = sorted(p.relative_to(stage) for p in stage.rglob("*") if p.is_file())
        for rel in files:
            if (target / rel).is_dir():
                raise InputError("is a folder where skinpipe writes a file", target / rel)
            check_output_file(target / rel, reads, force)
        relocate_records(stage, target)
        for rel in files:
            (target / rel).parent.mkdir(parents=True, exist_ok=True)
            os.replace(stage / rel, target / rel)
        for folder in (target, *(target / d for d in {r.parent for r in files})):
            os.chmod(folder, 0o755)
        record_outputs(target, [r.as_posix() for r in files], verb)
        ok = True
    finally:
        shutil.rmtree(stage, ignore_errors=True)
        if not ok:  # folders made for this output only, now empty, go too
            for folder in created:
                with contextlib.suppress(OSError):
                    folder.rmdir()
