"""Hostile input and faults, verb by verb: each must end with exit 1 or 2, one line on
stderr naming the file and the value, no traceback, no signal, nothing written and no
input changed.

Every case runs ``skinpipe`` in a child process (a signal there is a failure here, not a
dead test run) inside a copy of one small workspace, and compares the workspace's files
(bytes and modification times) before and after.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from skinpipe.capture.simulate import (
    CaptureSettings,
    sample_subject_truths,
    simulate_capture_set,
)
from skinpipe.profile.io import write_fit_json, write_profile_csv

from ..reference_profiles import deon_profile
from ..render_scenes import deon_fit, distant_down, patch_asset, scene_over, top_camera

# --------------------------------------------------------------------------- workspace

OBJ_QUAD = "v 0 0 0\nv 10 0 0\nv 0 10 0\nv 10 10 0\n"


def _build_workspace(root: Path) -> None:
    truths = [t for t in sample_subject_truths() if t.name in ("forehead", "cheek")]
    simulate_capture_set(truths, root / "caps", CaptureSettings(size_px=96), seed=1)
    write_profile_csv(root / "forehead.csv", deon_profile())
    (root / "fits").mkdir()
    for name in ("forehead", "cheek"):
        write_fit_json(root / "fits" / f"{name}.json", deon_fit(name))
    asset = patch_asset(root / "asset", [deon_fit("forehead")])
    scene = scene_over(asset, root / "scene.usda", lambda st: (top_camera(st), distant_down(st)))
    text = scene.read_text()  # relative, so that a copy of the workspace is whole
    scene.write_text(text.replace(f"@{asset}@", "@./asset/asset.usda@"))
    (root / "mesh.obj").write_text(OBJ_QUAD + "f 1 2 3\nf 2 4 3\n")
    (root / "landmarks.json").write_text(json.dumps(
        {"regions": {"forehead": [[0, 0, 0]], "cheek": [[10, 10, 0]]}}))
    deep = "[" * 20000 + "]" * 20000
    (root / "deep.usda").write_text(f"#usda 1.0\n(\n customLayerData = {{ int[] x = {deep} }}\n)\n")
    (root / "shallow.usda").write_text('#usda 1.0\n(\n subLayers = [@./deep.usda@]\n)\n')
    (root / "payload.usda").write_text('#usda 1.0\ndef "A" (prepend payload = @./deep.usda@) {}\n')


@pytest.fixture(scope="module")
def pristine(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("pristine")
    _build_workspace(root)
    return root


@pytest.fixture
def ws(pristine: Path, tmp_path: Path) -> Path:
    root = tmp_path / "ws"
    shutil.copytree(pristine, root)
    return root


def _snapshot(root: Path) -> dict[str, tuple[int, str]]:
    return {str(p.relative_to(root)): (p.stat().st_mtime_ns,
                                       hashlib.sha256(p.read_bytes()).hexdigest())
            for p in sorted(root.rglob("*")) if p.is_file()}


def _dirs(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_dir()}


def skinpipe(ws: Path, *args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", "import sys; from skinpipe.cli import main; "
                           "sys.exit(main(sys.argv[1:]))", *args], cwd=ws, capture_output=True,
                          text=True, timeout=timeout, env={**os.environ, "PYTHONPATH": str(
                              Path(__file__).resolve().parents[2])})


def assert_refused(ws: Path, proc: subprocess.CompletedProcess[str], *names: str,
                   before: dict[str, tuple[int, str]], dirs: set[str]) -> None:
    """Exit 1 or 2, no signal, no traceback, the last stderr line an error naming each
    of ``names``, the workspace untouched (no file changed, added or removed)."""
    err = proc.stderr.strip().splitlines()
    assert proc.returncode in (1, 2), (proc.returncode, proc.stderr[-2000:])
    assert "Traceback" not in proc.stderr, proc.stderr[-2000:]
    one_line = bool(err) and err[-1].startswith("skinpipe ")
    if proc.args[3] == "validate" and not one_line:  # usdchecker-style: then Failed!
        assert proc.stdout.strip().endswith("Failed!"), proc.stdout[-1000:]
        last = proc.stdout + proc.stderr
    else:
        assert err and err[-1].startswith("skinpipe ") and (": error: " in err[-1] or
                                                           ": failed: " in err[-1]), err[-3:]
        last = err[-1]
    for name in names:
        assert name in last, (name, last[-1000:])
    assert _snapshot(ws) == before, "the workspace changed"
    assert _dirs(ws) == dirs, "folders were left behind"


Case = tuple[str, Callable[[Path], None] | None, list[str], list[str]]

CASES: list[Case] = [
    # 1. pymeshlab's reader would SIGSEGV on this face line
    ("author-segv-obj", lambda w: (w / "mesh.obj").write_text(OBJ_QUAD + "f 1 2 -999999\n"),
     ["author", "--fits", "fits", "--mesh", "mesh.obj", "--landmarks", "landmarks.json",
      "-o", "out"], ["mesh.obj", "line 5", "-999999"]),
    ("run-segv-obj", lambda w: (w / "mesh.obj").write_text(OBJ_QUAD + "f 1 2 -999999\n"),
     ["run", "caps", "--mesh", "mesh.obj", "--landmarks", "landmarks.json", "-o", "out"],
     ["mesh.obj", "-999999"]),
    # 2. USD's parser would crash on a deep layer reached through a sublayer or payload
    ("validate-deep-sublayer", None, ["validate", "shallow.usda"], ["deep.usda", "nested"]),
    ("shot-deep-sublayer", None, ["shot", "shallow.usda", "-o", "s.usda"], ["deep.usda"]),
    ("render-deep-payload", None, ["render", "payload.usda", "-o", "out"], ["deep.usda"]),
    # 3. no verb writes over what it reads, or over a file skinpipe did not write
    ("shot-over-look", None, ["shot", "asset/asset.usda", "-o", "asset/look.usda"],
     ["look.usda", "input"]),
    ("validate-junit-over-asset", None,
     ["validate", "asset/asset.usda", "--junit", "asset/asset.usda"], ["asset.usda"]),
    ("fit-over-its-csv", None, ["fit", "forehead.csv", "-o", "forehead.csv"],
     ["forehead.csv", "input"]),
    ("ingest-over-user-file", lambda w: (w / "caps" / "cheek.csv").write_text("mine\n"),
     ["ingest", "caps", "-o", "caps"], ["cheek.csv", "did not write"]),
    ("simulate-over-captures", None, ["simulate", "-o", "caps"], ["capture.json"]),
    ("report-over-a-users-page", lambda w: (w / "fits" / "report.md").write_text("mine\n"),
     ["report", "fit", "forehead.csv", "--k", "1:1", "-o", "fits"], ["report.md"]),
    # 4. names that become paths
    ("ingest-region-traversal", lambda w: _rename_region(w, "../../../escaped_region"),
     ["ingest", "caps", "-o", "out"], ["capture.json", "escaped_region"]),
    ("render-name-traversal", None,
     ["render", "scene.usda", "--name", "../../x", "-o", "out"], ["../../x"]),
    # 5. corrupt meshes the loader would repair without a word
    ("author-nan-vertex", lambda w: (w / "mesh.obj").write_text(
        OBJ_QUAD.replace("v 10 10 0", "v nan 10 0") + "f 1 2 3\nf 2 4 3\n"),
     ["author", "--fits", "fits", "--mesh", "mesh.obj", "--landmarks", "landmarks.json",
      "-o", "out"], ["mesh.obj", "line 4"]),
    ("author-unparseable-vertex", lambda w: (w / "mesh.obj").write_text(
        OBJ_QUAD.replace("v 10 10 0", "v a b c") + "f 1 2 3\nf 2 4 3\n"),
     ["author", "--fits", "fits", "--mesh", "mesh.obj", "--landmarks", "landmarks.json",
      "-o", "out"], ["line 4", "v a b c"]),
    ("author-face-out-of-range", lambda w: (w / "mesh.obj").write_text(
        OBJ_QUAD + "f 1 2 3\nf 2 9 3\n"),
     ["author", "--fits", "fits", "--mesh", "mesh.obj", "--landmarks", "landmarks.json",
      "-o", "out"], ["line 6", "'9'"]),
    ("author-zero-area-face", lambda w: (w / "mesh.obj").write_text(
        OBJ_QUAD + "f 1 2 3\nf 2 2 3\n"),
     ["author", "--fits", "fits", "--mesh", "mesh.obj", "--landmarks", "landmarks.json",
      "-o", "out"], ["line 6", "no area"]),
    ("author-landmarks-far-away", lambda w: (w / "landmarks.json").write_text(json.dumps(
        {"regions": {"forehead": [[2000, 2000, 0]], "cheek": [[10, 10, 0]]}})),
     ["author", "--fits", "fits", "--mesh", "mesh.obj", "--landmarks", "landmarks.json",
      "-o", "out"], ["forehead", "from the nearest mesh vertex"]),
    # 6. values that used to give a silent bad result
    ("render-nan-camera", lambda w: _nan_camera(w),
     ["render", "scene.usda", "-o", "out", "--resolution", "32x32"], ["/Cam", "not finite"]),
    ("render-clipping-inverted", lambda w: _clipping(w, (100.0, 1.0)),
     ["render", "scene.usda", "-o", "out", "--resolution", "32x32"], ["clipping range"]),
    ("render-variance-grid-negative", None,
     ["render", "scene.usda", "-o", "out", "--variance-grid", "-3"], ["-3"]),
    ("author-blend-negative", None,
     ["author", "--fits", "fits", "--mesh", "mesh.obj", "--landmarks", "landmarks.json",
      "--blend-mm", "-5", "-o", "out"], ["-5"]),
    ("author-landmarks-lack-a-fit", lambda w: (w / "landmarks.json").write_text(json.dumps(
        {"regions": {"forehead": [[0, 0, 0]]}})),
     ["author", "--fits", "fits", "--mesh", "mesh.obj", "--landmarks", "landmarks.json",
      "-o", "out"], ["cheek", "no region"]),
    ("fit-negative-value", lambda w: _negative_value(w),
     ["fit", "forehead.csv", "-o", "fit.json"], ["forehead.csv", "negative"]),
    ("ingest-mm-per-pixel-true", lambda w: _manifest(w, mm_per_pixel=True),
     ["ingest", "caps", "-o", "out"], ["capture.json", "mm_per_pixel"]),
    # 7. where the outputs go
    ("fit-parent-is-a-file", lambda w: (w / "afile").write_text("x"),
     ["fit", "forehead.csv", "-o", "afile/fit.json"], ["afile", "is a file"]),
    ("render-output-is-a-file", lambda w: (w / "out").write_text("x"),
     ["render", "scene.usda", "-o", "out"], ["out", "is a file"]),
    # 8. the CI validator and the readers of assets
    ("validate-string-variances", lambda w: _edit_look(w, "float[] variances = [",
                                                      'string variances = "lots"\n#['),
     ["validate", "asset/asset.usda"], []),
    ("inspect-string-variances", lambda w: _edit_look(w, "float[] variances = [",
                                                     'string variances = "lots"\n#['),
     ["inspect", "asset/asset.usda"], ["variances", "expected numbers"]),
    ("render-invalid-utf8", lambda w: _bytes_into_look(w, b"\xff\xfe"),
     ["render", "scene.usda", "-o", "out"], ["look.usda", "UTF-8"]),
    ("validate-truncated-geo", lambda w: _truncate(w / "asset" / "geo.usdc"),
     ["validate", "asset/asset.usda"], []),
    ("inspect-truncated-geo", lambda w: _truncate(w / "asset" / "geo.usdc"),
     ["inspect", "asset/asset.usda"], ["geo.usdc", "truncated"]),
    ("paint-albedo-deep-look", lambda w: _edit_look(w, "(\n", "(\n customLayerData = { int[] x "
                                                    "= " + "[" * 3000 + "]" * 3000 + " }\n"),
     ["paint-albedo", "asset/asset.usda", "--size", "64"], ["look.usda", "nested"]),
    # 9. bounds instead of hangs
    ("fit-two-million-rows", lambda w: _big_csv(w / "big.csv", 2_000_000),
     ["fit", "big.csv", "-o", "big.json"], ["big.csv", "2000001 rows"]),
    ("simulate-hair-100000", None, ["simulate", "--hair", "100000", "-o", "sim"],
     ["hair_strands"]),
    # 10. a chain's inputs are checked before its first write
    ("run-k-out-of-range", None,
     ["run", "caps", "--mesh", "mesh.obj", "--landmarks", "landmarks.json", "-k", "99",
      "-o", "out"], ["99"]),
    ("run-landmarks-other-regions", lambda w: (w / "landmarks.json").write_text(json.dumps(
        {"regions": {"forehead": [[0, 0, 0]], "nose": [[10, 10, 0]]}})),
     ["run", "caps", "--mesh", "mesh.obj", "--landmarks", "landmarks.json", "-o", "out"],
     ["landmarks.json", "nose"]),
    # 11. accepted silently before
    ("shot-key-intensity-nan", None,
     ["shot", "asset/asset.usda", "--key-intensity", "nan", "-o", "s.usda"],
     ["key-intensity", "nan"]),
    ("shot-key-intensity-negative", None,
     ["shot", "asset/asset.usda", "--key-intensity", "-3", "-o", "s.usda"], ["-3"]),
    ("shot-turntable-negative", None,
     ["shot", "asset/asset.usda", "--turntable", "-5", "-o", "s.usda"], ["turntable", "-5"]),
    ("shot-usd-into-png", None, ["shot", "asset/asset.usda", "-o", "x.png"], ["x.png", ".png"]),
    ("fit-ragged-row", lambda w: (w / "r.csv").write_text(
        "radius_mm,R,G,B\n0.1,1,1,1\n0.2,1,1,1,5\n"), ["fit", "r.csv", "-o", "r.json"],
     ["r.csv", "line 3", "5 cells"]),
    ("fit-no-generations", None,
     ["fit", "forehead.csv", "--generations", "0", "--population", "1", "-o", "f.json"],
     ["generations", "0"]),
    ("fit-a-binary-file", None, ["fit", "asset/geo.usdc", "-o", "f.json"],
     ["geo.usdc", "not a CSV"]),
    ("ingest-missing-folder", None, ["ingest", "nowhere", "-o", "out"],
     ["nowhere", "no such capture folder"]),
    ("ingest-a-file", None, ["ingest", "forehead.csv", "-o", "out"],
     ["forehead.csv", "not a folder"]),
    ("render-missing-ocio", None,
     ["render", "scene.usda", "--ocio", "missing.ocio", "-o", "out"], ["missing.ocio"]),
    ("render-usd-syntax-error", lambda w: _edit_look(w, "float[] variances = [",
                                                    "float[] variances = [[["),
     ["render", "scene.usda", "-o", "out"], ["look.usda:", "parse error"]),
    ("ingest-exposure-1e308", lambda w: _exposure(w, 1e308), ["ingest", "caps", "-o", "out"],
     ["capture.json", "exposure_s", "1e+308"]),
    ("author-stray-vertex", lambda w: (w / "mesh.obj").write_text(
        OBJ_QUAD + "v 1000000 0 0\nf 1 2 3\nf 2 4 3\nf 2 5 4\n"),
     ["author", "--fits", "fits", "--mesh", "mesh.obj", "--landmarks", "landmarks.json",
      "-o", "out"], ["mesh.obj", "stray vertex"]),
    ("author-unused-far-vertex-widens-nothing", lambda w: (
        (w / "mesh.obj").write_text(OBJ_QUAD + "v 1000000 0 0\nf 1 2 3\nf 2 4 3\n"),
        (w / "landmarks.json").write_text(json.dumps(
            {"regions": {"forehead": [[0, 0, 0]], "cheek": [[730, 10, 0]]}}))),
     ["author", "--fits", "fits", "--mesh", "mesh.obj", "--landmarks", "landmarks.json",
      "-o", "out"], ["cheek", "from the nearest mesh vertex"]),
    # 12. what validate fails, render refuses, under the same rule's name
    ("render-huge-variance", lambda w: _profile_edit(w, "variances", 1e30),
     ["render", "scene.usda", "-o", "out"], ["ProfileVariancesValid", "1e+30"]),
    ("validate-huge-variance", lambda w: _profile_edit(w, "variances", 1e30),
     ["validate", "scene.usda"], ["ProfileVariancesValid", "1e+30"]),
    ("render-nan-weight", lambda w: _profile_edit(w, "weights", float("nan")),
     ["render", "scene.usda", "-o", "out"], ["ProfileWeightsNormalized", "weights"]),
    # 13. an override layer that does not restate the asset's units
    ("render-units-not-restated", lambda w: (w / "over.usda").write_text(
        "#usda 1.0\n(\n subLayers = [@./scene.usda@]\n)\n"),
     ["render", "over.usda", "-o", "out"], ["metersPerUnit", "over.usda", "0.001"]),
]


@pytest.mark.parametrize("case", CASES, ids=lambda c: c[0])
def test_hostile_input_is_refused_cleanly(ws: Path, case: Case) -> None:
    _, prepare, args, names = case
    if prepare is not None:
        prepare(ws)
    before, dirs = _snapshot(ws), _dirs(ws)
    proc = skinpipe(ws, *args)
    assert_refused(ws, proc, *names, before=before, dirs=dirs)


def test_render_never_replaces_the_asset_texture(ws: Path) -> None:
    from skinpipe.workflow.albedo import bake_sample_albedo

    bake_sample_albedo(ws / "asset" / "asset.usda", 64)
    before, dirs = _snapshot(ws), _dirs(ws)
    proc = skinpipe(ws, "render", "scene.usda", "--name", "albedo", "-o", "asset",
                    "--resolution", "32x32")
    assert_refused(ws, proc, "albedo.exr", before=before, dirs=dirs)


def test_force_writes_over_a_file_skinpipe_did_not_write(ws: Path) -> None:
    (ws / "fit.json").write_text("{}")
    assert skinpipe(ws, "fit", "forehead.csv", "-o", "fit.json").returncode == 2
    proc = skinpipe(ws, "fit", "forehead.csv", "-o", "fit.json", "--force")
    assert proc.returncode == 0, proc.stderr
    assert json.loads((ws / "fit.json").read_text())["terms"]
    # and a re-run into skinpipe's own output needs no --force
    assert skinpipe(ws, "fit", "forehead.csv", "-o", "fit.json").returncode == 0


# ------------------------------------------------------------------------------ faults


def test_disk_full_while_ingesting_leaves_nothing(ws: Path, monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """The third file written fails with ENOSPC: no output at all remains (the stage is
    removed), and the error is one line."""
    import errno

    from skinpipe import fileio
    from skinpipe.cli import main

    real = fileio.os.fsync
    calls = {"n": 0}

    def full(fd: int) -> None:
        calls["n"] += 1
        if calls["n"] == 3:
            raise OSError(errno.ENOSPC, "No space left on device", "forehead.exr")
        real(fd)

    monkeypatch.setattr(fileio.os, "fsync", full)
    monkeypatch.chdir(ws)
    before, dirs = _snapshot(ws), _dirs(ws)
    assert main(["ingest", "caps", "-o", "out"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "disk is full" in err[-1] and "Traceback" not in "\n".join(err)
    assert _snapshot(ws) == before and _dirs(ws) == dirs


def test_read_only_output_is_one_line(ws: Path, monkeypatch: pytest.MonkeyPatch,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    """A read-only file system (os.replace raising EROFS, as it does there even for
    root) ends in one line naming the file, and nothing is left."""
    import errno

    from skinpipe import fileio
    from skinpipe.cli import main

    def read_only(src: str, dst: str) -> None:
        raise OSError(errno.EROFS, "Read-only file system", str(dst))

    monkeypatch.setattr(fileio.os, "replace", read_only)
    monkeypatch.chdir(ws)
    before = _snapshot(ws)
    assert main(["fit", "forehead.csv", "-o", "fit.json"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "read-only file system" in err[-1] and "fit.json" in err[-1]
    assert _snapshot(ws) == before


def test_a_crashing_reader_child_is_an_error(ws: Path) -> None:
    """pymeshlab's reader killed by a signal in its child process (the pre-check
    bypassed) is a one-line InputError here."""
    from skinpipe.errors import InputError
    from skinpipe.usd.mesh_files import MeshFileFacts, load_in_child

    (ws / "segv.obj").write_text(OBJ_QUAD + "f 1 2 -999999\n")
    with pytest.raises(InputError, match="crashed"):
        load_in_child(ws / "segv.obj", MeshFileFacts(4, 1))


def test_unexpected_errors_are_one_line(monkeypatch: pytest.MonkeyPatch,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    """A bug is reported in one line (the traceback only with SKINPIPE_DEBUG=1)."""
    from skinpipe.cli import main
    from skinpipe.cli import simulate as verb

    def boom(args: object) -> int:
        raise ZeroDivisionError("division by zero")

    monkeypatch.setattr(verb, "cmd_simulate", boom)
    monkeypatch.delenv("SKINPIPE_DEBUG", raising=False)
    assert main(["simulate", "-o", "x"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "internal error: ZeroDivisionError: division by zero" in err[0]


# --------------------------------------------------------------------------- helpers


def _rename_region(ws: Path, name: str) -> None:
    doc = json.loads((ws / "caps" / "capture.json").read_text())
    doc["regions"][name] = doc["regions"].pop("cheek")
    (ws / "caps" / "capture.json").write_text(json.dumps(doc))


def _manifest(ws: Path, **changes: object) -> None:
    doc = json.loads((ws / "caps" / "capture.json").read_text())
    doc.update(changes)
    (ws / "caps" / "capture.json").write_text(json.dumps(doc))


def _exposure(ws: Path, seconds: float) -> None:
    doc = json.loads((ws / "caps" / "capture.json").read_text())
    next(iter(doc["regions"].values()))["images"][0]["exposure_s"] = seconds
    (ws / "caps" / "capture.json").write_text(json.dumps(doc))


def _edit_look(ws: Path, old: str, new: str) -> None:
    look = ws / "asset" / "look.usda"
    text = look.read_text()
    assert old in text
    look.write_text(text.replace(old, new, 1))


def _bytes_into_look(ws: Path, junk: bytes) -> None:
    look = ws / "asset" / "look.usda"
    data = look.read_bytes()
    i = data.find(b"Looks")
    look.write_bytes(data[:i] + junk + data[i:])


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[:len(data) // 2])


def _negative_value(ws: Path) -> None:
    lines = (ws / "forehead.csv").read_text().splitlines()
    cells = lines[5].split(",")
    cells[1] = "-0.5"
    lines[5] = ",".join(cells)
    (ws / "forehead.csv").write_text("\n".join(lines) + "\n")


def _big_csv(path: Path, rows: int) -> None:
    r = np.linspace(0, 4, rows)
    np.savetxt(path, np.c_[r, np.exp(-r)[:, None] * np.ones(3)], delimiter=",",
               header="radius_mm,R,G,B", comments="", fmt="%.6g")


def _scene_edit(ws: Path, edit: Callable[[object], None]) -> None:
    from pxr import Usd

    stage = Usd.Stage.Open(str(ws / "scene.usda"))
    edit(stage)
    stage.GetRootLayer().Save()


def _profile_edit(ws: Path, attribute: str, value: float) -> None:
    """The last number of the first profile's ``attribute`` in the asset's look layer."""
    from pxr import Sdf, Usd

    look = ws / "asset" / "look.usda"
    stage = Usd.Stage.Open(str(look))
    prim = next(p for p in stage.Traverse() if p.GetTypeName() == "SkinDiffusionProfile")
    attr = prim.GetAttribute(attribute)
    values = list(attr.Get())
    if attribute == "weights":
        values[-1] = type(values[-1])(value, values[-1][1], values[-1][2])
    else:
        values[-1] = value
    attr.Set(values)
    layer = Sdf.Layer.FindOrOpen(str(look))
    layer.Save()


def _nan_camera(ws: Path) -> None:
    from pxr import Gf, UsdGeom

    def edit(stage: object) -> None:
        cam = UsdGeom.Xformable(stage.GetPrimAtPath("/Cam"))  # type: ignore[attr-defined]
        cam.GetOrderedXformOps()[0].Set(Gf.Vec3d(float("nan"), 0, 100))

    _scene_edit(ws, edit)


def _clipping(ws: Path, near_far: tuple[float, float]) -> None:
    from pxr import Gf, UsdGeom

    def edit(stage: object) -> None:
        cam = UsdGeom.Camera(stage.GetPrimAtPath("/Cam"))  # type: ignore[attr-defined]
        cam.CreateClippingRangeAttr(Gf.Vec2f(*near_far))

    _scene_edit(ws, edit)


# ---------------------------------------------------------------- property-based inputs

_json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=True) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                   max_size=4),
    max_leaves=12)


@settings(max_examples=60, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(doc=st.fixed_dictionaries({}, optional={
    "mm_per_pixel": _json_values, "camera_colorspace": _json_values,
    "subject": _json_values, "regions": st.dictionaries(
        st.text(min_size=1, max_size=12), st.fixed_dictionaries({}, optional={
            "images": st.lists(st.fixed_dictionaries({}, optional={
                "file": st.text(max_size=12) | _json_values,
                "exposure_s": _json_values}), max_size=3)}) | _json_values, max_size=3)}))
def test_any_capture_manifest_is_read_or_refused(tmp_path: Path, doc: dict) -> None:
    """capture.json of any shape: read, or an InputError naming the manifest."""
    from skinpipe.capture.ingest import read_capture_set
    from skinpipe.errors import InputError

    root = tmp_path / "caps"
    root.mkdir(exist_ok=True)
    (root / "capture.json").write_text(json.dumps(doc))
    try:
        captures = read_capture_set(root)
    except InputError as exc:
        assert "capture.json" in str(exc) or "caps" in str(exc)
        return
    assert all(".." not in name and "/" not in name for name in captures.regions)


_cells = st.sampled_from(["0.5", "-1", "nan", "inf", "1e400", "", "x", "1,2", '"3"', "0x1p-3",
                          "1e-320", " 7 ", "\u00a0", "NaN"]) | st.text(max_size=6)


@settings(max_examples=80, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(header=st.sampled_from(["radius_mm,R,G,B", "radius_mm,R,G,B,std_R,std_G,std_B",
                               "R,radius_mm,B,G", "radius_mm,R,G"]),
       rows=st.lists(st.lists(_cells, min_size=0, max_size=8), max_size=12))
def test_any_profile_csv_is_read_or_refused(tmp_path: Path, header: str,
                                            rows: list[list[str]]) -> None:
    """PROFILE.csv with any cells: a profile of finite-or-flagged numbers, or an
    InputError naming the file."""
    from skinpipe.errors import InputError
    from skinpipe.profile.io import read_profile_csv

    path = tmp_path / "p.csv"
    path.write_text("\n".join([header] + [",".join(r) for r in rows]) + "\n")
    try:
        prof = read_profile_csv(path)
    except InputError as exc:
        assert "p.csv" in str(exc)
        return
    assert prof.values.shape == (prof.radius_mm.size, 3) and prof.radius_mm.size > 0


def test_child_processes_find_packages_on_pythonpath(tmp_path: Path) -> None:
    """pymeshlab's reader and xatlas run in child processes of the same interpreter. In
    an environment whose packages come only through PYTHONPATH (a studio's package
    environment; likewise a --user install's site-packages) the children find them too:
    started isolated (``python -I``) they did not."""
    import subprocess
    import sys
    import sysconfig
    import venv

    env_dir = tmp_path / "bare"
    venv.EnvBuilder(with_pip=False).create(env_dir)  # no packages of its own
    paths = [str(Path(__file__).resolve().parents[2]), sysconfig.get_paths()["purelib"],
             sysconfig.get_paths()["platlib"]]
    (tmp_path / "quad.obj").write_text(OBJ_QUAD + "f 1 2 3\nf 2 4 3\n")
    script = (
        "import sys\n"
        "from pathlib import Path\n"
        "from skinpipe.render.surface.unwrap import unwrap\n"
        "from skinpipe.usd.mesh import load_mesh\n"
        "mesh = load_mesh(Path(sys.argv[1]))\n"
        "layout = unwrap(mesh, resolution=64, timeout_s=60)\n"
        "print(mesh.n_faces, layout.uv_indices.size)\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONHOME"}
    env["PYTHONPATH"] = os.pathsep.join(paths)
    python = env_dir / "bin" / "python"
    check = subprocess.run([str(python), "-c", "import numpy"], env={**env, "PYTHONPATH": ""},
                           capture_output=True, text=True)
    assert check.returncode != 0, "the bare environment must not have numpy of its own"
    run = subprocess.run([str(python), "-c", script, str(tmp_path / "quad.obj")], env=env,
                         capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    faces, indices = map(int, run.stdout.split())
    assert indices == 3 * faces > 0
    assert sys.executable != str(python)


# ------------------------------------------- the user's files where a chain writes its own

def _users_files_survive(ws: Path, args: list[str], outputs: list[str]) -> None:
    """A user's file at every path the verb writes, except the two it checks before any
    work: the verb runs, then refuses at its commit naming one, and every user's file is
    as it was."""
    out = ws / "out2"
    mine = [name for name in outputs if name not in ("report.json", "scene.usda")]
    for name in mine:
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text(f"the user's {name}\n")
    before, dirs = _snapshot(ws), _dirs(ws)
    proc = skinpipe(ws, *args, "-o", "out2", timeout=600)
    assert_refused(ws, proc, "did not write", before=before, dirs=dirs)
    assert any(name in proc.stderr for name in mine), proc.stderr[-500:]


def test_run_never_writes_over_a_users_file_in_its_output(ws: Path) -> None:
    args = ["run", "caps", "--mesh", "mesh.obj", "--landmarks", "landmarks.json",
            "--resolution", "32x32", "--texture-size", "64"]
    first = skinpipe(ws, *args, "-o", "out1", timeout=600)
    assert first.returncode == 0, first.stderr[-2000:]
    written = json.loads((ws / "out1" / ".skinpipe-outputs.json").read_text())["files"]
    shutil.rmtree(ws / "out1")
    _users_files_survive(ws, args, sorted(written))


@pytest.mark.slow  # 29 s of demo runs; the default run holds the same guard for `run`
def test_demo_never_writes_over_a_users_file_in_its_output(
        ws: Path, demo_run: tuple[Path, str, str]) -> None:
    written = json.loads((demo_run[0] / ".skinpipe-outputs.json").read_text())["files"]
    _users_files_survive(ws, ["demo"], sorted(written))


def test_a_clean_error_is_never_followed_by_a_crash(ws: Path) -> None:
    """An albedo the render refuses (16 channels) ends in exit 2 and one line every
    time: threads and native workers are done before the process ends ("terminate
    called without an active exception" had turned 2 of 5 runs into exit 134)."""
    import OpenImageIO as oiio

    assert skinpipe(ws, "paint-albedo", "asset/asset.usda", "--size", "64").returncode == 0
    texture = ws / "asset" / "albedo.exr"
    out = oiio.ImageOutput.create(str(texture))
    assert out.open(str(texture), oiio.ImageSpec(64, 64, 16, oiio.FLOAT))
    out.write_image(np.ones((64, 64, 16), np.float32))
    out.close()
    before, dirs = _snapshot(ws), _dirs(ws)
    for _ in range(4):
        proc = skinpipe(ws, "render", "scene.usda", "-o", "out", "--resolution", "32x32")
        assert "terminate called" not in proc.stderr
        assert_refused(ws, proc, "albedo.exr", "16 channels", before=before, dirs=dirs)
