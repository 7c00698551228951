"""Run as ``python -P -m skinpipe.usd._prepare_child MESH.npz OUT.npz TARGET_FACES`` by
:class:`skinpipe.usd.mesh.ScanPreparation`: :func:`~skinpipe.usd.mesh.prepare_scan` and
:func:`~skinpipe.usd.mesh.seal_scan` of the mesh in MESH.npz (``points``, ``faces``,
``meters_per_unit``), written to OUT.npz (``points``, ``faces`` and, where the scan was
open, ``seal_points``, ``seal_faces``). A refusal is one stderr line
``skinpipe-prepare-error: ...`` and exit 3; a pymeshlab crash kills only this process."""

import sys

import numpy as np

from skinpipe.errors import InputError
from skinpipe.usd.mesh import MeshData, prepare_scan, seal_scan


def main(mesh: str, out: str, target_faces: int) -> int:
    with np.load(mesh) as data:
        faces = data["faces"]
        scan = MeshData(data["points"], np.full(faces.shape[0], 3, np.int32),
                        faces.reshape(-1), float(data["meters_per_unit"]))
    try:
        prepared = prepare_scan(scan, target_faces)
        seal = seal_scan(prepared)
    except InputError as exc:
        print(f"skinpipe-prepare-error: {exc}", file=sys.stderr)
        return 3
    arrays = {"points": prepared.points, "faces": prepared.face_indices.reshape(-1, 3)}
    if seal is not None:
        arrays.update(seal_points=seal.points, seal_faces=seal.face_indices.reshape(-1, 3))
    np.savez(out, **arrays)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2], int(sys.argv[3])))
