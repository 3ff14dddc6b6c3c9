"""The lsnif Python module on real assets: info, metadata and arrays, intersection and
occlusion against the C reader on 100 000 rays, instances, errors, and threads.

Environment (set by tests/CMakeLists.txt and scripts/check_packages):
  LSNIF_TEST_ASSET   one or more .lsnif files or directories (each standing for the .lsnif
                     files in it, as `lsnif convert -o DIR` writes them), separated by
                     os.pathsep (":"); every test runs on each asset
  LSNIF_TRACE_RAYS   the trace_rays program (trace_rays.c) built against the same reader
The module itself comes from PYTHONPATH (the build tree or an installed package).
"""
import contextlib
import json
import os
import pathlib
import re
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

import lsnif


def assets(spec):
    found = []
    for entry in spec.split(os.pathsep):
        path = pathlib.Path(entry)
        found += sorted(map(str, path.glob("*.lsnif"))) if path.is_dir() else [entry]
    return found


ASSETS = assets(os.environ["LSNIF_TEST_ASSET"])
TRACE = os.environ["LSNIF_TRACE_RAYS"]
RAY = np.dtype([("org", "<f4", 3), ("tmin", "<f4"), ("dir", "<f4", 3), ("tmax", "<f4")])
HIT = np.dtype([("t", "<f4"), ("normal", "<f4", 3), ("hit", "<u4"), ("material", "<u4")])


@pytest.fixture(scope="module", params=ASSETS, ids=os.path.basename)
def model(request):
    with lsnif.open(request.param) as m:
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


@contextlib.contextmanager
def no_forced_gil_switches():
    """While inside, a thread running Python code keeps the GIL until it blocks (a sleep, a
    lock, or C code that releases it): which thread runs next no longer depends on time."""
    interval = sys.getswitchinterval()
    sys.setswitchinterval(100.0)
    try:
        yield
    finally:
        sys.setswitchinterval(interval)


def test_the_assets_exist():
    assert ASSETS and all(os.path.isfile(a) for a in ASSETS), os.environ["LSNIF_TEST_ASSET"]


def test_module_version():
    assert lsnif.version() == lsnif.__version__
    assert re.fullmatch(r"\d+\.\d+\.\d+", lsnif.version())
    assert lsnif.container_version[0] == 1


def test_info_metadata_and_arrays_agree(model):
    info = model.info
    V, H, L, F = info["grid_resolution"], info["max_points"], info["level_count"], info["features_per_level"]
    assert info["version_major"] == lsnif.container_version[0]
    assert (info["version_major"], info["version_minor"]) <= lsnif.container_version
    assert info["file_size"] == os.path.getsize(model.path)
    occupancy = model.occupancy()
    assert occupancy.shape == (V, V, V) and occupancy.dtype == bool
    assert int(occupancy.sum()) == info["occupied_voxels"]
    assert len(info["level_resolution"]) == len(info["level_entries"]) == len(info["level_dense"]) == L
    parameters = 0
    for level in range(L):
        table = model.grid_level(level)
        assert table.shape == (info["level_entries"][level], F)
        parameters += table.size
        if info["grid_encoding"] == "u8_affine":
            assert table.dtype == np.uint8
            pair = model.grid_dequant(level)
            assert pair.shape == (2,) and pair.dtype == np.float32 and np.isfinite(pair).all()
        else:
            assert info["grid_encoding"] == "fp16" and table.dtype == np.float16
            with pytest.raises(ValueError, match="fp16"):
                model.grid_dequant(level)
    with pytest.raises(IndexError):
        model.grid_level(L)
    assert info["hidden_layer_count"] == len(info["hidden_width"])
    assert model.layer_count == info["hidden_layer_count"] + 1
    ray_inputs = model.ray_inputs
    assert info["input_width"] == (H * L * F + 3 * bool(ray_inputs & lsnif.RAY_INPUT_DIRECTION) +
                                   H * bool(ray_inputs & lsnif.RAY_INPUT_ENTRY_OFFSETS))
    assert info["output_count"] == 5 + info["material_count"]
    widths = [info["input_width"]] + info["hidden_width"] + [info["output_count"]]
    for k in range(model.layer_count):
        weights, bias = model.layer_weights(k), model.layer_bias(k)
        assert weights.shape == (widths[k + 1], widths[k]) and weights.dtype == np.float16
        assert bias.shape == (widths[k + 1],) and bias.dtype == np.float16
        assert np.isfinite(weights).all() and np.isfinite(bias).all()
        parameters += weights.size + bias.size
    with pytest.raises(IndexError):
        model.layer_weights(model.layer_count)
    assert info["parameter_count"] == parameters
    meta = model.metadata_json
    assert meta == json.loads(model.metadata)
    assert meta["format"] == "lsnif-metadata/1"
    described = meta["model"]
    for key, field in [("grid_resolution", "grid_resolution"), ("max_points", "max_points"),
                       ("features_per_level", "features_per_level"), ("log2_table_size", "log2_table_size"),
                       ("level_resolutions", "level_resolution"), ("hidden_widths", "hidden_width"),
                       ("output_count", "output_count"), ("material_count", "material_count"),
                       ("activation", "activation"), ("distance_encoding", "distance_encoding"),
                       ("grid_encoding", "grid_encoding"), ("parameter_count", "parameter_count")]:
        if key in described:  # version 1.0 metadata names fewer
            assert described[key] == info[field], key


def test_same_hits_as_the_c_reader_on_100k_rays(model, tmp_path):
    origins, directions = rays_at_box(model, 100_000, seed=1)
    rays = np.zeros(len(origins), RAY)
    rays["org"], rays["dir"], rays["tmin"], rays["tmax"] = origins, directions, 0.0, np.inf
    rays.tofile(tmp_path / "rays.bin")
    subprocess.run([TRACE, model.path, tmp_path / "rays.bin", tmp_path / "hits.bin", tmp_path / "occluded.bin"],
                   check=True)
    want = np.fromfile(tmp_path / "hits.bin", HIT)
    want_occluded = np.fromfile(tmp_path / "occluded.bin", np.uint8)
    assert len(want) == len(want_occluded) == len(origins)
    got = model.intersect(origins, directions)
    assert got["hit"].dtype == bool and got["hit"].shape == (len(origins),)
    assert got["t"].dtype == np.float32 and got["normal"].shape == (len(origins), 3)
    assert got["normal"].dtype == np.float32 and got["material"].dtype == np.uint32
    assert 1000 < got["hit"].sum() < len(origins) - 1000  # both answers, many times
    assert np.array_equal(got["hit"], want["hit"] != 0)
    assert np.array_equal(got["t"].view(np.uint32), want["t"].view(np.uint32))
    assert np.array_equal(got["normal"].view(np.uint32), want["normal"].view(np.uint32))
    assert np.array_equal(got["material"], want["material"])
    assert np.array_equal(model.occluded(origins, directions), want_occluded != 0)


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
    assert both.sum() > 100
    assert np.median(np.abs(local["t"][both] - world["t"][both]) / local["t"][both]) < 1e-4
    # The normal is the object-space one moved by A^-T and normalized again.
    moved = local["normal"][both].astype(np.float64) @ np.linalg.inv(A)
    moved /= np.linalg.norm(moved, axis=1, keepdims=True)
    assert np.median(np.sum(moved * world["normal"][both], axis=1)) > 0.999
    occluded = model.occluded(world_o, world_d, transform=transform)
    assert np.array_equal(occluded, world["hit"])


def test_bounds_as_numbers_or_arrays(model):
    origins, directions = rays_at_box(model, 1000, seed=3)
    none = model.occluded(origins, directions, tmin=0.0, tmax=0.0)
    assert not none.any()
    default = model.intersect(origins, directions)
    per_ray = model.intersect(origins, directions, tmin=np.zeros(1000), tmax=np.full(1000, np.inf))
    assert np.array_equal(per_ray["hit"], default["hit"])
    # Any float dtype is converted: float64 inputs give the float32 inputs' answers.
    wide = model.intersect(origins.astype(np.float64), directions.astype(np.float64))
    assert np.array_equal(wide["t"].view(np.uint32), default["t"].view(np.uint32))
    # A ray's own tmax cuts it short of its hit.
    cut = np.where(default["hit"], default["t"] * 0.5, np.inf)
    assert not model.occluded(origins, directions, tmax=cut)[default["hit"]].any()
    empty = model.intersect(np.zeros((0, 3)), np.zeros((0, 3)))
    assert empty["hit"].shape == (0,) and empty["normal"].shape == (0, 3)


def test_bad_arguments_raise_clear_errors(model, tmp_path):
    with pytest.raises(ValueError, match="origins"):
        model.intersect(np.zeros((4, 2)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="directions"):
        model.intersect(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="directions"):
        model.occluded(np.zeros((4, 3)), np.zeros(12))
    with pytest.raises(ValueError, match="tmax"):
        model.intersect(np.zeros((4, 3)), np.ones((4, 3)), tmax=np.ones(3))
    with pytest.raises(ValueError, match="tmin"):
        model.occluded(np.zeros((4, 3)), np.ones((4, 3)), tmin=np.zeros((4, 1)))
    with pytest.raises(ValueError, match="transform"):
        model.intersect(np.zeros((4, 3)), np.ones((4, 3)), transform=np.eye(3))
    with pytest.raises(lsnif.Error, match="lsnif_intersect_instance: invalid"):
        model.intersect(np.zeros((4, 3)), np.ones((4, 3)), transform=np.zeros((3, 4)))
    with pytest.raises(ValueError, match="arithmetic"):
        model.arithmetic = "fp64"
    assert issubclass(lsnif.Error, RuntimeError)
    truncated = tmp_path / "truncated.lsnif"
    truncated.write_bytes(pathlib.Path(model.path).read_bytes()[:1000])
    with pytest.raises(lsnif.Error, match=r"truncated\.lsnif: .*truncated"):
        lsnif.open(truncated)
    with pytest.raises(lsnif.Error, match=r"missing\.lsnif: "):
        lsnif.open(str(tmp_path / "missing.lsnif"))
    text = tmp_path / "text.lsnif"
    text.write_text("not an asset\n")
    with pytest.raises(lsnif.Error, match=r"text\.lsnif: "):
        lsnif.open(text)
    odd = os.path.join(os.fsencode(tmp_path), b"\xff.lsnif")  # not UTF-8
    with open(odd, "wb") as f:
        f.write(b"LSNIF")
    with pytest.raises(lsnif.Error, match=r"\\xff\.lsnif: "):
        lsnif.open(odd)
    with lsnif.open(os.fsencode(model.path)) as same:
        assert same.path == os.fsencode(model.path)
        assert same.info["parameter_count"] == model.info["parameter_count"]
    closed = lsnif.open(pathlib.Path(model.path))
    assert repr(closed) == f"<lsnif.Model {str(model.path)!r}>"
    closed.close()
    with pytest.raises(ValueError, match="closed"):
        closed.info
    with pytest.raises(ValueError, match="closed"):
        closed.intersect(np.zeros((4, 3)), np.ones((4, 3)))
    closed.close()  # twice is harmless


def test_arithmetic_can_be_chosen(model):
    origins, directions = rays_at_box(model, 5000, seed=4)
    model.arithmetic = "fp32"
    assert model.arithmetic == "fp32"
    fp32 = model.intersect(origins, directions)["hit"]
    for name in ("bf16", "int8", "auto"):
        model.arithmetic = name
        assert model.arithmetic in ("fp32", "bf16", "int8")  # what is in use after any fallback
        assert np.mean(model.intersect(origins, directions)["hit"] == fp32) >= 0.995


def test_escape_rule_takes_only_rays_that_start_in_the_surface(model):
    """Rays from outside never escape; rays leaving a hit point (1e-4 of the diagonal off it,
    a tenth of the diagonal long) that escape become misses, and every other answer stays."""
    origins, directions = rays_at_box(model, 20_000, seed=6)
    assert model.escape_points == 0
    outside = model.intersect(origins, directions)
    model.escape_points = 2
    try:
        assert model.escape_points == 2
        again = model.intersect(origins, directions)
        assert all(np.array_equal(again[k], outside[k]) for k in outside)
        hit = outside["hit"]
        diag = float(np.linalg.norm(np.array(model.info["box_max"]) - np.array(model.info["box_min"])))
        normals = outside["normal"][hit]
        points = origins[hit] + outside["t"][hit, None] * directions[hit]
        toward = np.sign(np.sum(normals * directions[hit], axis=1))[:, None]
        leave_dir = -toward * normals  # back along the normal, on the side the ray came from
        leave_org = (points + leave_dir * 1e-4 * diag).astype(np.float32)
        leave_dir = leave_dir.astype(np.float32)
        escaped = model.occluded(leave_org, leave_dir, 0.0, 0.1 * diag)
        model.escape_points = 0
        exact = model.occluded(leave_org, leave_dir, 0.0, 0.1 * diag)
        assert np.all(escaped <= exact)  # the rule only turns answers into misses
        # At the largest limit every ray whose occupied voxels are one run of face neighbours
        # from its start escapes: a superset of those at 2.
        model.escape_points = model.info["max_points"]
        everything = model.occluded(leave_org, leave_dir, 0.0, 0.1 * diag)
        assert np.all(everything <= escaped)
        if not model.path.endswith("v1_default.lsnif"):
            # On a converted mesh the network calls some of those rays hits (along the surface).
            # v1_default is the test generator's shell of voxels under random weights: where
            # its hits lie, and so whether any of its answers changes, is arbitrary.
            assert everything.sum() < exact.sum()
        with pytest.raises(ValueError, match="escape_points"):
            model.escape_points = model.info["max_points"] + 1
    finally:
        model.escape_points = 0


def test_enclosed_rule_only_turns_occlusion_answers_into_hits(model):
    """With the rule on, intersections keep every bit and occlusion answers only turn from miss
    to hit; off again, every answer is the network's."""
    origins, directions = rays_at_box(model, 20_000, seed=7)
    assert model.enclosed_rule is False
    exact = model.occluded(origins, directions)
    closest = model.intersect(origins, directions)
    model.enclosed_rule = True
    try:
        assert model.enclosed_rule is True
        ruled = model.occluded(origins, directions)
        again = model.intersect(origins, directions)
        assert all(np.array_equal(again[k], closest[k]) for k in closest)
        assert np.all(ruled >= exact)
    finally:
        model.enclosed_rule = False
    assert np.array_equal(model.occluded(origins, directions), exact)


def test_threads_trace_in_parallel_with_the_serial_answers(model):
    origins, directions = rays_at_box(model, 200_000, seed=5)
    serial = model.intersect(origins, directions)["t"]
    results = {}

    def trace(name):
        results[name] = model.intersect(origins, directions)["t"]

    workers = [threading.Thread(target=trace, args=(k,)) for k in ("a", "b")]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    for name in ("a", "b"):
        assert np.array_equal(results[name].view(np.uint32), serial.view(np.uint32))


def test_a_trace_releases_the_gil(model):
    """A thread counts while the main thread traces. Without forced switches the main thread
    keeps the GIL through the call unless the call releases it, so the count moves during a
    trace exactly when the GIL is released; a few tries allow for a counter thread that the
    scheduler left asleep through a whole trace."""
    origins, directions = rays_at_box(model, 100_000, seed=6)
    count, stop = [0], threading.Event()

    def counter():
        while not stop.is_set():
            count[0] += 1
            time.sleep(0.0002)

    with no_forced_gil_switches():
        thread = threading.Thread(target=counter)
        thread.start()
        try:
            moved = False
            for _ in range(20):
                before = count[0]
                model.occluded(origins, directions)
                model.intersect(origins, directions)
                if count[0] != before:
                    moved = True
                    break
        finally:
            stop.set()
            thread.join()
    assert moved


def test_close_and_arithmetic_while_another_thread_traces(model):
    """close() from one thread while another traces: the trace completes with the right
    answers and the handle is released after it. The arithmetic cannot change meanwhile."""
    origins, directions = rays_at_box(model, 100_000, seed=7)
    want = model.intersect(origins, directions)["t"]
    for action in ("close", "arithmetic"):
        other = lsnif.open(model.path)
        started, result, raised = threading.Event(), {}, []

        def trace():
            started.set()
            result["t"] = other.intersect(origins, directions)["t"]

        with no_forced_gil_switches():
            worker = threading.Thread(target=trace)
            worker.start()
            # The worker keeps the GIL from started.set() until its trace releases it: this
            # thread continues only once that trace is running.
            started.wait()
            try:
                if action == "close":
                    other.close()
                else:
                    other.arithmetic = "fp32"
            except lsnif.Error as e:
                raised.append(str(e))
            worker.join()
        assert np.array_equal(result["t"].view(np.uint32), want.view(np.uint32))
        if action == "close":
            assert not raised
            with pytest.raises(ValueError, match="closed"):
                other.info
        else:
            assert len(raised) == 1 and "arithmetic cannot change" in raised[0]
            other.arithmetic = "fp32"  # once no trace runs
            assert other.arithmetic == "fp32"
            other.close()
