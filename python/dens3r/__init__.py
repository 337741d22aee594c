"""dens3r: the Dens3R / DUSt3R / MASt3R network, reconstruction and fusion from Python.

Everything returns NumPy arrays in dens3r's conventions: OpenCV camera frame (x right, y down,
z forward), camera-to-world 4x4 poses, normals in the camera frame facing the camera.

    import dens3r
    model = dens3r.Model.load()                 # the bundled dens3r-s; or a checkpoint / known name
    out = model.predict("photo.jpg")            # depth, normals, pts3d, conf, desc, K
    feats = model.features("photo.jpg")         # frozen features for heads: [(C, h, w), ...]
    rec = dens3r.reconstruct(["a.jpg", "b.jpg"], "out/")   # cameras, depth, normals, mesh
    mesh = dens3r.fuse(rec["depth"], rec["K"], rec["cam_to_world"], voxel=0.01)
"""

from __future__ import annotations

import os
from typing import Callable, Optional, Sequence, Union

from . import _native
from ._native import Dens3rError, Model, fuse, holds_scene, read_mesh, read_scene, write_scene

__version__ = _native.__version__
__all__ = [
    "Dens3rError",
    "Model",
    "fuse",
    "holds_scene",
    "read_mesh",
    "read_scene",
    "reconstruct",
    "write_scene",
]

PathLike = Union[str, "os.PathLike[str]"]


def _tqdm_progress() -> Optional[Callable[[str, int, int], None]]:
    """A progress callback drawing tqdm bars (one per stage), when tqdm is installed."""
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return None
    bars = {}

    def report(stage: str, done: int, total: int) -> None:
        bar = bars.get(stage)
        if bar is None:
            for other in bars.values():
                other.close()
            bar = bars[stage] = tqdm(total=total, desc=stage, leave=False)
        bar.total = total
        bar.n = done
        bar.refresh()
        if done >= total:
            bar.close()

    return report


def reconstruct(
    photos: Union[PathLike, Sequence[PathLike]],
    output: PathLike,
    *,
    model: Optional[Model] = None,
    progress: Union[bool, Callable[[str, int, int], None], None] = True,
    **options,
) -> dict:
    """Photos -> cameras, depth, normals and a mesh, as ``dens3r reconstruct PHOTOS -o OUTPUT``.

    ``photos``: a folder or a list of image files. ``model``: a loaded :class:`Model` (default:
    the bundled dens3r-s). ``options``: ``align`` ("sfm": cameras by structure-from-motion, the
    default; "dense": the network's pairs and the dense alignment), ``graph`` ("complete",
    "swin", "logwin", "oneref": which photos are matched, or which pairs the network runs),
    ``window``, ``cyclic``, ``iterations``, ``fixed_focal``, ``focal``, ``voxel``, ``min_conf``
    (default: the model's, :attr:`Model.min_conf`), ``masks`` (a folder of object masks, one per
    photo by file stem: only the object is fused), ``mesh``, ``cache``, ``match_pictures``, ``gpu``. ``progress``: True for tqdm bars (when tqdm is
    installed), False for none, or a callable ``(stage, done, total)``.

    Returns :func:`read_scene` of ``OUTPUT/scene`` plus ``output``, ``mesh`` (vertices, faces,
    normals, colours; None without one) and ``summary``.
    """
    if isinstance(photos, (str, os.PathLike)):
        photos = [photos]
    callback = _tqdm_progress() if progress is True else (progress or None)
    return _native.reconstruct([os.fspath(p) for p in photos], os.fspath(output), model=model, progress=callback, **options)
