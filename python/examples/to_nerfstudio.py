"""dens3r cameras, depth and normals -> a nerfstudio dataset (transforms.json).

Reconstructs photos (default: the bundled rendered orbit), then writes nerfstudio's
transforms.json from the returned arrays: OpenGL camera-to-world poses (nerfstudio's
convention), per-frame intrinsics, images, depth as .npy (`depth_file_path`) and normals in
world coordinates as .npy (`normal_file_path`, for normal-supervised methods).
Run: python python/examples/to_nerfstudio.py [PHOTOS] [OUT]
"""
import json, pathlib, sys
import numpy as np
import dens3r

root = pathlib.Path(__file__).resolve().parents[2]
photos = sys.argv[1] if len(sys.argv) > 1 else root / "data-samples" / "orbit" / "images"
out = pathlib.Path(sys.argv[2] if len(sys.argv) > 2 else "out/nerfstudio")
rec = dens3r.reconstruct(photos, out / "dens3r", graph="swin", window=3, cyclic=True, progress=False)
opencv_to_opengl = np.diag([1.0, -1.0, -1.0, 1.0])  # camera axes: y down, z forward -> y up, z back
frames = []
for i, name in enumerate(rec["names"]):
    K, c2w = rec["K"][i], rec["cam_to_world"][i]
    h, w = rec["depth"][i].shape
    for sub in ["images", "depth", "normals"]:
        (out / sub).mkdir(parents=True, exist_ok=True)
    np.save(out / "depth" / f"{name}.npy", rec["depth"][i])
    frame = {"file_path": f"images/{name}.png", "depth_file_path": f"depth/{name}.npy",
             "transform_matrix": (c2w @ opencv_to_opengl).tolist(),
             # dens3r's K puts pixel centres at integers; nerfstudio's rays go through x + 0.5.
             "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2] + 0.5, "cy": K[1, 2] + 0.5, "w": w, "h": h}
    if rec["normals"][i] is not None:
        world = rec["normals"][i] @ c2w[:3, :3].T  # camera-frame normals rotated to world
        np.save(out / "normals" / f"{name}.npy", world.astype(np.float32))
        frame["normal_file_path"] = f"normals/{name}.npy"
    frames.append(frame)
    # The image as the scene folder holds it (the network's crop of the photo, which K describes).
    (out / "images" / f"{name}.png").write_bytes((pathlib.Path(rec["path"]) / "images" / f"{name}.png").read_bytes())
(out / "transforms.json").write_text(json.dumps({"camera_model": "OPENCV", "frames": frames}, indent=1))
print(f"{len(frames)} frames -> {out / 'transforms.json'} (OpenGL poses; depth and world normals as .npy)")
print("first pose:\n", np.round(np.array(frames[0]["transform_matrix"]), 4))
