"""Benchmark: what light through the volume costs a render of the demo face.

    python benchmarks/bench_transmission.py [--scene DEMO/scene.usda] [--sizes 1024,4096]
                                            [--rounds 3] [-o benchmarks/results/transmission.json]

Per texture size, `skinpipe render` of the scene at 768x768 in its own process, with
transmission (the default: where light first scatters, per light but domes, and the thin
parts' far sides, once for all lights) and with ``--no-transmission`` (the peer), taken
in turns round after round, each with an empty cache but the seam layout read back from
one folder (what a look-development TD's next render does). Prints the best seconds of
each and their ratio, and from render.json the first scatter's seconds per light moved
and the thin parts' seconds; writes JSON. Without --scene the demo is run first to make
one.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any


def render(scene: Path, out: Path, size: int, layouts: Path, *extra: str) -> dict[str, Any]:
    """One `skinpipe render` in a child process with a cache of its own: its seconds and
    the volume's measures."""
    log = out.with_suffix(".log")
    out.parent.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, XDG_CACHE_HOME=str(out.with_suffix(".cache")))
    with log.open("wb") as err:
        done = subprocess.run([sys.executable, "-m", "skinpipe", "render", str(scene), "-o",
                               str(out), "--resolution", "768x768", "--texture-size",
                               str(size), "--layout-cache", str(layouts), "--force", *extra],
                              stdout=err, stderr=err, env=env, check=False)
    if done.returncode != 0:
        raise SystemExit(f"skinpipe render failed ({done.returncode}); see {log}")
    frame = json.loads((out / "render.json").read_text())["frames"][0]
    first = frame["measures"].get("first_scatter") or {}
    return {"seconds": frame["seconds"],
            "irradiance_s": frame["tasks"].get("irradiance", 0.0),
            "media_s": next((v for k, v in frame["tasks"].items() if k.startswith("media")),
                            0.0),
            "first_scatter_s": first.get("seconds", 0.0),
            "lights_moved": first.get("lights", 0),
            "thin_parts_s": (frame["measures"].get("thin_parts") or {}).get("seconds", 0.0)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path)
    parser.add_argument("--sizes", default="1024,4096")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("-o", "--output", type=Path, default=Path(__file__).parent /
                        "results" / "transmission.json")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        scene = args.scene
        if scene is None:
            subprocess.run([sys.executable, "-m", "skinpipe", "demo", "-o", str(tmp / "demo")],
                           check=True, capture_output=True,
                           env=dict(os.environ, XDG_CACHE_HOME=str(tmp / "demo-cache")))
            scene = tmp / "demo" / "scene.usda"
        rows = []
        for size in (int(s) for s in args.sizes.split(",")):
            layouts = tmp / f"layouts_{size}"
            render(scene, tmp / f"warm_{size}", size, layouts)  # the layout, once
            runs: dict[str, list[dict[str, Any]]] = {"on": [], "off": []}
            for r in range(args.rounds):
                for way, extra in (("on", ()), ("off", ("--no-transmission",))):
                    runs[way].append(render(scene, tmp / f"{way}_{size}_{r}", size, layouts,
                                            *extra))
            best = {way: min(runs[way], key=lambda x: x["seconds"]) for way in runs}
            on = best["on"]
            row = {"texture_size": size, "rounds": args.rounds,
                   "seconds_on": on["seconds"], "seconds_off": best["off"]["seconds"],
                   "ratio_on_over_off": on["seconds"] / best["off"]["seconds"],
                   "first_scatter_s_per_light": on["first_scatter_s"]
                   / max(on["lights_moved"], 1),
                   "lights_moved": on["lights_moved"], "thin_parts_s": on["thin_parts_s"],
                   "media_s": on["media_s"], "runs": runs}
            rows.append(row)
            print(f"texture {size}: {on['seconds']:.2f} s with transmission, "
                  f"{best['off']['seconds']:.2f} s without (x{row['ratio_on_over_off']:.3f}); "
                  f"first scatter {row['first_scatter_s_per_light']:.2f} s a light "
                  f"({on['lights_moved']} moved), thin parts {on['thin_parts_s']:.2f} s, "
                  f"media {on['media_s']:.2f} s", flush=True)
    args.output.write_text(json.dumps({"host": platform.node(), "cpus": os.cpu_count(),
                                       "rows": rows}, indent=1) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
