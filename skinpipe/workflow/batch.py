"""Batch runs on Dask distributed: many subjects through ingest -> fit -> author -> render.

Each stage of each subject (and each region's fit) is one Dask task. A task's key is a
hash of everything its output depends on: the input files' bytes, the options, the
upstream tasks' keys and the skinpipe version. Its outputs go to a temporary directory
renamed into place with a ``done.json`` recording the key, so a finished task is
recognised and skipped on the next run, and a task killed half-way leaves nothing a
re-run would trust. Failures are caught per task and reported; dependants are skipped.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import __version__
from ..capture.ingest import ingest_capture_set, read_capture_set
from ..errors import InputError
from ..fileio import atomic_directory, atomic_write_json, relocate_records, stale_siblings
from ..native import import_pymeshlab, pymeshlab_folder
from ..profile.io import read_profile_csv, write_fit_json
from ..render.options import RenderOptions
from ..render.outputs import render_files
from ..render.surface.uvs import ensure_skin_uvs
from ..usd.shot import author_shot
from ..usd.validate import validate_file
from .albedo import bake_sample_albedo
from .chain import author_from_files, fit_ingested_profile

STAGES = ("ingest", "fit", "author", "render")
BATCH_FORMAT = 1
PYMESHLAB_PREFIX = "pymeshlab:"
"""A mesh named ``pymeshlab:rangemaps/face000.ply`` is read from pymeshlab's test meshes."""
_SUBJECT_KEYS = {"name", "captures", "mesh", "landmarks", "k", "prepare_scan",
                 "paint_albedo", "render"}
_RENDER_KEYS = {"resolution", "texture_size", "light_samples", "variance_grid", "aovs"}


@dataclass(frozen=True)
class Subject:
    """One subject of a batch: its capture set and, for author/render, its face mesh."""

    name: str
    captures: Path
    mesh: Path | None = None
    landmarks: Path | None = None
    k: int = 6
    prepare_scan: bool = True
    paint_albedo: bool = True
    render: dict[str, Any] = field(default_factory=dict)


def _resolve(value: Any, base: Path, what: str, source: Path) -> Path:
    if not isinstance(value, str) or not value:
        raise InputError(f"{what} must be a path string, got {value!r}", source)
    if value.startswith(PYMESHLAB_PREFIX):
        path = pymeshlab_folder() / "tests" / "sample_meshes" / \
            value[len(PYMESHLAB_PREFIX):]
    else:
        path = Path(value) if os.path.isabs(value) else base / value
    if not path.exists():
        raise InputError(f"{what} {value!r} does not exist ({path})", source)
    return path


def read_batch(path: str | Path) -> list[Subject]:
    """Read BATCH.json: ``{"defaults": {...}, "subjects": [{"name", "captures", "mesh",
    "landmarks", "k", "prepare_scan", "paint_albedo", "render": {...}}, ...]}``; paths
    relative to the file. Every subject is checked before anything runs."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"cannot read the batch file: {exc}", path) from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("subjects"), list) or \
            not doc["subjects"]:
        raise InputError("the batch file needs a non-empty \"subjects\" list", path)
    defaults = doc.get("defaults", {})
    if not isinstance(defaults, dict):
        raise InputError("\"defaults\" must be an object", path)
    # absolute: the paths travel to workers that may run in another folder or machine
    base = Path(os.path.abspath(path.parent))
    subjects: list[Subject] = []
    for i, entry in enumerate(doc["subjects"]):
        if not isinstance(entry, dict):
            raise InputError(f"subject {i} must be an object", path)
        merged = {**defaults, **entry}
        unknown = set(merged) - _SUBJECT_KEYS
        if unknown:
            raise InputError(f"subject {i}: unknown key(s) {sorted(unknown)}; known: "
                             f"{sorted(_SUBJECT_KEYS)}", path)
        name = merged.get("name")
        if not isinstance(name, str) or not name.replace("-", "_").isidentifier():
            raise InputError(f"subject {i}: name must be an identifier (a-z, 0-9, _, -), "
                             f"got {name!r}", path)
        render = merged.get("render", {})
        if not isinstance(render, dict) or set(render) - _RENDER_KEYS:
            raise InputError(f"subject {name}: render options must be an object with keys "
                             f"from {sorted(_RENDER_KEYS)}", path)
        k = merged.get("k", 6)
        if not isinstance(k, int) or not 1 <= k <= 12:
            raise InputError(f"subject {name}: k must be an integer 1-12, got {k!r}", path)
        subjects.append(Subject(
            name=name,
            captures=_resolve(merged.get("captures"), base, f"subject {name}: captures", path),
            mesh=(_resolve(merged["mesh"], base, f"subject {name}: mesh", path)
                  if merged.get("mesh") else None),
            landmarks=(_resolve(merged["landmarks"], base, f"subject {name}: landmarks", path)
                       if merged.get("landmarks") else None),
            k=k, prepare_scan=bool(merged.get("prepare_scan", True)),
            paint_albedo=bool(merged.get("paint_albedo", True)), render=dict(render)))
    names = [s.name for s in subjects]
    if len(set(names)) != len(names):
        raise InputError(f"subject names must be unique: {names}", path)
    return subjects


# ----------------------------------------------------------------------------- keys


def _hash_files(paths: list[Path]) -> str:
    digest = hashlib.sha256()
    for p in paths:
        digest.update(str(p.name).encode())
        with open(p, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def _hash_tree(root: Path) -> str:
    files = sorted(p for p in root.rglob("*") if p.is_file() and not p.name.startswith("."))
    digest = hashlib.sha256()
    for p in files:
        digest.update(str(p.relative_to(root)).encode())
        digest.update(_hash_files([p]).encode())
    return digest.hexdigest()


def task_key(*parts: Any) -> str:
    """A stable hash of a task's inputs (file hashes, options, upstream keys)."""
    text = json.dumps([BATCH_FORMAT, __version__, *parts], sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


@dataclass(frozen=True)
class TaskSpec:
    """One task of the graph: what it runs and where its outputs go."""

    stage: str
    subject: str
    unit: str  # the region for fit tasks, else the stage
    key: str
    out_dir: Path


def plan_subject(subject: Subject, out_root: Path, regions: list[str]) -> dict[str, Any]:
    """Keys and output directories of one subject's tasks (hashes its inputs)."""
    root = out_root / subject.name
    ingest_key = task_key("ingest", _hash_tree(subject.captures))
    fits = {r: TaskSpec("fit", subject.name, r, task_key("fit", ingest_key, r, subject.k),
                        root / "fit" / r) for r in regions}
    mesh_hash = _hash_files([subject.mesh]) if subject.mesh else None
    marks = _hash_files([subject.landmarks]) if subject.landmarks else None
    author_key = task_key("author", sorted(f.key for f in fits.values()), mesh_hash, marks,
                          subject.prepare_scan, subject.paint_albedo,
                          subject.render.get("texture_size", 1024))
    return {
        "ingest": TaskSpec("ingest", subject.name, "ingest", ingest_key, root / "ingest"),
        "fit": fits,
        "author": TaskSpec("author", subject.name, "author", author_key, root / "asset"),
        "render": TaskSpec("render", subject.name, "render",
                           task_key("render", author_key, subject.render), root / "render"),
    }


def _done(spec: TaskSpec) -> dict[str, Any] | None:
    """The recorded result of a finished task whose key matches, else None."""
    try:
        doc = json.loads((spec.out_dir / "done.json").read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return None
    if doc.get("key") != spec.key:
        return None
    return doc


def _run_task(spec: TaskSpec, upstream: list[dict[str, Any]],
              work: Callable[[Path], dict[str, Any]]) -> dict[str, Any]:
    """Skip a finished task, skip when upstream failed, else run ``work`` into a
    temporary directory that replaces ``spec.out_dir`` once ``done.json`` is in it."""
    base = {"stage": spec.stage, "subject": spec.subject, "unit": spec.unit, "key": spec.key,
            "dir": str(spec.out_dir)}
    failed = [u for u in upstream if u["status"] in ("failed", "skipped")]
    if failed:
        return {**base, "status": "skipped", "seconds": 0.0,
                "error": f"upstream {failed[0]['stage']} ({failed[0]['unit']}) "
                         f"{failed[0]['status']}"}
    done = _done(spec)
    if done is not None:
        return {**done, "status": "cached", "seconds": 0.0,
                "original_seconds": done.get("seconds", 0.0)}
    # an earlier attempt that died (its worker lost) left its temporaries: they go, and
    # the retry is recorded
    stale = stale_siblings(spec.out_dir)
    attempts = 1 + sum(".tmp-" in p.name for p in stale)
    for path in stale:
        shutil.rmtree(path, ignore_errors=True)
    if attempts > 1:
        base |= {"attempts": attempts, "retried_because":
                 "an earlier attempt stopped without finishing (its worker was lost) and "
                 "left " + ", ".join(p.name for p in stale)}
    start = time.perf_counter()
    if spec.out_dir.is_dir() and any(spec.out_dir.iterdir()) and \
            not (spec.out_dir / "done.json").is_file():
        return {**base, "status": "failed", "seconds": 0.0,
                "error": f"{spec.out_dir}: a folder that no batch task made is in the way "
                         "(skinpipe replaces only its own task folders): move it"}
    try:
        with atomic_directory(spec.out_dir) as tmp:
            result = work(tmp)
            relocate_records(tmp, spec.out_dir)
            doc = {**base, **result, "status": "done",
                   "seconds": time.perf_counter() - start}
            atomic_write_json(tmp / "done.json", doc)
        return doc
    except Exception as exc:  # reported per task; the batch goes on
        message = str(exc) if isinstance(exc, InputError) else \
            f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=4)}"
        return {**base, "status": "failed", "seconds": time.perf_counter() - start,
                "error": message}


# ---------------------------------------------------------------------------- tasks


def ingest_task(spec: TaskSpec, subject: Subject) -> dict[str, Any]:
    def work(tmp: Path) -> dict[str, Any]:
        report = ingest_capture_set(subject.captures, tmp)
        return {"regions": sorted(report["regions"]),
                "measures": {r: {"samples": e["samples"], "max_radius_mm": e["max_radius_mm"],
                                 "unresolved_pixel_fraction": e["unresolved_pixel_fraction"]}
                             for r, e in report["regions"].items()},
                "outputs": [f"{r}.csv" for r in sorted(report["regions"])]}

    return _run_task(spec, [], work)


def fit_task(spec: TaskSpec, subject: Subject, ingest: dict[str, Any],
             ingest_dir: Path) -> dict[str, Any]:
    def work(tmp: Path) -> dict[str, Any]:
        fit = fit_ingested_profile(read_profile_csv(ingest_dir / f"{spec.unit}.csv"),
                                   subject.k)
        write_fit_json(tmp / f"{spec.unit}.json", fit)
        return {"measures": {"fit_error_eq2c": fit.error.tolist(), "terms": len(fit.weights),
                             "solver_status": fit.status},
                "outputs": [f"{spec.unit}.json"]}

    return _run_task(spec, [ingest], work)


def author_task(spec: TaskSpec, subject: Subject, fits: list[dict[str, Any]],
                fit_dirs: list[Path], ingest_dir: Path) -> dict[str, Any]:
    def work(tmp: Path) -> dict[str, Any]:
        if subject.mesh is None or subject.landmarks is None:
            raise InputError(f"subject {subject.name}: author needs \"mesh\" and \"landmarks\"")
        paths = author_from_files([d / f"{d.name}.json" for d in fit_dirs], subject.mesh, tmp,
                                 landmarks=subject.landmarks, profiles_dir=ingest_dir,
                                 prepare=subject.prepare_scan)
        measures: dict[str, Any] = {}
        if subject.paint_albedo:
            bake_sample_albedo(paths.asset, int(subject.render.get("texture_size", 1024)))
        else:
            # unwrap here, so that a render never writes into a finished asset
            measures["uvs"] = ensure_skin_uvs(paths.asset).note
        check = validate_file(paths.asset)
        if check.failed(strict=False):
            raise InputError("the authored asset is invalid: " + "; ".join(
                p.message for p in check.problems if p.severity == "error"), paths.asset)
        return {"measures": measures,
                "outputs": ["asset.usda", "geo.usdc", "look.usda", "look.mtlx"]}

    return _run_task(spec, fits, work)


def render_task(spec: TaskSpec, subject: Subject, author: dict[str, Any],
                asset_dir: Path) -> dict[str, Any]:
    def work(tmp: Path) -> dict[str, Any]:
        opts = dict(subject.render)
        if "resolution" in opts:
            opts["resolution"] = tuple(opts["resolution"])
        if "aovs" in opts:
            opts["aovs"] = tuple(opts["aovs"])
        options = RenderOptions(**opts, write_uvs=False)
        scene = author_shot(asset_dir / "asset.usda", tmp / "scene.usda")
        doc = render_files(scene, tmp, options, name=subject.name)
        frame = doc["frames"][0]
        return {"measures": frame["measures"], "tasks_seconds": frame["tasks"],
                "outputs": [Path(p).name for p in frame["outputs"].values()]}

    return _run_task(spec, [author], work)


# ------------------------------------------------------------------------------ graph


@dataclass
class BatchResult:
    """Every task's result, by subject and stage; ``failed`` lists failing subjects."""

    tasks: list[dict[str, Any]]
    seconds: float
    workers: int

    @property
    def failed(self) -> list[str]:
        return sorted({t["subject"] for t in self.tasks if t["status"] == "failed"})

    def by_subject(self) -> dict[str, dict[str, Any]]:
        out: dict[str, dict[str, Any]] = {}
        for t in self.tasks:
            row = out.setdefault(t["subject"], {})
            if t["stage"] == "fit":
                row.setdefault("fit", {})[t["unit"]] = t
            else:
                row[t["stage"]] = t
        return out


def regions_of(captures: Path) -> list[str]:
    return list(read_capture_set(captures).regions)


def submit_batch(client: Any, subjects: list[Subject], out_root: Path,
                 stages: tuple[str, ...]) -> tuple[list[Any], dict[str, tuple[str, str, str]]]:
    """Submit every subject's tasks up to the last stage asked for; returns the futures
    and, per task key, (stage, subject, unit) to report a task whose worker kept dying.

    A stage before the last one asked for runs too (a no-op when its output is there)."""
    last = max(STAGES.index(s) for s in stages)
    futures = []
    meta: dict[str, tuple[str, str, str]] = {}
    for subject in subjects:
        try:
            plan = plan_subject(subject, out_root, regions_of(subject.captures))
        except InputError as exc:  # unreadable capture.json: the subject fails, not the batch
            futures.append(client.submit(_failed_plan, subject.name, str(exc),
                                         key=f"plan-{subject.name}-{time.time_ns()}"))
            continue
        ing = plan["ingest"]
        meta.update(_task_names(plan, subject.name))
        f_ing = client.submit(ingest_task, ing, subject, key=f"ingest-{subject.name}-{ing.key}")
        futures.append(f_ing)
        if last < 1:
            continue
        f_fits, fit_dirs = [], []
        for region, spec in plan["fit"].items():
            f_fits.append(client.submit(fit_task, spec, subject, f_ing, ing.out_dir,
                                        key=f"fit-{subject.name}-{region}-{spec.key}"))
            fit_dirs.append(spec.out_dir)
        futures.extend(f_fits)
        if last < 2:
            continue
        aut = plan["author"]
        f_aut = client.submit(author_task, aut, subject, f_fits, fit_dirs, ing.out_dir,
                              key=f"author-{subject.name}-{aut.key}")
        futures.append(f_aut)
        if last < 3:
            continue
        ren = plan["render"]
        futures.append(client.submit(render_task, ren, subject, f_aut, aut.out_dir,
                                     key=f"render-{subject.name}-{ren.key}"))
    return futures, meta


def _task_names(plan: dict[str, Any], subject: str) -> dict[str, tuple[str, str, str]]:
    """Dask key -> (stage, subject, unit) for one subject's tasks."""
    names = {f"{stage}-{subject}-{plan[stage].key}": (stage, subject, stage)
             for stage in ("ingest", "author", "render")}
    for region, spec in plan["fit"].items():
        names[f"fit-{subject}-{region}-{spec.key}"] = ("fit", subject, region)
    return names


def _failed_plan(subject: str, error: str) -> dict[str, Any]:
    return {"stage": "ingest", "subject": subject, "unit": "ingest", "key": "",
            "status": "failed", "seconds": 0.0, "error": error}


def _import_native_libraries() -> Any:
    """A worker plugin that imports pymeshlab on the worker's main thread.

    pymeshlab first imported on a task thread, then USD used on it, corrupts the heap
    at process exit ("malloc_consolidate(): unaligned fastbin chunk"); importing it on
    the main thread first avoids that (reproduced without Dask in a ThreadPoolExecutor).
    """
    from distributed import WorkerPlugin  # lazy: 0.39 s to import

    class NativeImports(WorkerPlugin):
        name = "skinpipe-native-imports"

        def setup(self, worker: Any) -> None:
            import_pymeshlab()

    return NativeImports()


def ignore_interrupts() -> Any:
    """A worker plugin for workers this process started (a local cluster): Ctrl-C at the
    terminal reaches their process group too, and they would print tracebacks while the
    client shuts them down; they ignore SIGINT and are closed by the client instead."""
    from distributed import WorkerPlugin  # lazy: 0.39 s to import

    class IgnoreInterrupts(WorkerPlugin):
        name = "skinpipe-ignore-interrupts"

        def setup(self, worker: Any) -> None:
            import logging
            import signal

            with contextlib.suppress(ValueError):  # not the main thread: nothing to do
                signal.signal(signal.SIGINT, signal.SIG_IGN)
            # tasks cancelled by the client's shutdown are expected, not warnings
            logging.getLogger("distributed.worker.state_machine").setLevel(logging.ERROR)

    return IgnoreInterrupts()


def remove_temporaries(out_root: Path) -> list[Path]:
    """Task folders' temporaries under ``out_root`` (``<subject>/.<stage>.tmp-*``) that
    workers stopped mid-task left; removed, and returned."""
    stale = sorted(out_root.glob("*/.*.tmp-*")) if out_root.is_dir() else []
    for path in stale:
        shutil.rmtree(path, ignore_errors=True)
    for folder in sorted(out_root.iterdir()) if out_root.is_dir() else []:
        if folder.is_dir() and not folder.is_symlink():
            with contextlib.suppress(OSError):  # only an empty one goes: nothing is lost
                folder.rmdir()
    return stale


def run_batch(client: Any, subjects: list[Subject], out_root: Path,
              stages: tuple[str, ...] = STAGES,
              progress: Callable[[int, int, dict[str, Any]], None] | None = None
              ) -> BatchResult:
    """Run the graph on ``client`` and gather every task's result (a task lost with
    its worker is re-run by the scheduler; one lost too often is reported failed)."""
    from distributed import as_completed  # lazy: 0.39 s to import

    bad = [s for s in stages if s not in STAGES]
    if bad or not stages:
        raise InputError(f"unknown stage(s) {bad}; choose from {', '.join(STAGES)}")
    if {"author", "render"} & set(stages):
        lacking = [s.name for s in subjects if s.mesh is None or s.landmarks is None]
        if lacking:
            raise InputError(f"subject(s) {lacking}: the author and render stages need "
                             "\"mesh\" and \"landmarks\" (or run --stages ingest,fit)")
    start = time.perf_counter()
    out_root.mkdir(parents=True, exist_ok=True)
    client.register_plugin(_import_native_libraries())
    futures, meta = submit_batch(client, subjects, out_root, stages)
    results = []
    for n, fut in enumerate(as_completed(futures), start=1):
        try:
            res = fut.result()
        except Exception as exc:  # e.g. KilledWorker after repeated worker deaths
            stage, subject, unit = meta.get(fut.key, ("?", "?", fut.key))
            res = {"stage": stage, "subject": subject, "unit": unit,
                   "status": "failed", "seconds": 0.0, "error": f"{type(exc).__name__}: {exc}"}
        results.append(res)
        if progress:
            progress(n, len(futures), res)
    workers = len(client.scheduler_info().get("workers", {}))
    order = {s: i for i, s in enumerate(STAGES)}
    results.sort(key=lambda r: (r["subject"], order.get(r["stage"], 9), r["unit"]))
    return BatchResult(results, time.perf_counter() - start, workers)


def summary_table(result: BatchResult) -> str:
    """One line per subject: each stage's status and seconds (fits summed)."""
    lines = [f"{'subject':<14} " + " ".join(f"{s:>16}" for s in STAGES)]
    for subject, row in result.by_subject().items():
        cells = []
        for stage in STAGES:
            entry = row.get(stage)
            if stage == "fit" and entry:
                fits = list(entry.values())
                states = {f["status"] for f in fits}
                status = "failed" if "failed" in states else (
                    "skipped" if "skipped" in states else "/".join(sorted(states)))
                secs = sum(f["seconds"] for f in fits)
            elif entry:
                status, secs = entry["status"], entry["seconds"]
            else:
                cells.append(f"{'-':>16}")
                continue
            cells.append(f"{status + f' {secs:.1f}s':>16}")
        lines.append(f"{subject:<14} " + " ".join(cells))
    return "\n".join(lines)


def batch_document(result: BatchResult, out_root: Path, stages: tuple[str, ...]
                   ) -> dict[str, Any]:
    """What batch.json holds: per subject and stage, status, seconds, measures, outputs
    (absolute paths) and errors."""
    subjects = {}
    for subject, row in result.by_subject().items():
        entry: dict[str, Any] = {}
        for stage, value in row.items():
            items = value.values() if stage == "fit" else [value]
            for t in items:
                if "outputs" in t:
                    t = {**t, "outputs": [str(Path(t["dir"]) / o) for o in t["outputs"]]}
                if stage == "fit":
                    entry.setdefault("fit", {})[t["unit"]] = t
                else:
                    entry[stage] = t
        subjects[subject] = entry
    counts: dict[str, int] = {}
    for t in result.tasks:
        counts[t["status"]] = counts.get(t["status"], 0) + 1
    retried = [{"subject": t["subject"], "stage": t["stage"], "unit": t["unit"],
                "attempts": t["attempts"], "why": t["retried_because"]}
               for t in result.tasks if t.get("attempts", 1) > 1]
    return {"stages": list(stages), "workers": result.workers, "seconds": result.seconds,
            "tasks": counts, "failed_subjects": result.failed, "retried": retried,
            "subjects": subjects}
