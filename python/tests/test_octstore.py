"""The Python package against the command line on the same store, readers beside a writer, and
bad inputs. The scene: a sphere in a room, seen by a ring of cameras, rendered with numpy."""

import json
import os
import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest

import octstore

REPO = Path(__file__).resolve().parents[2]
SPHERE_CENTER = np.array([0.1, -0.05, 0.0])
SPHERE_RADIUS = 0.5
ROOM_HALF = 2.0


def octstore_cli():
    """The `octstore` binary the tests compare with: $OCTSTORE_BIN, else the release build."""
    path = Path(os.environ.get("OCTSTORE_BIN", REPO / "target" / "release" / "octstore"))
    if not path.exists():
        pytest.fail(f"no octstore binary at {path}: run `cargo build --release` or set OCTSTORE_BIN")
    return str(path)


def cli(*args):
    result = subprocess.run([octstore_cli(), *map(str, args)], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    return result.stdout


def look_at(eye, target):
    """Camera-to-world with OpenCV axes (x right, y down, z forward), z up in the world."""
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
    return pose


def render(pose, K, width, height):
    """Pinhole depth (z in the camera) of the sphere inside the room's walls."""
    j, i = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.stack([(i - K[0, 2]) / K[0, 0], (j - K[1, 2]) / K[1, 1], np.ones_like(i)], axis=-1)
    d = rays @ pose[:3, :3].T  # world direction per unit of camera depth
    o = pose[:3, 3]
    # Room: the nearest wall the ray leaves through.
    with np.errstate(divide="ignore"):
        t_walls = np.where(d > 0, (ROOM_HALF - o) / d, (-ROOM_HALF - o) / d)
    t = np.min(np.where(np.isfinite(t_walls) & (t_walls > 0), t_walls, np.inf), axis=-1)
    # Sphere.
    oc = o - SPHERE_CENTER
    a = np.sum(d * d, axis=-1)
    b = np.sum(d * oc, axis=-1)
    c = oc @ oc - SPHERE_RADIUS**2
    disc = b * b - a * c
    hit = disc >= 0
    t_sphere = np.where(hit, (-b - np.sqrt(np.where(hit, disc, 0))) / a, np.inf)
    t = np.where((t_sphere > 0) & (t_sphere < t), t_sphere, t)
    return t.astype(np.float32)


def views(count=8, width=64, height=48):
    K = np.array([[50.0, 0, width / 2], [0, 50.0, height / 2], [0, 0, 1]])
    poses, depths = [], []
    for k in range(count):
        angle = 2 * np.pi * k / count
        eye = np.array([1.6 * np.cos(angle), 1.6 * np.sin(angle), 0.4 if k % 2 else -0.4])
        pose = look_at(eye, SPHERE_CENTER)
        poses.append(pose)
        depths.append(render(pose, K, width, height))
    return np.stack(depths), K, np.stack(poses)


OPTIONS = dict(max_depth=7, quiet=True, threads=2)


@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    """A store built and solved through the package (depth maps from arrays)."""
    path = tmp_path_factory.mktemp("scene") / "store"
    store = octstore.Store.create(path)
    depths, K, poses = views()
    report = octstore.ingest_arrays(store, depths, K, poses, kind="rgbd", **OPTIONS)
    assert report.stage == "ingest" and report.version == 1, report
    reports = octstore.solve(store, iterations=40, device="cpu", quiet=True, threads=2)
    assert reports and reports[-1].version is not None, reports
    return store


def test_indicator_matches_the_command_line_and_the_geometry(solved):
    snap = solved.snapshot()
    rng = np.random.default_rng(5)
    points = np.concatenate(
        [
            SPHERE_CENTER + rng.normal(size=(20, 3)) * 0.05,  # inside the sphere
            SPHERE_CENTER + np.array([[1.0, 0, 0], [0, -1.0, 0], [-0.9, 0, 0]]),  # free space
        ]
    )
    u = snap.indicator(points)
    assert u.dtype == np.float32 and u.shape == (len(points),)
    assert np.all(u[:20] < 0), u[:20]
    assert np.all(u[20:] > 0), u[20:]
    for point, value in zip(points[::4], u[::4]):
        answer = json.loads(cli("query", solved.path, "--json", "--point", ",".join(repr(float(v)) for v in point)))
        # The command line prints u's shortest decimal form: the same f32, bit for bit.
        assert np.float32(answer["u"]) == value, (point, answer, value)
    # Outside the root: NaN.
    assert np.isnan(snap.indicator(np.array([[1e6, 0, 0]])))[0]
    # Any real dtype and layout.
    assert np.array_equal(snap.indicator(points.astype(np.float32)), snap.indicator(points.astype(np.float32).astype(np.float64)))
    assert np.array_equal(snap.indicator(np.asfortranarray(points)), u)


def test_extract_is_the_command_lines_mesh(solved, tmp_path):
    snap = solved.snapshot()
    ours = tmp_path / "python.ply"
    vertices, faces, normals = snap.extract(path=ours)
    theirs = tmp_path / "cli.ply"
    cli("extract", solved.path, "-o", theirs)
    assert ours.read_bytes() == theirs.read_bytes()
    assert vertices.dtype == np.float32 and vertices.shape[1] == 3 and len(vertices) > 100
    assert faces.dtype == np.uint32 and faces.shape[1] == 3 and faces.max() < len(vertices)
    assert normals.shape == vertices.shape
    # The sphere's vertices lie on it (within about a finest cube: root ~4.4 m / 2^7).
    near = np.linalg.norm(vertices - SPHERE_CENTER, axis=1)
    on_sphere = near[near < 1.0]
    assert len(on_sphere) > 50 and np.median(np.abs(on_sphere - SPHERE_RADIUS)) < 0.035
    region = [-0.5, -0.6, -0.6, 0.7, 0.6, 0.6]
    clipped, _, _ = snap.extract(region=region)
    assert 0 < len(clipped) < len(vertices)


def test_cubes_versions_and_snapshots(solved):
    snap = solved.snapshot()
    assert snap.method() == "tgv" and snap.levels()[-1] == 7
    cubes = snap.cubes([-0.3, -0.3, -0.3, 0.3, 0.3, 0.3])
    n = len(cubes["u"])
    assert n > 10
    assert cubes["center"].shape == (n, 3) and cubes["histogram"].shape == (n, 8)
    assert cubes["observed"].dtype == np.bool_ and len(cubes["key"]) == n
    versions = solved.versions()
    assert versions == sorted(versions) and versions[-1] == snap.version
    assert solved.snapshot(versions[0]).version == versions[0]


def build_half(path, iterations):
    """A store of the first four views, solved; returns the writer and the other four views'
    (depths, K, poses), for a second ingest."""
    writer = octstore.Store.create(path)
    depths, K, poses = views()
    octstore.ingest_arrays(writer, depths[:4], K, poses[:4], **OPTIONS)
    octstore.solve(writer, iterations=iterations, device="cpu", quiet=True, threads=2)
    return writer, (depths[4:], K, poses[4:])


def test_readers_in_threads_see_their_version_while_a_writer_runs(tmp_path):
    path = tmp_path / "store"
    writer, rest = build_half(path, iterations=20)
    pinned = writer.snapshot().version
    points = SPHERE_CENTER + np.random.default_rng(1).normal(size=(2000, 3)) * 0.6
    expected = writer.snapshot(pinned).indicator(points)

    done = threading.Event()
    reads, failures = [0], []

    def reader():
        store = octstore.Store.open_read_only(path)
        try:
            while not done.is_set():
                got = store.snapshot(pinned).indicator(points)
                if not np.array_equal(got, expected, equal_nan=True):
                    failures.append("changed")
                reads[0] += 1
        except Exception as e:  # noqa: BLE001 - reported below
            failures.append(repr(e))

    threads = [threading.Thread(target=reader) for _ in range(3)]
    for t in threads:
        t.start()
    try:
        octstore.ingest_arrays(writer, *rest, **OPTIONS)
        octstore.solve(writer, iterations=20, device="cpu", quiet=True, threads=2)
    finally:
        done.set()
        for t in threads:
            t.join()
    assert not failures, failures[:3]
    assert reads[0] > 3, "the readers did not run while the writer held the GIL-free work"
    assert writer.snapshot().version > pinned


def test_bad_inputs_raise_clear_errors(tmp_path):
    store = octstore.Store.create(tmp_path / "store")
    created = store.versions()
    depths, K, poses = views(count=1)
    with pytest.raises(TypeError, match="float array of metres"):
        octstore.ingest_arrays(store, (depths[0] * 1000).astype(np.uint16), K, poses[0])
    with pytest.raises(ValueError, match="shape"):
        octstore.ingest_arrays(store, depths[0].reshape(-1), K, poses[0])
    with pytest.raises(ValueError, match="camera_to_world"):
        octstore.ingest_arrays(store, depths[0], K, np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match="K must have shape"):
        octstore.ingest_arrays(store, depths[0], K[:2], poses[0])
    scaled = poses[0].copy()
    scaled[:3, :3] *= 2.0
    with pytest.raises(octstore.OctstoreError, match="pose"):
        octstore.ingest_arrays(store, depths[0], K, scaled, quiet=True)
    with pytest.raises(octstore.OctstoreError, match="missing.json"):
        octstore.ingest(store, tmp_path / "missing.json", quiet=True)
    with pytest.raises(octstore.OctstoreError, match="--max-depth"):
        octstore.ingest_arrays(store, depths[0], K, poses[0], max_depth=99, quiet=True)
    with pytest.raises(octstore.OctstoreError, match="--iterations"):
        octstore.solve(store, iterations=0)
    with pytest.raises(octstore.OctstoreError, match="unexpected argument"):
        octstore.solve(store, no_such_option=3)
    # Nothing above committed a version: the store is as it was created.
    assert store.versions() == created
    with pytest.raises(octstore.OctstoreError):
        octstore.Store.open(tmp_path / "nowhere")
    reader = octstore.Store.open_read_only(tmp_path / "store")
    # Before any solve there is no field: NaN, as outside the root.
    assert np.isnan(reader.snapshot().indicator(np.zeros((1, 3)))).all()
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        reader.snapshot().indicator(np.zeros((4, 2)))
    with pytest.raises(TypeError, match="real numbers"):
        reader.snapshot().indicator(np.array([["a", "b", "c"]]))


def test_a_snapshot_keeps_its_version_from_gc(tmp_path):
    path = tmp_path / "store"
    writer, rest = build_half(path, iterations=10)
    first = writer.snapshot().version
    octstore.ingest_arrays(writer, *rest, **OPTIONS)
    octstore.solve(writer, iterations=10, device="cpu", quiet=True, threads=2)
    del writer  # gc runs in another process, which needs the writer's lock
    reader = octstore.Store.open_read_only(path)
    held = reader.snapshot(first)
    points = SPHERE_CENTER + np.random.default_rng(2).normal(size=(500, 3)) * 0.5
    before = held.indicator(points)
    out = cli("gc", path, "--keep", "1")
    assert np.array_equal(held.indicator(points), before, equal_nan=True), out
    # A version nobody held is gone, and reading it says so.
    with pytest.raises(octstore.OctstoreError, match="gc|gone|collected"):
        reader.snapshot(first - 1).indicator(points)
