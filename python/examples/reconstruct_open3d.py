"""Photos -> cameras and a mesh with dens3r.reconstruct, shown in Open3D.

Reconstructs the bundled rendered orbit (or a folder of photos given as the first argument; views around an object, in order)
with the bundled dens3r-s, builds an Open3D mesh and camera frustums from the returned arrays,
saves them as out/open3d_scene.ply and out/cameras.ply, and opens a window when a display
exists. Run: python python/examples/reconstruct_open3d.py [PHOTOS] (needs open3d)
"""
import os, pathlib, sys
import numpy as np, open3d as o3d
import dens3r

root = pathlib.Path(__file__).resolve().parents[2]
photos = sys.argv[1] if len(sys.argv) > 1 else root / "data-samples" / "orbit" / "images"
out = pathlib.Path("out") / "open3d"
rec = dens3r.reconstruct(photos, out, graph="swin", window=3, cyclic=True, progress=False)
print(f"{len(rec['names'])} cameras; alignment residual {rec['summary']['alignment_loss']}")

geoms = []
if rec["mesh"] is not None:
    m = rec["mesh"]
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(m["vertices"].astype(np.float64)),
                                     o3d.utility.Vector3iVector(m["faces"].astype(np.int32)))
    if "colors" in m:
        mesh.vertex_colors = o3d.utility.Vector3dVector(m["colors"] / 255.0)
    mesh.compute_vertex_normals()
    o3d.io.write_triangle_mesh(str(out / "open3d_scene.ply"), mesh)
    print(f"mesh: {len(m['vertices'])} vertices, {len(m['faces'])} triangles -> {out / 'open3d_scene.ply'}")
    geoms.append(mesh)
frusta = o3d.geometry.LineSet()
for K, c2w, img in zip(rec["K"], rec["cam_to_world"], rec["images"]):
    h, w = img.shape[:2]
    # Open3D takes world-to-camera extrinsics in the same OpenCV camera frame dens3r uses.
    cam = o3d.geometry.LineSet.create_camera_visualization(w, h, K, np.linalg.inv(c2w), scale=0.1)
    frusta += cam
o3d.io.write_line_set(str(out / "cameras.ply"), frusta)
centres = rec["cam_to_world"][:, :3, 3]
print("camera centres:\n", np.round(centres, 3))
geoms.append(frusta)
if os.environ.get("DISPLAY") or sys.platform in ("darwin", "win32"):
    o3d.visualization.draw_geometries(geoms)
