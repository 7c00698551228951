"""skinpipe as a studio deploys it: a wheel built from this tree, installed (not
editable) into a fresh virtual environment, used from an unrelated folder."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_the_test_run_keeps_its_caches_to_itself() -> None:
    """tests/__init__.py points every cache at a folder of the run's own: a test reads
    nothing an earlier version left in the user's cache, and writes nothing there."""
    from skinpipe.render.cache import cache_root

    root = cache_root().resolve()
    assert root.parent.name.startswith("skinpipe-test-cache-"), root
    assert root.is_relative_to(Path(tempfile.gettempdir()).resolve())
    assert os.environ["POCL_CACHE_DIR"].startswith(str(root.parent))


@pytest.mark.slow  # a wheel build, an install with every dependency, the demo: 1-3 min
def test_the_wheel_installs_and_runs_the_demo_from_anywhere(tmp_path: Path) -> None:
    # from a copy of the sources alone: a build/ folder left by an earlier build would
    # hand setuptools files this tree no longer declares
    source = tmp_path / "source"
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(
        ".git", ".venv", "build", "*.egg-info", "__pycache__", ".*_cache", ".hypothesis"))
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w",
                    str(wheels), str(source)], check=True, capture_output=True, text=True,
                   timeout=900)
    (wheel,) = wheels.glob("skinpipe-*.whl")
    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=True)
    python = env_dir / "bin" / "python"
    subprocess.run([str(python), "-m", "pip", "install", "-q", str(wheel)], check=True,
                   capture_output=True, text=True, timeout=1800)
    work = tmp_path / "empty"
    work.mkdir()
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME")}
    env["PATH"] = f"{env_dir / 'bin'}{os.pathsep}{env.get('PATH', '')}"

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(list(args), cwd=work, env=env, capture_output=True, text=True,
                              timeout=1200)

    imported = run(str(python), "-c", "import skinpipe, sys; print(skinpipe.__file__)")
    assert imported.returncode == 0, imported.stderr
    assert Path(imported.stdout.strip()).is_relative_to(env_dir), imported.stdout
    assert not run(str(python), "-c", "import pipeline").returncode == 0
    demo = run(str(env_dir / "bin" / "skinpipe"), "demo", "-o", "out")
    assert demo.returncode == 0, demo.stderr[-3000:]
    valid = run(str(env_dir / "bin" / "skinpipe"), "validate", "out/asset/asset.usda")
    assert valid.returncode == 0, valid.stdout[-3000:] + valid.stderr[-3000:]
    assert "Success!" in valid.stdout
    line = run(str(env_dir / "bin" / "skinpipe"), "env").stdout.splitlines()[0]
    folders = line.split("=", 1)[1].split("$")[0].split(os.pathsep)
    assert all(Path(f).is_dir() and Path(f).is_relative_to(env_dir) for f in folders), line
    assert (Path(folders[0]) / "plugInfo.json").is_file()


def _declared_minimum(name: str) -> str:
    """The version after ``>=`` in pyproject.toml's dependency on ``name``."""
    import tomllib

    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    (spec,) = [d for d in deps if d.split(">=")[0].strip().lower() == name]
    return spec.split(">=")[1].split(";")[0].split(",")[0].strip()


@pytest.mark.slow  # an install of usd-core, the demo: about a minute
def test_the_oldest_declared_usd_core_authors_validates_and_renders(tmp_path: Path) -> None:
    """The demo (author, validate, render) and ``skinpipe validate`` on the usd-core that
    pyproject.toml declares as the oldest it works with."""
    version = _declared_minimum("usd-core")
    target = tmp_path / "usd"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target",
                    str(target), f"usd-core=={version}"], check=True, capture_output=True,
                   text=True, timeout=900)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(target), *filter(None, [os.environ.get("PYTHONPATH")])])}

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, *args], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=1200)

    got = run("-c", "from pxr import Usd; print('.'.join(map(str, Usd.GetVersion()[1:])))")
    assert got.stdout.strip() == version, got.stdout + got.stderr
    demo = run("-m", "skinpipe", "demo", "-o", "out")
    assert demo.returncode == 0, demo.stderr[-3000:]
    valid = run("-m", "skinpipe", "validate", "out/asset/asset.usda")
    assert valid.returncode == 0 and "Success!" in valid.stdout, valid.stdout + valid.stderr
