#!/usr/bin/env python3
"""Reads an exported scan with real readers (trimesh for glTF/GLB and PLY, Open3D for
PLY as well) and prints what they found as JSON: vertex and face counts, bounds,
whether colours or a texture came through.

usage: check_export.py FILE
"""

import json
import sys

import numpy as np
import trimesh


def main():
    path = sys.argv[1]
    out = {}
    if path.endswith(".ply"):
        mesh = trimesh.load(path, process=False)
        out["trimesh"] = {"vertices": len(mesh.vertices), "faces": len(mesh.faces),
                          "min": mesh.vertices.min(axis=0).tolist(),
                          "max": mesh.vertices.max(axis=0).tolist(),
                          "colours": mesh.visual.kind == "vertex",
                          "mean_colour": np.asarray(mesh.visual.vertex_colors)[:, :3].mean(axis=0).tolist()}
        import open3d as o3d
        pcd = o3d.io.read_point_cloud(path)
        tri = o3d.io.read_triangle_mesh(path)
        pts = np.asarray(pcd.points)
        out["open3d"] = {"points": len(pts), "triangles": len(tri.triangles),
                         "min": pts.min(axis=0).tolist(), "max": pts.max(axis=0).tolist(),
                         "colours": pcd.has_colors()}
    else:
        scene = trimesh.load(path, process=False)
        # The scene graph applies each node's transform, as a viewer would.
        dumped = scene.dump(concatenate=False) if hasattr(scene, "dump") else [scene]
        vertices = np.concatenate([m.vertices for m in dumped])
        out["trimesh"] = {"meshes": len(dumped), "vertices": len(vertices),
                          "faces": int(sum(len(m.faces) for m in dumped)),
                          "min": vertices.min(axis=0).tolist(), "max": vertices.max(axis=0).tolist(),
                          "textured": all(getattr(m.visual, "kind", None) == "texture" and
                                          m.visual.material.baseColorTexture is not None
                                          for m in dumped),
                          "texture_sizes": [list(m.visual.material.baseColorTexture.size) for m in dumped]}
    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
