"""Fuzz the readers that could kill the interpreter: USD text (through skinpipe's
guarded open), OBJ/PLY meshes (pre-check + pymeshlab in its child), EXR/TIFF headers
(OpenImageIO through skinpipe's image reader).

Each example is a valid seed file mutated by hypothesis (bytes flipped, inserted or cut,
brackets nested, lines repeated). A reader may accept it or raise skinpipe's InputError;
anything else fails the example, and a crash kills this process, which the caller sees
as a signal (``tests/test_fuzz.py`` runs it briefly in CI; run it longer on demand)::

    python tools/fuzz_readers.py --examples 2000 --target usd
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import seed as hypothesis_seed
from hypothesis import strategies as st

from skinpipe.errors import InputError

USDA_SEED = b'''#usda 1.0
(
    defaultPrim = "A"
    metersPerUnit = 0.001
)

def Xform "A" (
    kind = "component"
)
{
    def Mesh "M"
    {
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0, 1, 2]
        point3f[] points = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]
        dictionary d = {string s = "x"; int[] a = [1, 2]}
    }
}
'''
OBJ_SEED = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n"
PLY_SEED = (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            b"property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
            b"end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")


def _image_seed(suffix: str) -> bytes:
    from skinpipe.imageio import write_exr, write_ldr

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"seed{suffix}"
        pixels = np.random.default_rng(0).random((8, 8, 3)).astype(np.float32)
        if suffix == ".exr":
            write_exr(path, pixels, "lin_ap1_scene")
        else:
            write_ldr(path, pixels, 16)
        return path.read_bytes()


@st.composite
def mutated(draw: st.DrawFn, seed: bytes) -> bytes:
    """``seed`` with a few edits: byte flips, inserted junk, cuts, nested brackets, a
    repeated line; edits near the start (headers) as likely as anywhere."""
    data = bytearray(seed)
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["flip", "insert", "cut", "nest", "repeat", "truncate"]))
        at = draw(st.integers(0, max(len(data) - 1, 0)))
        if kind == "flip" and data:
            data[at] = draw(st.integers(0, 255))
        elif kind == "insert":
            data[at:at] = draw(st.binary(min_size=1, max_size=16))
        elif kind == "cut":
            del data[at:at + draw(st.integers(1, 32))]
        elif kind == "nest":
            depth = draw(st.integers(1, 5000))
            data[at:at] = b"[" * depth + b"]" * draw(st.integers(0, depth))
        elif kind == "repeat":
            line = bytes(data[at:]).split(b"\n", 1)[0] + b"\n"
            data[at:at] = line * draw(st.integers(1, 50))
        elif kind == "truncate":
            del data[at:]
    return bytes(data)


def _reader(target: str) -> Callable[[Path], object]:
    """The skinpipe reader that a file of ``target``'s kind goes through."""
    if target == "usd":
        from skinpipe.usd.io import open_stage_guarded

        return open_stage_guarded
    if target in ("obj", "ply"):
        from skinpipe.usd.mesh import load_mesh

        return load_mesh
    from skinpipe.imageio import read_image

    return read_image


def _read_or_refuse(read: Callable[[Path], object], data: bytes, path: Path) -> None:
    """Read ``data`` from ``path``: accepted, or refused with skinpipe's InputError; any
    other exception fails the example (and a crash kills the process)."""
    path.write_bytes(data)
    try:
        read(path)
    except InputError:
        pass


TARGETS = ("usd", "obj", "ply", "exr", "tif")


def run(target: str, examples: int, folder: Path, random_seed: int = 0) -> None:
    seeds = {"usd": USDA_SEED, "obj": OBJ_SEED, "ply": PLY_SEED}
    seed = seeds.get(target) or _image_seed(f".{target}")
    read = _reader(target)
    path = folder / f"fuzz.{'usda' if target == 'usd' else target}"

    @hypothesis_seed(random_seed)
    @settings(max_examples=examples, deadline=None, database=None,
              suppress_health_check=list(HealthCheck))
    @given(mutated(seed))
    def one(data: bytes) -> None:
        _read_or_refuse(read, data, path)

    one()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--examples", type=int, default=25, help="examples per target")
    parser.add_argument("--target", choices=TARGETS, action="append",
                        help="reader(s) to fuzz (default: all)")
    parser.add_argument("--seed", type=int, default=0,
                        help="hypothesis seed (CI uses 0: the same examples every run)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="skinpipe-fuzz-") as tmp:
        for target in args.target or TARGETS:
            run(target, args.examples, Path(tmp), args.seed)
            print(f"{target}: {args.examples} examples, no crash", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
