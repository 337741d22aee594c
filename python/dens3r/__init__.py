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
from ._native import Dens3rError, Model, compute_shard, fuse, holds_scene, read_mesh, read_scene, write_scene

__version__ = _native.__version__
__all__ = [
    "Dens3rError",
    "Model",
    "compute_shard",
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
    executor: str = "local",
    shards: Optional[int] = None,
    **options,
) -> dict:
    """Photos -> cameras, depth, normals and a mesh, as ``dens3r reconstruct PHOTOS -o OUTPUT``.

    ``photos``: a folder or a list of image files. ``model``: a loaded :class:`Model` (default:
    the bundled dens3r-s). ``options``: ``align`` ("sfm": cameras by structure-from-motion, the
    default; "dense": the network's pairs and the dense alignment), ``graph`` ("auto": every
    pair up to 30 photos, retrieval above; "complete", "swin", "logwin", "oneref", "retrieval"
    or "retrieval-NA-K": which photos are matched, or which pairs the network runs),
    ``window``, ``cyclic``, ``iterations``, ``fixed_focal``, ``focal``, ``voxel``, ``min_conf``
    (default: the model's, :attr:`Model.min_conf`), ``masks`` (a folder of object masks, one per
    photo by file stem: only the object is fused), ``mesh``, ``cache``, ``cache_dir`` (the pair
    cache's folder instead of ``OUTPUT/cache``), ``match_pictures``, ``gpu``. ``progress``: True
    for tqdm bars (when tqdm is installed), False for none, or a callable ``(stage, done, total)``.

    ``executor="ray"`` runs the network's share as Ray tasks on the cluster the caller connected
    to (``ray.init(address=...)``; a local one is started if none is): ``shards`` tasks (default:
    the cluster's CPUs), each loading the model once and computing its share into the pair cache
    (``cache_dir``, default ``OUTPUT/cache``: a folder every machine sees); the cameras and
    everything after are then computed here from the cache, as a single-process run computes
    them. Needs ``pip install 'dens3r[ray]'``.

    Returns :func:`read_scene` of ``OUTPUT/scene`` plus ``output``, ``page`` (``OUTPUT/index.html``,
    the page that shows it all: open it in a browser), ``mesh`` (vertices, faces, normals,
    colours; None without one) and ``summary``.
    """
    if isinstance(photos, (str, os.PathLike)):
        photos = [photos]
    photos = [os.fspath(p) for p in photos]
    callback = _tqdm_progress() if progress is True else (progress or None)
    if executor == "ray":
        cache_dir = options.get("cache_dir") or os.path.join(os.fspath(output), "cache")
        options["cache_dir"] = os.path.abspath(cache_dir)
        _ray_shards(photos, options["cache_dir"], model, shards, options)
    elif executor != "local":
        raise ValueError(f"executor={executor!r}: expected 'local' or 'ray'")
    return _native.reconstruct(photos, os.fspath(output), model=model, progress=callback, **options)


def _ray_shards(photos, cache_dir, model, shards, options) -> None:
    """Computes every shard of the network's runs as Ray tasks into ``cache_dir``."""
    try:
        import ray
    except ImportError:
        raise Dens3rError("executor='ray' needs Ray: pip install 'dens3r[ray]' (or pip install ray)") from None
    if not ray.is_initialized():
        ray.init()
    n = shards or max(1, int(ray.cluster_resources().get("CPU", 1)))
    spec = None if model is None else {"weights": os.fspath(model.weights), "size": model.size}
    keys = ("align", "graph", "window", "cyclic")
    shard_options = {k: options[k] for k in keys if k in options}
    task = ray.remote(num_cpus=1)(_shard_task)
    done = ray.get([task.remote(photos, cache_dir, spec, (i, n), shard_options) for i in range(n)])
    missing = sum(d["total"] for d in done[:1]) - sum(d["entries"] for d in done)
    if missing != 0:
        raise Dens3rError(f"the Ray shards computed {sum(d['entries'] for d in done)} network runs, expected {done[0]['total']}")


def _shard_task(photos, cache_dir, spec, shard, options) -> dict:
    """One Ray task: loads the model once and computes its shard."""
    import dens3r

    model = None if spec is None else dens3r.Model.load(spec["weights"], size=spec["size"])
    return dens3r.compute_shard(photos, cache_dir, model=model, shard=shard, **options)
