"""What Open3D reads of mesh files, as a JSON file (Open3D prints its warnings on stdout). Run by the
interpreter that has Open3D:

    python tests/inference/open3d_probe.py report.json room.glb room.obj room.ply

Imports nothing of usl or the tests, so it runs in a scratch environment (``pip install open3d-cpu``).
Per file: ``read_triangle_mesh`` (one merged mesh: vertices, triangle count, which material each
triangle uses, vertex colours) and ``read_triangle_model`` (the meshes it keeps apart, by name, with
their unique vertices, triangle count, base colour and whether a colour texture came with it).
"""

import json
import sys

import numpy as np
import open3d as o3d


def probe(path: str) -> dict:
    merged = o3d.io.read_triangle_mesh(path)
    model = o3d.io.read_triangle_model(path)
    materials = model.materials
    return {
        "mesh": {
            "vertices": np.asarray(merged.vertices).tolist(),
            "triangles": len(merged.triangles),
            "triangle_material_ids": np.asarray(merged.triangle_material_ids).tolist(),
            "vertex_colors": np.asarray(merged.vertex_colors).tolist(),
        },
        "model": [
            {
                "name": m.mesh_name,
                "vertices": np.unique(np.asarray(m.mesh.vertices), axis=0).tolist(),
                "triangles": len(m.mesh.triangles),
                "base_color": np.asarray(materials[m.material_idx].base_color).tolist(),
                "textured": materials[m.material_idx].albedo_img is not None,
            }
            for m in model.meshes
        ],
    }


if __name__ == "__main__":
    report = {"open3d": o3d.__version__, **{path: probe(path) for path in sys.argv[2:]}}
    with open(sys.argv[1], "w") as f:
        json.dump(report, f)
