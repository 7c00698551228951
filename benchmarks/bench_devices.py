"""Benchmark: every OpenCL device that passes skinpipe's probe, in one run.

    python benchmarks/bench_devices.py [--scene demo_out/scene.usda] [--size 2048]
                                       [-o benchmarks/results/devices.json]

For each device (one process each, chosen with $SKINPIPE_OPENCL_DEVICE):

- the blur: benchmarks/bench_blur.py (ours vs cv2 vs scipy, same run);
- the face diffusion: benchmarks/bench_render.py on the demo scene (diffusion seconds);
- kernel builds cold and warm: `skinpipe render` of the demo scene twice with an empty
  cache folder ($XDG_CACHE_HOME: pyopencl's program binaries, PoCL's kernel cache and
  the measured blur switch), the second run warm; each run's build seconds, programs
  built and wall seconds, and the cold / warm ratio (the goal: within 2x).

Without --scene the demo is run first to make one. Ratios compare devices measured in
the same run: diffusion and blur times against the first device (PoCL where it works).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent


def _run(cmd: list[str], env: dict[str, str]) -> None:
    print("$ " + " ".join(cmd), flush=True)
    subprocess.run(cmd, cwd=ROOT, env={**os.environ, **env}, check=True)


def working_devices() -> list[str]:
    """Runtime ids of the devices that pass the probe (one per runtime)."""
    from skinpipe.render.device import choice

    out: list[str] = []
    for cand, device in choice.candidates(all_runtimes=True):
        if cand.runtime not in out and choice.probe(device) is None:
            out.append(cand.runtime)
    return out


def bench_device(runtime: str, scene: Path, size: int, sigmas: str, tmp: Path
                 ) -> dict[str, Any]:
    py = sys.executable
    env = {"SKINPIPE_OPENCL_DEVICE": runtime}
    blur_json, diff_json = tmp / f"blur-{runtime}.json", tmp / f"diffusion-{runtime}.json"
    _run([py, "benchmarks/bench_blur.py", "--size", str(size), "--sigmas", sigmas,
          "-o", str(blur_json)], env)
    _run([py, "benchmarks/bench_render.py", str(scene), "--sizes", "1024", "--naive-sizes",
          "", "--repeats", "3", "-o", str(diff_json)], env)
    cache = tmp / f"cache-{runtime}"
    builds = {}
    for kind in ("cold", "warm"):
        out = tmp / f"render-{runtime}-{kind}"
        _run([py, "-m", "skinpipe", "render", str(scene), "--texture-size", "1024",
              "--resolution", "768x768", "-o", str(out)],
             # the programs' caches cold then warm; the seam layout made both times
             {**env, "XDG_CACHE_HOME": str(cache), "POCL_CACHE_DIR": str(cache / "pocl"),
              "SKINPIPE_LAYOUT_CACHE": "off"})
        doc = json.loads((out / "render.json").read_text())
        builds[kind] = {"wall_s": doc["total_seconds"], **{
            k: doc["opencl"][k] for k in ("programs_built", "build_seconds")}}
    builds["cold_vs_warm"] = builds["cold"]["wall_s"] / builds["warm"]["wall_s"]
    blur = json.loads(blur_json.read_text())
    diffusion = json.loads(diff_json.read_text())
    return {"runtime": runtime, "device": blur["device"]["device"],
            "blur_switch": blur["blur_switch"], "blur": blur["rows"],
            "diffusion": diffusion["rows"], "render_builds": builds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", type=Path, default=None, help="demo scene (default: run demo)")
    ap.add_argument("--size", type=int, default=2048, help="blur texture size")
    ap.add_argument("--sigmas", default="1,2,4,8,16,32,64")
    ap.add_argument("-o", "--output", type=Path,
                    default=ROOT / "benchmarks" / "results" / "devices.json")
    args = ap.parse_args()
    devices = working_devices()
    with tempfile.TemporaryDirectory(prefix="skinpipe-devices-") as tmp_name:
        tmp = Path(tmp_name)
        scene = args.scene
        if scene is None:
            _run([sys.executable, "-m", "skinpipe", "demo", "-o", str(tmp / "demo")], {})
            scene = tmp / "demo" / "scene.usda"
        rows = [bench_device(d, scene.resolve(), args.size, args.sigmas, tmp) for d in devices]
    base = rows[0]
    for row in rows:
        row["face_diffusion_s"] = row["diffusion"][0]["diffusion"]["ours grid 6"]["seconds"]
        row["face_diffusion_vs_first"] = row["face_diffusion_s"] / base["face_diffusion_s"]
        row["blur_vs_first"] = [r["ours_s"] / b["ours_s"]
                                for r, b in zip(row["blur"], base["blur"], strict=True)]
    doc = {"benchmark": "devices", "size": args.size, "devices": rows}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(doc, indent=2) + "\n")
    for row in rows:
        b = row["render_builds"]
        print(f"{row['runtime']:>10} {row['device']}: switch direct <= R "
              f"{row['blur_switch']['max_radius']} (per texel "
              f"{row['blur_switch']['max_radius_per_texel']})")
        for r in row["blur"]:
            print(f"{'':>12}sigma {r['sigma']:>4g}: ours {r['ours']:>9} {r['ours_s'] * 1e3:7.1f} ms"
                  f"  /cv2 {r['ours_vs_cv2']:5.2f}  /scipy {r['ours_s'] / r['scipy_s']:5.2f}")
        print(f"{'':>12}face diffusion (1024, grid 6) {row['face_diffusion_s'] * 1e3:.0f} ms"
              f" = {row['face_diffusion_vs_first']:.2f}x the first device's")
        print(f"{'':>12}render builds cold {b['cold']['build_seconds']:.2f} s "
              f"({b['cold']['programs_built']} programs), warm {b['warm']['build_seconds']:.2f}"
              f" s; wall cold {b['cold']['wall_s']:.1f} s / warm {b['warm']['wall_s']:.1f} s"
              f" = {b['cold_vs_warm']:.2f}x")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
