"""Benchmark: a render that reads its seam layout from disk against one that makes it.

    python benchmarks/bench_layout_store.py [--scene DEMO/scene.usda] [--sizes 1024,2048]
                                            [--rounds 2] [-o benchmarks/results/layout_store.json]

Per texture size, `skinpipe render` of the scene at 768x768 in its own process, three
ways taken in turns, round after round (a slow spell of the host reaches all three):

- off: ``--layout-cache off`` (the layout made, nothing kept; the peer);
- first: an empty layout folder (the layout made and written beside the diffusion);
- next: the folder the first left (the layout read back).

Prints each render's own seconds (render.json), its layout task and peak resident memory
(from the process's rusage; for ``next`` also in bytes a texel, issue 23 asks for 120 at
most at texture 4096), the ratios to ``off``, the folder's size, and whether the three
EXRs are the same bit for bit; writes JSON. Without --scene the demo is run first
to make one.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np


def render(scene: Path, out: Path, size: int, cache: str) -> dict[str, Any]:
    """One `skinpipe render` in a child process: its seconds, layout task and peak RSS
    (the child's own rusage, from wait4)."""
    log = out.with_suffix(".log")
    out.parent.mkdir(parents=True, exist_ok=True)
    with log.open("wb") as err:
        proc = subprocess.Popen([sys.executable, "-m", "skinpipe", "render", str(scene),
                                 "-o", str(out), "--resolution", "768x768",
                                 "--texture-size", str(size), "--layout-cache", cache,
                                 "--force"], stdout=err, stderr=err)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"skinpipe render failed ({proc.returncode}); see {log}")
    frame = json.loads((out / "render.json").read_text())["frames"][0]
    return {"seconds": frame["seconds"],
            "layout_s": frame["tasks"].get("diffusion_layout", 0.0),
            "irradiance_s": frame["tasks"].get("irradiance", 0.0),
            "peak_rss_gb": usage.ru_maxrss * 1024 / 1e9,  # kB on Linux
            "tile_store": frame["measures"].get("tile_store")}


def exr_pixels(path: Path) -> np.ndarray:
    import OpenImageIO as oiio

    return oiio.ImageBuf(str(path)).get_pixels(oiio.FLOAT)


def folder_bytes(folder: Path) -> int:
    return sum(f.stat().st_size for f in folder.rglob("*.npz"))


def measure(scene: Path, sizes: list[int], rounds: int, work: Path) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for size in sizes:
        runs: dict[str, list[dict[str, Any]]] = {"off": [], "first": [], "next": []}
        same = True
        stored = 0
        for r in range(rounds):
            cache = work / f"layouts-{size}-{r}"
            for way, folder in (("off", "off"), ("first", str(cache)), ("next", str(cache))):
                runs[way].append(render(scene, work / way, size, folder))
            stored = folder_bytes(cache)
            ref = exr_pixels(work / "off" / "scene.exr")
            same = same and all(np.array_equal(exr_pixels(work / w / "scene.exr"), ref)
                                for w in ("first", "next"))
            shutil.rmtree(cache, ignore_errors=True)
        best = {way: min(x["seconds"] for x in rs) for way, rs in runs.items()}
        per_texel = max(x["peak_rss_gb"] for x in runs["next"]) * 1e9 / size**2
        out[str(size)] = {
            "runs": runs, "best_seconds": best, "next_peak_bytes_per_texel": per_texel,
            "first_over_off": best["first"] / best["off"],
            "next_over_off": best["next"] / best["off"],
            "stored_gb": stored / 1e9, "images_identical": same}
        print(f"texture {size}: off {best['off']:.2f} s, first {best['first']:.2f} s "
              f"({best['first'] / best['off']:.2f}x), next {best['next']:.2f} s "
              f"({best['next'] / best['off']:.2f}x); layout "
              f"{min(x['layout_s'] for x in runs['off']):.2f} -> "
              f"{min(x['layout_s'] for x in runs['next']):.2f} s; peak "
              f"{max(x['peak_rss_gb'] for x in runs['off']):.2f} / "
              f"{max(x['peak_rss_gb'] for x in runs['next']):.2f} GB ({per_texel:.0f} bytes a "
              f"texel next); {stored / 1e9:.2f} GB on "
              f"disk; images {'identical' if same else 'DIFFER'}", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, default=None, help="demo scene (default: run demo)")
    ap.add_argument("--sizes", default="1024,2048", help="texture sizes, comma-separated")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("-o", "--output", type=Path,
                    default=Path("benchmarks/results/layout_store.json"))
    args = ap.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        scene = args.scene
        if scene is None:
            subprocess.run([sys.executable, "-m", "skinpipe", "demo", "-o", str(work / "demo"),
                            "--layout-cache", "off"], check=True, capture_output=True)
            scene = work / "demo" / "scene.usda"
        doc = {"machine": {"platform": platform.platform(), "cores": os.cpu_count()},
               "rounds": args.rounds, "sizes": measure(scene, sizes, args.rounds, work)}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
