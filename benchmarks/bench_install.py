"""What each dependency costs an install of skinpipe, and what the demo costs on it.

    python benchmarks/bench_install.py [-o benchmarks/results/install.json]

Builds the wheel from a copy of this tree, installs it into a new virtual environment
(pip's cache serves the downloads), and measures, per installed distribution, the bytes
its RECORD lists, grouped under the direct dependency of skinpipe that brings it. Then
the extras one at a time (``intel-cpu``, ``dashboard``, ``bench``) as increments over
the default install, and ``skinpipe demo`` from an empty folder with an empty cache.
Every figure is printed as a share of the default install (the peer in the same run).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import venv
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent

# Run inside the new environment: every distribution's bytes (its RECORD) and the
# direct dependencies each one declares (extras left out).
_SIZES = r"""
import json, re, importlib.metadata as md
dists = {}
for d in md.distributions():
    name = re.sub(r"[-_.]+", "-", d.metadata["Name"]).lower()
    size = 0
    for f in d.files or []:
        p = d.locate_file(f)
        try:
            if p.is_file() and not p.is_symlink():
                size += p.stat().st_size
        except OSError:
            pass
    reqs = []
    for r in d.requires or []:
        if "extra ==" in r:
            continue
        reqs.append(re.sub(r"[-_.]+", "-", re.split(r"[ ;<>=!~\[(]", r, 1)[0]).lower())
    dists[name] = {"bytes": size, "requires": reqs}
print(json.dumps(dists))
"""


def _sizes(python: Path) -> dict[str, Any]:
    out = subprocess.run([str(python), "-c", _SIZES], check=True, capture_output=True,
                         text=True)
    return json.loads(out.stdout)


def _closure(root: str, dists: dict[str, Any]) -> set[str]:
    seen, todo = set(), [root]
    while todo:
        name = todo.pop()
        if name in seen or name not in dists:
            continue
        seen.add(name)
        todo.extend(dists[name]["requires"])
    return seen


def _by_direct_dependency(dists: dict[str, Any]) -> list[dict[str, Any]]:
    """Each direct dependency of skinpipe with the bytes only it brings, then one row for
    what several of them share and one for what none declares outright (a dependency's
    own extras, such as pyopencl[pocl]'s PoCL)."""
    direct = dists["skinpipe"]["requires"]
    closures = {d: _closure(d, dists) for d in direct}
    owners: dict[str, list[str]] = {}
    for dep, names in closures.items():
        for n in names:
            owners.setdefault(n, []).append(dep)
    rows = [{"dependency": dep, "bytes": sum(dists[n]["bytes"] for n in names
                                             if len(owners[n]) == 1),
             "distributions": sorted(n for n in names if len(owners[n]) == 1)}
            for dep, names in closures.items()]
    shared = sorted(n for n, o in owners.items() if len(o) > 1)
    rows.append({"dependency": "(shared by several)",
                 "bytes": sum(dists[n]["bytes"] for n in shared), "distributions": shared})
    rest = sorted(set(dists) - set(owners) - {"skinpipe", "pip", "setuptools"})
    rows.append({"dependency": "(their extras)", "bytes": sum(dists[n]["bytes"] for n in rest),
                 "distributions": rest})
    return sorted(rows, key=lambda r: -r["bytes"])


def _timed(cmd: list[str], cwd: Path, env: dict[str, str]) -> float:
    start = time.perf_counter()
    subprocess.run(cmd, cwd=cwd, env=env, check=True, capture_output=True, timeout=3600)
    return time.perf_counter() - start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--output", type=Path,
                    default=ROOT / "benchmarks" / "results" / "install.json")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="skinpipe-bench-install-"))
    try:
        source = work / "source"
        shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(
            ".git", ".venv", "build", "*.egg-info", "__pycache__", ".*_cache",
            ".hypothesis", "benchmarks", "tests"))
        subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w",
                        str(work / "wheels"), str(source)], check=True)
        (wheel,) = (work / "wheels").glob("skinpipe-*.whl")
        env_dir = work / "venv"
        venv.create(env_dir, with_pip=True)
        python = env_dir / "bin" / "python"
        install_s = _timed([str(python), "-m", "pip", "install", "-q", str(wheel)], work,
                           dict(os.environ))
        base = _sizes(python)
        total = sum(d["bytes"] for d in base.values())
        rows = _by_direct_dependency(base)
        empty = work / "empty"
        empty.mkdir()
        env = {**os.environ, "XDG_CACHE_HOME": str(work / "cache"),
               "PATH": f"{env_dir / 'bin'}{os.pathsep}{os.environ.get('PATH', '')}"}
        env.pop("PYTHONPATH", None)
        demo_s = _timed([str(env_dir / "bin" / "skinpipe"), "demo", "-o", "out"], empty, env)
        extras = {}
        for extra in ("dashboard", "intel-cpu", "bench"):
            before = _sizes(python)
            subprocess.run([str(python), "-m", "pip", "install", "-q",
                            f"{wheel}[{extra}]"], check=True, capture_output=True)
            after = _sizes(python)
            added = {n: d["bytes"] for n, d in after.items() if n not in before}
            extras[extra] = {"bytes": sum(added.values()), "distributions": sorted(added)}
    finally:
        shutil.rmtree(work, ignore_errors=True)

    mb = 1e6
    print(f"default install: {total / mb:.0f} MB in {install_s:.0f} s "
          f"({len(base)} distributions); demo {demo_s:.1f} s")
    print(f"{'direct dependency':<22} {'MB':>7} {'share':>6}")
    for row in rows:
        print(f"{row['dependency']:<22} {row['bytes'] / mb:7.0f} {row['bytes'] / total:6.1%}")
    for name, extra in extras.items():
        print(f"extra [{name}]: +{extra['bytes'] / mb:.0f} MB ({extra['bytes'] / total:.1%} "
              f"of the default install): {', '.join(extra['distributions'])}")
    doc = {"python": sys.version.split()[0], "default_install_bytes": total,
           "install_seconds": install_s, "demo_seconds": demo_s,
           "by_direct_dependency": rows, "extras": extras}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
