"""The lsnif Python module on a real asset: info, metadata and arrays, intersection and
occlusion against the C reader on 100 000 rays, instances, errors and the released GIL.

Environment (set by tests/CMakeLists.txt and scripts/check_packages):
  LSNIF_TEST_ASSET   a .lsnif file
  LSNIF_TRACE_RAYS   the trace_rays program (trace_rays.c) built against the same reader
The module itself comes from PYTHONPATH (the build tree or an installed package).
"""
import json
import os
import subprocess
import threading
import time

import numpy as np
import pytest

import lsnif

ASSET = os.environ["LSNIF_TEST_ASSET"]
TRACE = os.environ["LSNIF_TRACE_RAYS"]
RAY = np.dtype([("org", "<f4", 3), ("tmin", "<f4"), ("dir", "<f4", 3), ("tmax", "<f4")])
HIT = np.dtype([("t", "<f4"), ("normal", "<f4", 3), ("hit", "<u4"), ("material", "<u4")])


@pytest.fixture(scope="module")
def model():
    with lsnif.open(ASSET) as m:
        yield m


def rays_at_box(model, n, seed):
    """n rays from a sphere around the asset's box through points inside it."""
    rng = np.random.default_rng(seed)
    lo, hi = np.array(model.info["box_min"]), np.array(model.info["box_max"])
    target = lo + rng.random((n, 3)) * (hi - lo)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    origins = (target - d * np.linalg.norm(hi - lo)).astype(np.float32)
    return origins, d.astype(np.float32)


def test_info_metadata_and_arrays_agree(model):
    info = model.info
    V, L, F = info["grid_resolution"], info["level_count"], info["features_per_level"]
    assert info["version"][0] == lsnif.container_version[0] and info["version"] <= lsnif.container_version
    assert model.occupancy().shape == (V, V, V) and model.occupancy().dtype == bool
    assert int(model.occupancy().sum()) == info["occupied_voxels"]
    for level in range(L):
        table = model.grid_level(level)
        assert table.shape == (info["level_entries"][level], F)
        assert table.dtype == (np.uint8 if info["grid_encoding"] == "u8_affine" else np.float16)
    with pytest.raises(IndexError):
        model.grid_level(L)
    assert model.layer_count == len(info["hidden_width"]) + 1
    widths = [info["input_width"]] + info["hidden_width"] + [info["output_count"]]
    for k in range(model.layer_count):
        assert model.layer_weights(k).shape == (widths[k + 1], widths[k])
        assert model.layer_bias(k).shape == (widths[k + 1],)
    meta = json.loads(model.metadata)
    assert meta["format"] == "lsnif-metadata/1"
    assert meta["model"]["grid_resolution"] == V


def test_same_hits_as_the_c_reader_on_100k_rays(model, tmp_path):
    origins, directions = rays_at_box(model, 100_000, seed=1)
    rays = np.zeros(len(origins), RAY)
    rays["org"], rays["dir"], rays["tmin"], rays["tmax"] = origins, directions, 0.0, np.inf
    rays.tofile(tmp_path / "rays.bin")
    subprocess.run([TRACE, ASSET, tmp_path / "rays.bin", tmp_path / "hits.bin", tmp_path / "occluded.bin"],
                   check=True)
    want = np.fromfile(tmp_path / "hits.bin", HIT)
    want_occluded = np.fromfile(tmp_path / "occluded.bin", np.uint8).astype(bool)
    got = model.intersect(origins, directions)
    assert 1000 < got["hit"].sum() < len(origins)  # both answers, many times
    assert np.array_equal(got["hit"], want["hit"] != 0)
    assert np.array_equal(got["t"].view(np.uint32), want["t"].view(np.uint32))
    hit = want["hit"] != 0
    assert np.array_equal(got["normal"][hit].view(np.uint32), want["normal"][hit].view(np.uint32))
    assert np.array_equal(got["material"], want["material"])
    assert np.array_equal(model.occluded(origins, directions), want_occluded)


def test_an_instance_is_the_object_space_query_moved(model):
    origins, directions = rays_at_box(model, 20_000, seed=2)
    c, s = np.cos(0.7), np.sin(0.7)
    A = np.array([[2 * c, 0, 2 * s], [0, 0.5, 0], [-2 * s, 0, 2 * c]])  # rotation and scale
    b = np.array([10.0, -3.0, 4.0])
    transform = np.hstack([A, b[:, None]]).astype(np.float32)
    world_o = (origins.astype(np.float64) @ A.T + b).astype(np.float32)
    world_d = (directions.astype(np.float64) @ A.T).astype(np.float32)
    local = model.intersect(origins, directions)
    world = model.intersect(world_o, world_d, transform=transform)
    agree = np.mean(local["hit"] == world["hit"])
    assert agree >= 0.999, agree
    both = local["hit"] & world["hit"]
    assert np.median(np.abs(local["t"][both] - world["t"][both]) / local["t"][both]) < 1e-4
    occluded = model.occluded(world_o, world_d, transform=transform)
    assert np.array_equal(occluded, world["hit"])


def test_bounds_as_numbers_or_arrays(model):
    origins, directions = rays_at_box(model, 1000, seed=3)
    none = model.occluded(origins, directions, tmin=0.0, tmax=0.0)
    assert not none.any()
    per_ray = model.intersect(origins, directions, tmin=np.zeros(1000), tmax=np.full(1000, np.inf))
    assert np.array_equal(per_ray["hit"], model.intersect(origins, directions)["hit"])


def test_bad_arguments_raise_clear_errors(model, tmp_path):
    with pytest.raises(ValueError, match="origins"):
        model.intersect(np.zeros((4, 2)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="directions"):
        model.intersect(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="tmax"):
        model.intersect(np.zeros((4, 3)), np.ones((4, 3)), tmax=np.ones(3))
    with pytest.raises(ValueError, match="transform"):
        model.intersect(np.zeros((4, 3)), np.ones((4, 3)), transform=np.eye(3))
    with pytest.raises(lsnif.Error, match="singular|INVALID|invalid"):
        model.intersect(np.zeros((4, 3)), np.ones((4, 3)), transform=np.zeros((3, 4)))
    with pytest.raises(ValueError, match="arithmetic"):
        model.arithmetic = "fp64"
    truncated = tmp_path / "truncated.lsnif"
    truncated.write_bytes(open(ASSET, "rb").read()[:1000])
    with pytest.raises(lsnif.Error, match="truncated.lsnif"):
        lsnif.open(str(truncated))
    with pytest.raises(lsnif.Error, match="missing.lsnif"):
        lsnif.open(str(tmp_path / "missing.lsnif"))
    closed = lsnif.open(ASSET)
    closed.close()
    with pytest.raises(ValueError, match="closed"):
        closed.info


def test_arithmetic_can_be_chosen(model):
    origins, directions = rays_at_box(model, 5000, seed=4)
    model.arithmetic = "fp32"
    assert model.arithmetic == "fp32"
    fp32 = model.intersect(origins, directions)["hit"]
    model.arithmetic = "auto"
    assert np.mean(model.intersect(origins, directions)["hit"] == fp32) >= 0.995


def test_threads_trace_while_the_gil_is_released(model):
    """Two threads tracing at once get the serial answers, and while a thread traces a large
    batch the main thread keeps running Python code: it could not if the trace held the GIL."""
    origins, directions = rays_at_box(model, 400_000, seed=5)
    serial = model.intersect(origins, directions)["t"]
    results = {}

    def trace(name):
        results[name] = model.intersect(origins, directions)["t"]

    workers = [threading.Thread(target=trace, args=(k,)) for k in ("a", "b")]
    for w in workers:
        w.start()
    ticks = 0
    while any(w.is_alive() for w in workers):
        ticks += 1
        time.sleep(0.001)
    for name in ("a", "b"):
        assert np.array_equal(results[name].view(np.uint32), serial.view(np.uint32))
    assert ticks > 20, ticks
