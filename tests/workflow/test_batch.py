"""Batch runs on a real distributed.LocalCluster (2 worker processes): idempotent
hash-keyed tasks, a worker killed mid-batch, a corrupt subject, atomic outputs."""

from __future__ import annotations

import json
import os
import shutil
import signal
import threading
import time
from pathlib import Path

import pytest

from skinpipe.cli import main
from skinpipe.errors import InputError
from skinpipe.fileio import relocate_paths
from skinpipe.workflow.batch import read_batch

SAMPLE = Path(__file__).resolve().parents[2] / "skinpipe" / "samples"


def _write_batch(root: Path, names: list[str], **defaults: object) -> Path:
    doc = {"defaults": {"k": 4, **defaults},
           "subjects": [{"name": n, "captures": f"captures_{n}"} for n in names]}
    path = root / "batch.json"
    path.write_text(json.dumps(doc))
    return path


def _copy_captures(root: Path, name: str) -> Path:
    return Path(shutil.copytree(SAMPLE / "captures", root / f"captures_{name}"))


@pytest.fixture(scope="module")
def cluster():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as c:
        yield c


def _statuses(out: Path) -> dict[tuple[str, str, str], str]:
    doc = json.loads((out / "batch.json").read_text())
    got = {}
    for subject, row in doc["subjects"].items():
        for stage, entry in row.items():
            for t in (entry.values() if stage == "fit" else [entry]):
                got[(subject, stage, t["unit"])] = t["status"]
    return got


@pytest.mark.slow  # 42 s; the default run kills real workers in the test after next
def test_batch_survives_a_killed_worker_and_a_corrupt_subject_and_is_idempotent(
        cluster, tmp_path: Path) -> None:
    for name in ("a", "b", "c"):
        _copy_captures(tmp_path, name)
    bad = tmp_path / "captures_c" / "lips" / "e2.tif"
    bad.write_bytes(bad.read_bytes()[:1000])  # truncated: unreadable image
    batch = _write_batch(tmp_path, ["a", "b", "c"])
    out = tmp_path / "out"
    args = ["batch", str(batch), "--scheduler", cluster.scheduler_address,
            "--stages", "ingest,fit", "-o", str(out)]

    codes: list[int] = []
    runner = threading.Thread(target=lambda: codes.append(main(args)))
    runner.start()
    deadline = time.monotonic() + 600  # a hang guard, not a time limit
    busy: list = []
    while not busy and time.monotonic() < deadline:  # the scheduler lives in this process
        busy = [ws for ws in cluster.scheduler.workers.values() if ws.processing]
        time.sleep(0.02)
    assert busy, "no task started"
    os.kill(busy[0].pid, signal.SIGKILL)  # a worker dies mid-task
    runner.join(timeout=300)
    assert codes == [1]  # subject c failed
    first = _statuses(out)
    assert first[("c", "ingest", "ingest")] == "failed"
    assert all(first[("c", "fit", r)] == "skipped" for r in ("lips", "nose"))
    ok = {k: v for k, v in first.items() if k[0] != "c"}
    assert len(ok) == 2 * 7 and set(ok.values()) == {"done"}
    doc = json.loads((out / "batch.json").read_text())
    assert "e2.tif" in doc["subjects"]["c"]["ingest"]["error"]
    for subject in ("a", "b"):  # every finished directory is whole
        assert (out / subject / "ingest" / "done.json").is_file()
        for region in ("forehead", "lips", "chin", "cheekbone", "cheek", "nose"):
            fit_dir = out / subject / "fit" / region
            assert json.loads((fit_dir / "done.json").read_text())["status"] == "done"
            assert (fit_dir / f"{region}.json").stat().st_size > 0
            assert doc["subjects"][subject]["fit"][region]["measures"]["fit_error_eq2c"]

    # a re-run does no work
    assert main(args) == 1
    again = _statuses(out)
    assert {v for k, v in again.items() if k[0] != "c"} == {"cached"}

    # changing one subject's capture re-runs that subject only
    cap = tmp_path / "captures_b" / "capture.json"
    cap.write_text(cap.read_text() + "\n")
    assert main(args) == 1
    third = _statuses(out)
    assert {v for k, v in third.items() if k[0] == "a"} == {"cached"}
    assert {v for k, v in third.items() if k[0] == "b"} == {"done"}


@pytest.mark.slow  # 27-32 s (xatlas unwrap, author, render on workers); the default run
# keeps the real-scheduler test, and the demo runs the same author and render stages
def test_batch_runs_author_and_render_for_a_subject(cluster, tmp_path: Path) -> None:
    _copy_captures(tmp_path, "face")
    batch = _write_batch(
        tmp_path, ["face"], mesh="pymeshlab:rangemaps/face000.ply",
        landmarks=str(SAMPLE / "face" / "landmarks.json"),
        render={"resolution": [96, 96], "texture_size": 256, "light_samples": 2})
    out = tmp_path / "out"
    assert main(["batch", str(batch), "--scheduler", cluster.scheduler_address,
                 "-o", str(out)]) == 0
    status = _statuses(out)
    assert status[("face", "author", "author")] == "done"
    assert status[("face", "render", "render")] == "done"
    doc = json.loads((out / "batch.json").read_text())
    render = doc["subjects"]["face"]["render"]
    assert 0.99 < render["measures"]["diffusion"]["energy_ratio"] < 1.01
    assert any(p.endswith("face.exr") and Path(p).is_file() for p in render["outputs"])
    assert (out / "face" / "asset" / "albedo.exr").is_file()
    # the render did not write into the author stage's asset: its key still matches
    assert main(["batch", str(batch), "--scheduler", cluster.scheduler_address,
                 "-o", str(out)]) == 0
    assert set(_statuses(out).values()) == {"cached"}


@pytest.mark.parametrize(("subjects", "message"), [
    ([{"name": "a", "captures": "nowhere"}], "does not exist"),
    ([{"name": "a", "captures": "."}, {"name": "a", "captures": "."}], "unique"),
    ([{"name": "a", "captures": ".", "colour": 1}], "unknown key"),
    ([{"name": "a b", "captures": "."}], "identifier"),
    ([], "non-empty"),
    ([{"name": "a", "captures": ".", "k": 0}], "k must be"),
])
def test_read_batch_rejects_bad_files(tmp_path: Path, subjects: list, message: str) -> None:
    path = tmp_path / "batch.json"
    path.write_text(json.dumps({"subjects": subjects}))
    with pytest.raises(InputError, match=message):
        read_batch(path)


def test_batch_cli_reports_a_bad_batch_file(tmp_path: Path, capsys) -> None:
    path = tmp_path / "batch.json"
    path.write_text("{not json")
    assert main(["batch", str(path), "-o", str(tmp_path / "out")]) == 2
    assert "batch.json" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def _without_run_facts(doc: object) -> object:
    """A record with its run facts (seconds, attempts) left out."""
    if isinstance(doc, dict):
        return {k: _without_run_facts(v) for k, v in doc.items()
                if "seconds" not in k and k not in ("attempts", "retried_because")}
    if isinstance(doc, list):
        return [_without_run_facts(v) for v in doc]
    return doc


def _contents(out: Path) -> dict[str, object]:
    """Every output of a batch: content files (profiles, HDR images, fits) byte for
    byte; the ingest report with its run facts (seconds) and paths into the root left
    out. batch.json and done.json are run records."""
    got: dict[str, object] = {}
    for path in sorted(out.rglob("*")):
        rel = str(path.relative_to(out))
        if path.name == "ingest.json":
            got[rel] = relocate_paths(_without_run_facts(json.loads(path.read_text())),
                                      str(out), "<out>")
        elif path.is_file() and path.name not in ("batch.json", "done.json"):
            got[rel] = path.read_bytes()
    return got


@pytest.mark.timeout(600)
def test_real_scheduler_and_workers_with_one_killed(tmp_path: Path) -> None:
    """`dask scheduler` and two `dask worker` processes on 127.0.0.1; the busy workers
    are SIGKILLed mid-task. The batch completes, equal to a clean run, no temporary
    left, the retry recorded."""
    import subprocess
    import sys

    distributed = pytest.importorskip("distributed")
    for name in ("a", "b"):
        _copy_captures(tmp_path, name)
    batch = _write_batch(tmp_path, ["a", "b"])
    sched_file = tmp_path / "scheduler.json"
    py = sys.executable
    procs = [subprocess.Popen([py, "-m", "distributed.cli.dask_scheduler", "--host",
                               "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(sched_file)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        deadline = time.monotonic() + 600  # a hang guard, not a time limit
        while not sched_file.is_file() and time.monotonic() < deadline:
            time.sleep(0.1)
        address = json.loads(sched_file.read_text())["address"]
        procs += [subprocess.Popen([py, "-m", "distributed.cli.dask_worker", address,
                                    "--nthreads", "1", "--host", "127.0.0.1",
                                    "--no-dashboard"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                  for _ in range(2)]
        with distributed.Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=120)
            clean, killed = tmp_path / "clean", tmp_path / "killed"
            assert main(["batch", str(batch), "--scheduler", address, "--stages",
                         "ingest,fit", "-o", str(clean)]) == 0
            codes: list[int] = []
            runner = threading.Thread(target=lambda: codes.append(main(
                ["batch", str(batch), "--scheduler", address, "--stages", "ingest,fit",
                 "-o", str(killed)])))
            runner.start()
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and not list(killed.rglob(".*.tmp-*")):
                time.sleep(0.02)
            assert list(killed.rglob(".*.tmp-*")), "no task started"
            pids = client.run(os.getpid)
            for addr, keys in client.processing().items():
                if keys:  # every busy worker dies mid-task (its nanny starts a new one)
                    os.kill(pids[addr], signal.SIGKILL)
            runner.join(timeout=400)
            assert codes == [0]
        assert not [p for p in killed.rglob("*") if ".tmp-" in p.name or ".old-" in p.name]
        assert _contents(killed) == _contents(clean)
        doc = json.loads((killed / "batch.json").read_text())
        assert doc["retried"] and all(r["attempts"] >= 2 and "worker" in r["why"]
                                      for r in doc["retried"])
        # records name final paths, never the temporary directory they were written in
        assert ".tmp-" not in (killed / "a" / "ingest" / "ingest.json").read_text()
    finally:
        for p in procs:
            p.kill()
            p.wait(timeout=30)


def test_batch_never_replaces_a_folder_it_did_not_make(cluster, tmp_path: Path) -> None:
    """On a real Dask cluster: a user's folder where a task would write (no done.json)
    fails that task with the folder named, keeps the folder's files, and skips what
    depends on it; batch.json of someone else is refused before anything runs."""
    from skinpipe.cli import main

    _copy_captures(tmp_path, "a")
    batch = _write_batch(tmp_path, ["a"])
    out = tmp_path / "out"
    mine = out / "a" / "ingest" / "notes.txt"
    mine.parent.mkdir(parents=True)
    mine.write_text("mine\n")
    assert main(["batch", str(batch), "--scheduler", cluster.scheduler_address,
                 "--stages", "ingest,fit", "-o", str(out)]) == 1
    assert mine.read_text() == "mine\n"
    statuses = _statuses(out)
    assert statuses[("a", "ingest", "ingest")] == "failed"
    assert {s for (_, stage, _), s in statuses.items() if stage == "fit"} == {"skipped"}
    other = tmp_path / "other"
    other.mkdir()
    (other / "batch.json").write_text("{}")
    assert main(["batch", str(batch), "--scheduler", cluster.scheduler_address,
                 "-o", str(other)]) == 2
    assert (other / "batch.json").read_text() == "{}"


def test_a_relative_output_root_means_the_clients_folder_on_a_real_cluster(
        tmp_path: Path) -> None:
    """A scheduler and a worker started as a farm starts them (``dask scheduler``,
    ``dask worker``), the worker in a folder of its own: ``-o rel`` given to the client
    puts every output, and batch.json with absolute paths, in the client's folder."""
    import subprocess
    import sys

    client_dir, worker_dir = tmp_path / "client", tmp_path / "worker"
    client_dir.mkdir()
    worker_dir.mkdir()
    _copy_captures(client_dir, "a")
    _write_batch(client_dir, ["a"])
    address_file = tmp_path / "scheduler.json"
    daemons = [subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
         "--port", "0", "--scheduler-file", str(address_file), "--no-dashboard"],
        cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        for _ in range(600):  # the scheduler writes its address when it listens
            if address_file.is_file() and address_file.stat().st_size:
                break
            time.sleep(0.1)
        address = json.loads(address_file.read_text())["address"]
        daemons.append(subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_worker", address, "--nworkers", "1",
             "--nthreads", "1", "--no-dashboard"], cwd=worker_dir,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        run = subprocess.run([sys.executable, "-m", "skinpipe", "batch", "batch.json",
                              "--scheduler", address, "--stages", "ingest", "-o", "rel"],
                             cwd=client_dir, capture_output=True, text=True, timeout=600)
    finally:
        for daemon in reversed(daemons):
            daemon.terminate()
            daemon.wait(timeout=60)
    assert run.returncode == 0, run.stderr[-2000:]
    assert not any(worker_dir.iterdir())  # nothing in the worker's folder
    doc = json.loads((client_dir / "rel" / "batch.json").read_text())
    outputs = doc["subjects"]["a"]["ingest"]["outputs"]
    assert outputs and all(Path(p).is_absolute() and Path(p).is_file() for p in outputs)
    assert all(Path(p).is_relative_to(client_dir / "rel") for p in outputs)


def test_the_local_clusters_dashboard_serves_or_names_what_it_needs(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """--dashboard: a real dashboard answering HTTP where bokeh is installed (the dev
    extra has it); without bokeh an error naming the extra, before any worker starts."""
    import importlib.util
    import urllib.request

    from skinpipe.cli.batch import local_cluster

    with local_cluster(1, "127.0.0.1:0") as cluster:
        link = cluster.dashboard_link
        with urllib.request.urlopen(link, timeout=60) as page:
            assert page.status == 200
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "bokeh" else real(name, *a))
    with pytest.raises(InputError, match=r"skinpipe\[dashboard\]"):
        local_cluster(1, "127.0.0.1:0")
