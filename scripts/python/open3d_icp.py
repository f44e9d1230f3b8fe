"""Open3D point-to-plane ICP on scan pairs, the peer of Texel's pairwise registration.

Reads a manifest (JSON) that `texel-bench tradeoffs registration` writes:

    {"max_correspondence_distance_m": 0.1, "max_iterations": 30,
     "normal_radius_m": 0.1, "normal_max_nn": 30, "repeats": 3,
     "pairs": [{"name": "...", "source": "a.npy", "target": "b.npy",
                "initial": [[4x4 row-major target_from_source]]}, ...]}

(`.npy` paths relative to the manifest: N x 3 float32 points, each scan in its own
frame), estimates the target's normals (hybrid KD-tree search), runs point-to-plane
ICP from the initial guess (or, with `"method": "colored"` in the manifest and
`source_colors` / `target_colors` per pair, N x 3 float32 RGB in [0, 1], Park, Zhou
& Koltun's colored ICP, with normals on both clouds), and writes the result (JSON) with per pair the
transformation, Open3D's fitness and inlier RMSE, and the CPU time (process time,
median over the repeats) of the normal estimation and of ICP. Run it on one thread
(OMP_NUM_THREADS=1) to compare with a one-core measurement.

Usage: python open3d_icp.py MANIFEST.json RESULT.json
"""

import json
import os
import statistics
import sys
import time

import numpy as np
import open3d as o3d


def cloud(path, colors=None):
    points = np.load(path).astype(np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{path}: expected N x 3 points, got shape {points.shape}")
    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(points)
    if colors is not None:
        rgb = np.load(colors).astype(np.float64)
        if rgb.shape != points.shape:
            raise ValueError(f"{colors}: expected {points.shape} colours, got {rgb.shape}")
        pc.colors = o3d.utility.Vector3dVector(rgb)
    return pc


def run_pair(pair, base, settings):
    colored = settings["method"] == "colored"
    colors = lambda key: os.path.join(base, pair[key]) if colored else None
    source = cloud(os.path.join(base, pair["source"]), colors("source_colors"))
    target_points = os.path.join(base, pair["target"])
    initial = np.asarray(pair["initial"], dtype=np.float64)
    if initial.shape != (4, 4):
        raise ValueError(f"{pair['name']}: initial must be 4 x 4")
    search = o3d.geometry.KDTreeSearchParamHybrid(
        radius=settings["normal_radius_m"], max_nn=settings["normal_max_nn"]
    )
    criteria = o3d.pipelines.registration.ICPConvergenceCriteria(
        max_iteration=settings["max_iterations"]
    )
    normals_ms, icp_ms = [], []
    result = None
    for _ in range(settings["repeats"]):
        target = cloud(target_points, colors("target_colors"))
        start = time.process_time()
        target.estimate_normals(search)
        if colored:
            source.estimate_normals(search)
        normals_ms.append((time.process_time() - start) * 1000.0)
        start = time.process_time()
        if colored:
            result = o3d.pipelines.registration.registration_colored_icp(
                source,
                target,
                settings["max_correspondence_distance_m"],
                initial,
                o3d.pipelines.registration.TransformationEstimationForColoredICP(),
                criteria,
            )
        else:
            result = o3d.pipelines.registration.registration_icp(
                source,
                target,
                settings["max_correspondence_distance_m"],
                initial,
                o3d.pipelines.registration.TransformationEstimationPointToPlane(),
                criteria,
            )
        icp_ms.append((time.process_time() - start) * 1000.0)
    return {
        "name": pair["name"],
        "points": [len(source.points), len(target.points)],
        "transformation": np.asarray(result.transformation).tolist(),
        "fitness": result.fitness,
        "inlier_rmse_m": result.inlier_rmse,
        "normals_ms": statistics.median(normals_ms),
        "icp_ms": statistics.median(icp_ms),
    }


def main():
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    manifest_path, result_path = sys.argv[1], sys.argv[2]
    with open(manifest_path) as f:
        manifest = json.load(f)
    base = os.path.dirname(os.path.abspath(manifest_path))
    settings = {
        "max_correspondence_distance_m": float(manifest["max_correspondence_distance_m"]),
        "max_iterations": int(manifest.get("max_iterations", 30)),
        "normal_radius_m": float(manifest.get("normal_radius_m", 0.1)),
        "normal_max_nn": int(manifest.get("normal_max_nn", 30)),
        "repeats": max(1, int(manifest.get("repeats", 1))),
        "method": manifest.get("method", "point_to_plane"),
    }
    if settings["method"] not in ("point_to_plane", "colored"):
        raise ValueError(f"unknown method {settings['method']!r}")
    pairs = [run_pair(p, base, settings) for p in manifest["pairs"]]
    out = {
        "open3d_version": o3d.__version__,
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS", ""),
        "settings": settings,
        "pairs": pairs,
    }
    with open(result_path, "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
