"""Caches as a hostile or unlucky user meets them, through ``skinpipe render`` in its own
process: a layout cache pointed at the user's folder, another layout's files under this
one's key, kept tables tampered with or linked to /dev/zero, a cache folder that cannot
be used, garbage in PoCL's kernel cache, a blur switch out of range, two renders making
one layout at once. Each render exits 0 (no signal), says what it met in one warning
line, deletes nothing of the user's, and gives the image a render on an empty cache
gives."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from skinpipe.render.cache import write_json_entry

from ..render_scenes import deon_fit, distant_down, patch_asset, scene_over, top_camera

SIZE = 128
pytestmark = pytest.mark.slow  # 20-odd renders in processes of their own: about 2.5 min


def _scene(folder: Path, n: int, size_mm: float) -> Path:
    asset = patch_asset(folder / "asset", [deon_fit()], n=n, size_mm=size_mm)

    def build(stage) -> None:
        top_camera(stage)
        distant_down(stage, intensity=2.0, angle=3.0)  # sampled: the Sobol points are kept

    return scene_over(asset, folder / "scene.usda", build)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("scenes")
    return {"a": _scene(root / "a", 16, 40.0), "b": _scene(root / "b", 12, 30.0)}


def _env(cache: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items()
           if k not in ("POCL_CACHE_DIR", "SKINPIPE_LAYOUT_CACHE", "OCL_ICD_VENDORS")}
    env["XDG_CACHE_HOME"] = str(cache)
    env.update(extra)
    return env


def _render(scene: Path, out: Path, env: dict[str, str], size: int = SIZE,
            *extra: str) -> tuple[subprocess.CompletedProcess[str], np.ndarray | None]:
    run = subprocess.run(
        [sys.executable, "-m", "skinpipe", "render", str(scene), "-o", str(out), "--resolution",
         "48x48", "--texture-size", str(size), "--light-samples", "4", "--force", *extra],
        env=env, capture_output=True, text=True, timeout=300)
    exr = out / f"{scene.stem}.exr"
    image = oiio.ImageBuf(str(exr)).get_pixels(oiio.FLOAT) if run.returncode == 0 else None
    return run, image


def _ok(run: subprocess.CompletedProcess[str]) -> None:
    assert run.returncode == 0, (run.returncode, run.stderr[-2000:])


@pytest.fixture(scope="module")
def reference(scenes: dict[str, Path], tmp_path_factory: pytest.TempPathFactory
              ) -> dict[tuple[str, int], np.ndarray]:
    """Each scene's image on an empty cache, the layout store off."""
    out = {}
    for name, size in (("a", SIZE), ("b", SIZE)):
        root = tmp_path_factory.mktemp(f"ref-{name}")
        run, image = _render(scenes[name], root / "out", _env(root / "cache"), size,
                             "--layout-cache", "off")
        _ok(run)
        out[name, size] = image
    return out


def _warned(run: subprocess.CompletedProcess[str], *words: str) -> None:
    lines = [ln for ln in run.stderr.splitlines() if "warning:" in ln]
    assert any(all(w in ln for w in words) for ln in lines), (words, run.stderr[-2000:])


def _layout_files(cache: Path) -> dict[str, list[Path]]:
    entries = sorted((cache / "skinpipe" / "layouts").glob("layout-*"))
    return {e.name: sorted(e.glob("L*_M*.npz")) for e in entries}


def test_a_layout_cache_in_the_users_folder_evicts_only_its_own(
        scenes: dict[str, Path], reference: dict, tmp_path: Path) -> None:
    shared = tmp_path / "farm_share"
    scan = shared / "actor01" / "scan.ply"
    scan.parent.mkdir(parents=True)
    scan.write_bytes(b"9 GB of scan, in spirit" * 1000)
    (shared / "notes.txt").write_text("mine")
    env = _env(tmp_path / "cache", SKINPIPE_LAYOUT_CACHE_GB="1e-9")  # evict at every write
    for name in ("a", "b", "a"):
        run, image = _render(scenes[name], tmp_path / name, env, SIZE,
                             "--layout-cache", str(shared))
        _ok(run)
        np.testing.assert_array_equal(image, reference[name, SIZE])
    assert scan.read_bytes().startswith(b"9 GB") and (shared / "notes.txt").is_file()
    assert len(list(shared.glob("layout-*"))) == 1  # the other layout went


@pytest.mark.parametrize("other", ["size", "mesh"])
def test_another_layouts_file_under_this_key_is_refused(
        other: str, scenes: dict[str, Path], reference: dict, tmp_path: Path) -> None:
    """A whole, valid layout file of another texture size, or of another mesh at this
    size, copied over every file of this layout: each is refused by its header (it
    crashed the renderer, or gave a wrong image), removed, and the tiles made again."""
    cache = tmp_path / "cache"
    env = _env(cache)
    _ok(_render(scenes["a"], tmp_path / "first", env)[0])
    (mine,) = _layout_files(cache).values()
    before = set(_layout_files(cache))
    if other == "size":
        _ok(_render(scenes["a"], tmp_path / "other", env, 2 * SIZE)[0])
    else:
        _ok(_render(scenes["b"], tmp_path / "other", env)[0])
    (theirs,) = [v for k, v in _layout_files(cache).items() if k not in before]
    for path in mine:
        shutil.copyfile(theirs[0], path)
    run, image = _render(scenes["a"], tmp_path / "again", env)
    _ok(run)
    _warned(run, "cannot be used", "another layout's file")
    np.testing.assert_array_equal(image, reference["a", SIZE])
    run, image = _render(scenes["a"], tmp_path / "third", env)  # made again, read back
    _ok(run)
    assert "warning:" not in run.stderr
    np.testing.assert_array_equal(image, reference["a", SIZE])


@pytest.mark.parametrize("damage", ["weights x3", "/dev/zero"])
def test_a_tampered_kept_table_is_made_again(damage: str, scenes: dict[str, Path],
                                             reference: dict, tmp_path: Path) -> None:
    """The blur schedule's weights scaled x3 with the key intact (every pixel was off by
    up to 2x), or the light samples' table a link to /dev/zero (read until memory ran
    out): refused, made again, the image the same."""
    cache = tmp_path / "cache"
    env = _env(cache)
    _ok(_render(scenes["a"], tmp_path / "first", env, SIZE, "--layout-cache", "off")[0])
    if damage == "weights x3":
        (path,) = (cache / "skinpipe" / "diffusion-terms").glob("terms-*.json")
        doc = json.loads(path.read_text())
        doc["payload"]["weights"] = (np.asarray(doc["payload"]["weights"]) * 3).tolist()
        path.write_text(json.dumps(doc))
        words = ("checksum",)
    else:
        paths = list((cache / "skinpipe" / "light-samples").glob("sobol-*.json"))
        assert paths
        for path in paths:
            path.unlink()
            path.symlink_to("/dev/zero")
        words = ("cannot be used",)
    run, image = _render(scenes["a"], tmp_path / "again", env, SIZE, "--layout-cache", "off")
    _ok(run)
    _warned(run, *words)
    np.testing.assert_array_equal(image, reference["a", SIZE])


@pytest.mark.parametrize("where", ["cache is a file", "home unusable"])
def test_a_cache_folder_that_cannot_be_used_costs_only_the_cache(
        where: str, scenes: dict[str, Path], reference: dict, tmp_path: Path) -> None:
    """A regular file where skinpipe's cache folder should be, or a home whose cache
    cannot be made and no XDG_CACHE_HOME (a sandboxed farm node): the render goes on
    without caches (it said no OpenCL device passed the probe), warning of the folder."""
    blocker = tmp_path / "blocker"
    blocker.write_text("a file")
    if where == "cache is a file":
        (tmp_path / "cache").mkdir()
        (tmp_path / "cache" / "skinpipe").write_text("a file where the folder should be")
        env = _env(tmp_path / "cache")
        folder = str(tmp_path / "cache" / "skinpipe")
    else:
        env = _env(tmp_path / "unused")
        del env["XDG_CACHE_HOME"]
        env["HOME"] = str(blocker / "home")  # under a file: nothing can be made there
        folder = str(blocker)
    run, image = _render(scenes["a"], tmp_path / "out", env)
    _ok(run)
    _warned(run, "cache folder", folder, "cannot be used")
    np.testing.assert_array_equal(image, reference["a", SIZE])
    assert blocker.read_text() == "a file"


@pytest.mark.parametrize("damage", ["garbage", "truncated"])
def test_a_damaged_pocl_kernel_cache_is_checked_before_pocl_reads_it(
        damage: str, scenes: dict[str, Path], reference: dict, tmp_path: Path) -> None:
    """Garbage in a program's bitcode, or a kernel library cut short, in PoCL's cache
    folder (SIGABRT and SIGBUS at every later render): found against the manifest the
    last process left, removed, built again."""
    cache = tmp_path / "cache"
    env = _env(cache, SKINPIPE_OPENCL_DEVICE="pocl")
    _ok(_render(scenes["a"], tmp_path / "first", env)[0])
    pocl = cache / "skinpipe" / "pocl"
    assert (cache / "skinpipe" / ".pocl.manifest.json").is_file()
    if damage == "garbage":
        victims = sorted(pocl.rglob("program.bc"))
        for path in victims:
            path.write_bytes(os.urandom(2048))
    else:
        victims = sorted(pocl.rglob("*.so"))
        for path in victims:
            with open(path, "r+b") as f:
                f.truncate(64)
    assert victims
    run, image = _render(scenes["a"], tmp_path / "again", env)
    _ok(run)
    _warned(run, str(pocl), "removed")
    np.testing.assert_array_equal(image, reference["a", SIZE])


def test_a_blur_switch_record_out_of_range_is_measured_again(
        scenes: dict[str, Path], reference: dict, tmp_path: Path) -> None:
    """A switch record (checksum intact) whose radius the kernels are not built for
    (every render failed until the cache was deleted by hand): removed, measured again.
    The measured switch may pick the other blur for a term than the tests' pinned one,
    so the image is compared within the two blurs' agreement."""
    cache = tmp_path / "cache"
    env = _env(cache)
    env.pop("SKINPIPE_BLUR_SWITCH", None)
    _ok(_render(scenes["a"], tmp_path / "first", env)[0])
    records = list((cache / "skinpipe" / "opencl").glob("blur-switch-*.json"))
    assert records
    for path in records:
        doc = json.loads(path.read_text())
        write_json_entry(path, doc["key"], {k: 10**6 for k in doc["payload"]})
    run, image = _render(scenes["a"], tmp_path / "again", env)
    _ok(run)
    _warned(run, "is not a radius")
    ref = reference["a", SIZE]
    np.testing.assert_allclose(image, ref, atol=2e-3 * float(ref.max()))


def test_two_renders_making_one_layout_at_once_agree(scenes: dict[str, Path],
                                                     reference: dict, tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    env = _env(cache)
    cmd = [sys.executable, "-m", "skinpipe", "render", str(scenes["a"]), "--resolution",
           "48x48", "--texture-size", str(SIZE), "--light-samples", "4"]
    procs = [subprocess.Popen([*cmd, "-o", str(tmp_path / f"out{i}")], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for i in range(2)]
    for proc in procs:
        _, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err[-2000:]
    for i in range(2):
        image = oiio.ImageBuf(str(tmp_path / f"out{i}" / "scene.exr")).get_pixels(oiio.FLOAT)
        np.testing.assert_array_equal(image, reference["a", SIZE])
    (files,) = _layout_files(cache).values()
    assert files  # the layout is on disk, whole
    run, image = _render(scenes["a"], tmp_path / "third", env)
    _ok(run)
    np.testing.assert_array_equal(image, reference["a", SIZE])
