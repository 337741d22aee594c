"""Open3D 0.20 peer for `dens3r bench fusion`: TSDF-fuse a dens3r scene folder on the CPU with
Open3D's VoxelBlockGrid (8^3 blocks, tsdf/weight/color, truncation = 4 voxels, same depth
range), extract the mesh and print one JSON line with the timings and peak RSS. With
--device CUDA:0 the grid lives on the GPU (the PyPI wheel's CUDA build); when CUDA is not
available it prints {"error": ...} instead.

usage: open3d_fusion.py SCENE_DIR VOXEL OUT.ply [--max-depth 10] [--trunc-voxels 4] [--device CPU:0]
"""
import argparse
import json
import os
import resource
import time

import numpy as np


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("voxel", type=float)
    ap.add_argument("out")
    ap.add_argument("--max-depth", type=float, default=10.0)
    ap.add_argument("--trunc-voxels", type=float, default=4.0)
    ap.add_argument("--device", default="CPU:0")
    a = ap.parse_args()
    import open3d as o3d
    import open3d.core as o3c
    from PIL import Image

    cuda = a.device.upper().startswith("CUDA")
    if cuda and not o3c.cuda.is_available():
        print(json.dumps({"error": f"Open3D {o3d.__version__} has no CUDA device here"}))
        return
    device = o3c.Device(a.device)

    cams = json.load(open(os.path.join(a.scene, "cameras.json")))
    frames = cams["frames"]
    data = []
    for f in frames:
        depth = np.load(os.path.join(a.scene, "depth", f["name"] + ".npy")).astype(np.float32)
        depth = np.nan_to_num(depth, nan=0.0)
        rgb = np.asarray(Image.open(os.path.join(a.scene, f["image"])).convert("RGB")).astype(np.float32) / 255.0
        k = np.array(f["K"], dtype=np.float64)
        c2w = np.array(f["cam_to_world"], dtype=np.float64)
        w2c = np.linalg.inv(c2w)
        data.append((o3d.t.geometry.Image(depth).to(device), o3d.t.geometry.Image(rgb).to(device),
                     o3c.Tensor(k), o3c.Tensor(w2c)))
    vbg = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)),
        voxel_size=a.voxel,
        block_resolution=8,
        block_count=50000,
        device=device,
    )
    t0 = time.perf_counter()
    for depth, color, k, w2c in data:
        coords = vbg.compute_unique_block_coordinates(
            depth, k, w2c, depth_scale=1.0, depth_max=a.max_depth, trunc_voxel_multiplier=a.trunc_voxels
        )
        vbg.integrate(coords, depth, color, k, k, w2c, depth_scale=1.0, depth_max=a.max_depth,
                      trunc_voxel_multiplier=a.trunc_voxels)
    if cuda:
        o3c.cuda.synchronize()
    integrate = time.perf_counter() - t0
    t0 = time.perf_counter()
    # weight_threshold 0.5: keep every voxel observed at least once, as dens3r does (the
    # default 3.0 drops surfaces seen by fewer than 3 frames and lowers completeness).
    mesh = vbg.extract_triangle_mesh(weight_threshold=0.5).to_legacy()
    extract = time.perf_counter() - t0
    o3d.io.write_triangle_mesh(a.out, mesh)
    print(json.dumps({
        "frames": len(data),
        "integrate_ms_per_frame": 1e3 * integrate / len(data),
        "extract_seconds": extract,
        "vertices": len(mesh.vertices),
        "triangles": len(mesh.triangles),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "open3d": o3d.__version__,
    }))


if __name__ == "__main__":
    main()
