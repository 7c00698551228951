"""Run as a script (``python -P _meshlab_child.py MESH OUT.npz``) by
:func:`skinpipe.usd.mesh_files.load_in_child`: pymeshlab reads MESH and the arrays go to
OUT.npz. A reader crash kills only this process. It imports nothing of skinpipe."""

import sys

import numpy as np
import pymeshlab


def main(mesh: str, out: str) -> int:
    ms = pymeshlab.MeshSet()
    try:
        ms.load_new_mesh(mesh)
    except pymeshlab.PyMeshLabException as exc:
        print(f"skinpipe-meshlab-error: {str(exc).strip()}", file=sys.stderr)
        return 3
    m = ms.current_mesh()
    arrays = {"points": np.asarray(m.vertex_matrix(), dtype=np.float64),
              "faces": np.asarray(m.face_matrix(), dtype=np.int32)}
    if m.has_vertex_tex_coord():
        arrays["st"] = np.asarray(m.vertex_tex_coord_matrix(), dtype=np.float64)
    np.savez(out, **arrays)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2]))
