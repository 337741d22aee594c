"""Reads a COLMAP text model with pycolmap (PyPI) and prints, as one JSON line, each image's
name, camera model and parameters, projection centre, world-to-camera matrix and its observed
keypoints, and each 3-D point: the cross-check of dens3r's COLMAP export.

usage: pycolmap_read.py MODEL_DIR
"""
import json
import sys

import numpy as np
import pycolmap


def main():
    rec = pycolmap.Reconstruction(sys.argv[1])
    images = []
    for image_id in sorted(rec.images):
        im = rec.images[image_id]
        cam = rec.cameras[im.camera_id]
        pose = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        images.append({
            "name": im.name,
            "model": cam.model.name,
            "width": cam.width,
            "height": cam.height,
            "params": [float(p) for p in cam.params],
            "center": [float(c) for c in im.projection_center()],
            "world_to_cam": np.asarray(pose.matrix()).tolist(),
            "points2d": [[float(p.xy[0]), float(p.xy[1])] for p in im.points2D],
        })
    points = [{"xyz": [float(c) for c in p.xyz], "track": [[e.image_id, e.point2D_idx] for e in p.track.elements]}
              for _, p in sorted(rec.points3D.items())]
    print(json.dumps({"pycolmap": pycolmap.__version__, "images": images, "points": points}))


if __name__ == "__main__":
    main()
