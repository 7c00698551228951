"""Write skinpipe/samples/face/landmarks.json: the six regions' landmarks on the face scan.

    python tools/make_sample_face.py [--plot regions.png]

The face is the real range scan shipped in pymeshlab's wheel (face000.ply, mm, y up,
looking down -z). Landmarks were picked by eye on a shaded front view as (x, y) in mm
and are lifted onto the surface: each becomes the frontmost scan vertex within 2 mm of
that (x, y).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from skinpipe.usd.mesh import load_mesh, pymeshlab_face_scan

PICKS_XY_MM = {
    "forehead": [(-10, 8), (-30, 5), (10, 5), (-10, 16)],
    "nose": [(-12, -22), (-12, -35), (-12, -46)],
    "lips": [(-12, -64), (-24, -62), (0, -62)],
    "chin": [(-10, -80), (-22, -77), (2, -77)],
    "cheekbone": [(-42, -18), (24, -18)],
    "cheek": [(-40, -46), (24, -46)],
}
OUT = Path(__file__).resolve().parents[1] / "skinpipe" / "samples" / "face" / "landmarks.json"


def lift(points: np.ndarray, xy: tuple[float, float]) -> list[float]:
    near = np.hypot(points[:, 0] - xy[0], points[:, 1] - xy[1]) < 2.0
    front = np.flatnonzero(near)[np.argmax(points[near, 2])]
    return [round(float(c), 3) for c in points[front]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--plot", type=Path, help="also plot the regions on the scan (PNG)")
    args = parser.parse_args()
    mesh = load_mesh(pymeshlab_face_scan())
    doc = {
        "mesh": "pymeshlab tests/sample_meshes/rangemaps/face000.ply",
        "units": "mesh units (mm)",
        "regions": {name: [lift(mesh.points, xy) for xy in picks]
                    for name, picks in PICKS_XY_MM.items()},
    }
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {OUT}")
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from skinpipe.usd.author import assign_regions_from_landmarks, read_landmarks

        regions = assign_regions_from_landmarks(mesh, read_landmarks(OUT))
        c = mesh.face_centroids()
        fig, ax = plt.subplots(figsize=(7, 9), dpi=90)
        ax.scatter(c[:, 0], c[:, 1], c=regions.face_region, s=0.2, cmap="tab10")
        for name, pts in doc["regions"].items():
            for p in pts:
                ax.annotate(name, (p[0], p[1]), fontsize=7)
        ax.set_aspect("equal")
        fig.savefig(args.plot)


if __name__ == "__main__":
    main()
