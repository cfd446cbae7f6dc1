#!/usr/bin/env python3
"""Comparison benchmarks: octstore against Open3D's TSDF fusion (VoxelBlockGrid) and screened
Poisson on the same depth maps. Run through tools/bench/run.sh, which sets up the Python
environment and builds octstore; this script writes BENCHMARKS.md and PNG plots.

Sections:
  objects      the bunny and the dragon seen from all around in empty space (background pixels 0)
               at two scales, clean and noisy: octstore with no flags against TSDF at its best
               voxel and truncation and Poisson with outlier removal
  groundtruth  the bunny and the dragon rendered by octstore-gt-render at several noise and
               outlier levels; accuracy, completeness, Chamfer and F-score from octstore-evaluate
  redkitchen   RedKitchen subsets: wall time, CPU time, peak RSS and output size for octstore and
               TSDF at the same voxel size
  divide       `octstore divide` of a generated billion-point cloud at two memory budgets, and the
               bunny divided, reconstructed part by part and merged (divide_bench.py)

Every method sees exactly the same depth maps and poses. Wall and CPU time and peak RSS of
Open3D are measured in a child process (resource.getrusage of the children), like octstore's.
"""

import argparse
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT.parent / "shared" / "data"
BIN = ROOT / "target" / "release"


def run_measured(args, **kwargs):
    """Runs a command; returns (stdout, stderr, wall seconds, CPU seconds, peak RSS MB) of the
    child."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.monotonic()
    out = subprocess.run(args, check=True, capture_output=True, text=True, **kwargs)
    wall = time.monotonic() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    # ru_maxrss of the children is the largest child so far: each measured run is the largest
    # of its own sub-processes only when runs are ordered small to large; the worker therefore
    # reports its own peak, and octstore prints its own.
    return out.stdout, out.stderr, wall, cpu, after.ru_maxrss / 1024.0


class DiskPeak:
    """The most bytes the file system holding `path` gained over its use at entry, polled every
    `period` seconds while the `with` block runs: a store and its scratch files (which ingest
    unlinks as it creates them, so no listing of the store finds them)."""

    def __init__(self, path, period=1.0):
        self.path, self.period = path, period
        self.peak_bytes = 0

    def _poll(self):
        while not self._stop.wait(self.period):
            self.peak_bytes = max(self.peak_bytes, shutil.disk_usage(self.path).used - self._base)

    def __enter__(self):
        import threading

        self._base = shutil.disk_usage(self.path).used
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak_bytes = max(self.peak_bytes, shutil.disk_usage(self.path).used - self._base)
        return False


def tree_bytes(path):
    """Bytes the files under `path` take on disk."""
    return sum(os.stat(Path(root) / name).st_blocks * 512 for root, _, names in os.walk(path) for name in names)


def mesh_triangles(path):
    """Faces of a PLY file, from its header."""
    with open(path, "rb") as f:
        for line in f:
            if line.startswith(b"element face"):
                return int(line.split()[2])
            if line.strip() == b"end_header":
                break
    raise ValueError(f"{path}: no face element in the PLY header")


# ---------------------------------------------------------------------------------------------
# Depth maps as every method sees them


def read_pfm(path):
    import numpy as np

    data = Path(path).read_bytes()
    header, rest = data.split(b"\n", 1)
    if header.strip() != b"Pf":
        raise ValueError(f"{path}: not a one-channel PFM")
    dims, rest = rest.split(b"\n", 1)
    scale, rest = rest.split(b"\n", 1)
    width, height = (int(x) for x in dims.split())
    dtype = "<f4" if float(scale) < 0 else ">f4"
    image = np.frombuffer(rest, dtype=dtype, count=width * height).reshape(height, width)
    return np.flipud(image).astype(np.float32)


def read_manifest(manifest):
    """(depth in metres with 0 for missing, K 3x3, camera-to-world 4x4) per view."""
    import numpy as np

    spec = json.loads(Path(manifest).read_text())
    views = []
    for entry in spec["depth_maps"]:
        depth = read_pfm(Path(manifest).parent / entry["image"])
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
        k = entry["intrinsics"]
        intrinsic = np.array([[k["fx"], 0, k["cx"]], [0, k["fy"], k["cy"]], [0, 0, 1]], dtype=np.float64)
        pose = np.array(entry["pose"]["camera_to_world"], dtype=np.float64).reshape(4, 4)
        if entry["pose"].get("axes", "opencv") != "opencv":
            raise ValueError(f"{manifest}: only OpenCV camera axes are handled here")
        views.append((depth, intrinsic, pose))
    return views


def read_redkitchen(frames):
    import numpy as np
    import open3d as o3d

    folder = SHARED / "7scenes-redkitchen"
    intrinsic = np.loadtxt(folder / "camera-intrinsics.txt")
    stride = 1000 // frames
    views = []
    for i in range(0, 1000, stride)[:frames]:
        depth = np.asarray(o3d.io.read_image(str(folder / f"frame-{i:06d}.depth.png"))).astype(np.float32)
        depth[depth >= 65535] = 0
        pose = np.loadtxt(folder / f"frame-{i:06d}.pose.txt")
        views.append((depth / 1000.0, intrinsic, pose))
    return views


# ---------------------------------------------------------------------------------------------
# The other tools (run in a child process: `bench.py worker METHOD ...`)


def read_seven_scenes(folder):
    """(depth in scene units with 0 for missing, K 3x3, camera-to-world 4x4) per frame of a
    7-Scenes folder (16-bit PNG depths in thousandths of a unit)."""
    import numpy as np
    import open3d as o3d

    folder = Path(folder)
    intrinsic = np.loadtxt(folder / "camera-intrinsics.txt")
    views = []
    for png in sorted(folder.glob("frame-*.depth.png")):
        depth = np.asarray(o3d.io.read_image(str(png))).astype(np.float32)
        depth[depth >= 65535] = 0
        pose = np.loadtxt(str(png).replace(".depth.png", ".pose.txt"))
        views.append((depth / 1000.0, intrinsic, pose))
    return views


def tsdf(views, voxel, depth_max, out, truncation=8.0):
    import numpy as np
    import open3d as o3d
    import open3d.core as o3c

    device = o3c.Device("CPU:0")
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"),
        attr_dtypes=(o3c.float32, o3c.float32),
        attr_channels=((1), (1)),
        voxel_size=voxel,
        block_resolution=8,
        block_count=200000,
        device=device,
    )
    for depth, intrinsic, pose in views:
        image = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth))).to(device)
        k = o3c.Tensor(intrinsic, o3c.float64)
        extrinsic = o3c.Tensor(np.linalg.inv(pose), o3c.float64)
        blocks = grid.compute_unique_block_coordinates(image, k, extrinsic, 1.0, depth_max)
        grid.integrate(blocks, image, k, extrinsic, 1.0, depth_max, truncation)
    mesh = grid.extract_triangle_mesh().to_legacy()
    o3d.io.write_triangle_mesh(str(out), mesh)


def back_project(views, step):
    """Points and normals (oriented to their camera) of every `step`-th pixel."""
    import numpy as np
    import open3d as o3d

    clouds = o3d.geometry.PointCloud()
    for depth, intrinsic, pose in views:
        h, w = depth.shape
        jj, ii = np.mgrid[0:h:step, 0:w:step]
        z = depth[jj, ii]
        keep = z > 0
        x = (ii[keep] - intrinsic[0, 2]) * z[keep] / intrinsic[0, 0]
        y = (jj[keep] - intrinsic[1, 2]) * z[keep] / intrinsic[1, 1]
        local = np.stack([x, y, z[keep], np.ones_like(x)], axis=1)
        world = (pose @ local.T).T[:, :3]
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(world))
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(16))
        cloud.orient_normals_towards_camera_location(pose[:3, 3])
        clouds += cloud
    return clouds


def poisson(views, depth_level, out, remove_outliers=False):
    import numpy as np
    import open3d as o3d

    cloud = back_project(views, 2)
    if remove_outliers:
        # Open3D's statistical outlier removal: points whose mean distance to their 20
        # neighbours is over 2 deviations above the cloud's.
        cloud, _ = cloud.remove_statistical_outlier(nb_neighbors=20, std_ratio=2.0)
    mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(cloud, depth=depth_level)
    # The usual trimming of unsupported surface: drop the 2 % least dense vertices.
    densities = np.asarray(densities)
    mesh.remove_vertices_by_mask(densities < np.quantile(densities, 0.02))
    o3d.io.write_triangle_mesh(str(out), mesh)


def worker(argv):
    method, source, out = argv[0], argv[1], Path(argv[2])
    if source.endswith(".json"):
        views = read_manifest(source)
    elif Path(source).is_dir():
        views = read_seven_scenes(source)
    else:
        views = read_redkitchen(int(source))
    if method == "tsdf":
        tsdf(views, float(argv[3]), float(argv[4]), out, *(float(a) for a in argv[5:6]))
    elif method == "poisson":
        poisson(views, int(argv[3]), out, remove_outliers=argv[4:5] == ["remove-outliers"])
    else:
        raise SystemExit(f"unknown method {method}")
    print(json.dumps({"peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}))


def run_worker(*args):
    stdout, _, wall, cpu, _ = run_measured([sys.executable, __file__, "worker", *map(str, args)])
    peak = json.loads(stdout.strip().splitlines()[-1])["peak_mb"]
    return wall, cpu, peak


# ---------------------------------------------------------------------------------------------
# octstore


STAGE_LINE = re.compile(r"^(\S+)\s.*\| ([0-9.]+)s \| peak memory ([0-9]+) MB")
LEVEL_CUBES = re.compile(r"level [0-9]+: ([0-9]+) cubes, .*\(([0-9]+) iterations per cube")
OCTREE_PARTS = re.compile(r"octree: merge ([0-9.]+)s, balance ([0-9.]+)s, nodes ([0-9.]+)s, treetop ([0-9.]+)s")
# Extraction's log of its open seams: what grows with the scene's cross-section.
SEAM_LINE = re.compile(r"extract: at most ([0-9]+) seam vertices and ([0-9]+) seam edges open at once; .* held at most "
                       r"([0-9]+) MB along the open seams(?: \(the weld ([0-9]+) MB of it\))?")


def octstore(store, source, args_ingest, args_solve, mesh, budget=None, args_extract=()):
    """Ingest, solve and extract. Returns wall and CPU time of the three, the largest peak RSS,
    and the stage breakdown: seconds and peak MB per stage from octstore's summary lines, plus
    the octree stage's parts (merge, balance, nodes, treetop) from its log."""
    octstore_bin = str(BIN / "octstore")
    total_wall = total_cpu = peak = 0.0
    stages = {}
    common = ["--quiet"] + (["--memory-budget", budget] if budget else [])
    for args in (
        ["ingest", str(store), str(source), *args_ingest],
        ["solve", str(store), *args_solve],
        ["extract", str(store), "-o", str(mesh), *args_extract],
    ):
        # `--quiet` keeps the log at warnings: its info lines (the octree's parts, extraction's
        # open seams) are asked for by name.
        env = {**os.environ, "OCTSTORE_LOG": "warn,octstore=info"}
        stdout, stderr, wall, cpu, _ = run_measured([octstore_bin, *common, *args], env=env)
        total_wall += wall
        total_cpu += cpu
        for line in stdout.splitlines():
            match = STAGE_LINE.match(line)
            if match:
                name, seconds, mb = match.group(1), float(match.group(2)), float(match.group(3))
                stages[name] = {"seconds": seconds, "peak_mb": mb}
                level = LEVEL_CUBES.search(line)
                if name.startswith("solution-") and level:
                    # The cubes of the level's cut: each is updated once per iteration.
                    stages[name]["cubes"] = int(level.group(1))
                    stages[name]["iterations"] = int(level.group(2))
                peak = max(peak, mb)
        for line in stderr.splitlines():
            match = OCTREE_PARTS.search(line)
            if match:
                stages["octree-parts"] = dict(zip(("merge", "balance", "nodes", "treetop"), map(float, match.groups())))
            match = SEAM_LINE.search(line)
            if match:
                stages["extract-seams"] = {k: int(v) for k, v in zip(("vertices", "edges", "held_mb", "weld_mb"),
                                                                     match.groups()) if v is not None}
    return total_wall, total_cpu, peak, stages


TAUS = (0.01, 0.005, 0.002)


def evaluate(mesh, truth, extra=()):
    """octstore-evaluate at tau = 1 % of the diagonal (all its figures, samples tau / 5 apart)
    and the F-score at 0.5 % and 0.2 % (`f_score_0.005`, `f_score_0.002`; samples tau / 2 apart,
    which keeps a room's tens of millions of samples to a few)."""
    result = {}
    for tau in TAUS:
        spacing = [] if tau == TAUS[0] else ["--spacing", str(tau / 2)]
        out = subprocess.run(
            [str(BIN / "octstore-evaluate"), str(mesh), str(truth), "--json", "--tau", str(tau), *spacing, *extra],
            check=True, capture_output=True, text=True,
        )
        figures = json.loads(out.stdout)
        if tau == TAUS[0]:
            result.update(figures)
        result[f"f_score_{tau}"] = figures["f_score"]
    return result


# ---------------------------------------------------------------------------------------------
# Sections


GT_MESHES = {"bunny": SHARED / "meshes" / "bunny00.off", "dragon": SHARED / "meshes" / "dragon_vrip_res3.ply.gz"}
GT_NOISE = [0.002, 0.01]
GT_OUTLIERS = [0.0, 0.05, 0.2]


# Objects seen from all around in empty space (no room, no ground: background pixels 0), at
# two scales: 0.3 m seen from 0.6 m in metres (PFM files and a manifest), and 3 units seen from
# 4 to 8 units in a 7-Scenes folder (16-bit PNG, thousandths of a unit). Clean, and with 0.5 %
# depth noise plus 10 % outlier pixels. 60 views of 320x240 from a sphere.
OBJECT_SCALES = {
    "0.3 m at 0.6 m": {"size": 0.3, "near": 0.6, "far": None, "seven_scenes": False},
    "3 units at 4-8": {"size": 3.0, "near": 4.0, "far": 8.0, "seven_scenes": True},
}
OBJECT_NOISES = [(0.0, 0.0), (0.005, 0.1)]
# TSDF's best of these voxels (fractions of the diagonal) and truncations (voxels) by F at 1 %.
OBJECT_TSDF_VOXELS = [0.0025, 0.005, 0.01]
OBJECT_TSDF_TRUNCATIONS = [4.0, 8.0]


def read_object_mesh(work, name, source):
    """The ground-truth mesh `name` (`GT_MESHES`) as an Open3D mesh, gunzipped into `work` first
    when stored compressed."""
    import open3d as o3d

    if str(source).endswith(".gz"):
        import gzip

        plain = work / f"{name}.ply"
        plain.write_bytes(gzip.decompress(Path(source).read_bytes()))
        source = plain
    return o3d.io.read_triangle_mesh(str(source))


def write_scaled(original, factor, path):
    """`original` scaled by `factor` about the origin, written to `path`."""
    import open3d as o3d

    scaled = o3d.geometry.TriangleMesh(original)
    scaled.scale(factor, center=(0.0, 0.0, 0.0))
    o3d.io.write_triangle_mesh(str(path), scaled)


# The same capture in other units (issue's scale test): the 0.3 m object at 0.6 m, its depths
# and poses multiplied by each factor (PFM files keep every digit).
OBJECT_UNIT_FACTORS = [(1.0, "metres"), (10.0, "decimetres (x 10)"), (1000.0, "millimetres (x 1000)")]


def object_units(work):
    """octstore with no flags on the bunny and the dragon in empty space (0.3 m at 0.6 m, clean
    and noisy), in metres, decimetres and millimetres: each mesh scaled back to metres against
    the mesh made in metres (F at 0.2 % of the diagonal: the issue's criterion is 0.99), and
    against the ground truth."""
    import numpy as np
    import open3d as o3d

    rows = []
    spec = OBJECT_SCALES["0.3 m at 0.6 m"]
    for name, source in GT_MESHES.items():
        original = read_object_mesh(work, name, source)
        extent = np.asarray(original.get_max_bound()) - np.asarray(original.get_min_bound())
        metres = spec["size"] / extent.max()
        diagonal = float(np.linalg.norm(extent)) * metres
        truth = work / f"units-{name}-truth.ply"
        write_scaled(original, metres, truth)
        for noise, outliers in OBJECT_NOISES:
            reference = None
            for factor, units in OBJECT_UNIT_FACTORS:
                case = work / f"units-{name}-{noise}-{factor:g}"
                views = case / "views"
                subprocess.run(
                    [str(BIN / "octstore-gt-render"), str(source), "--out", str(views), "--views", "60", "--width",
                     "320", "--height", "240", "--room", "0", "--scale", str(metres * factor), "--distance",
                     str(spec["near"] / diagonal), "--noise", str(noise), "--outliers", str(outliers)],
                    check=True, capture_output=True,
                )
                mesh = case / "octstore.ply"
                wall, cpu, peak, _ = octstore(case / "store", views / "scene.json", [], [], mesh)
                back = case / "octstore-in-metres.ply"
                made = o3d.io.read_triangle_mesh(str(mesh))
                made.scale(1.0 / factor, center=(0.0, 0.0, 0.0))
                o3d.io.write_triangle_mesh(str(back), made)
                reference = reference or back
                against_metres = evaluate(back, reference)
                row = {"mesh": name, "noise": noise, "outliers": outliers, "units": units, "factor": factor,
                       "wall_s": wall, "peak_mb": peak, "triangles": len(made.triangles),
                       "f_score_0.002_vs_metres": against_metres["f_score_0.002"],
                       "f_score_vs_metres": against_metres["f_score"],
                       **{f"truth_{k}": v for k, v in evaluate(back, truth).items()
                          if k in ("f_score", "f_score_0.002", "normal_consistency")},
                       **mesh_topology(back)}
                rows.append(row)
                print(json.dumps(row), flush=True)
    return rows


def mesh_topology(mesh):
    """Connected components and boundary edges of a mesh."""
    import numpy as np
    import open3d as o3d

    m = o3d.io.read_triangle_mesh(str(mesh))
    triangles = np.asarray(m.triangles)
    if len(triangles) == 0:
        return {"components": 0, "boundary_edges": 0}
    clusters, _, _ = m.cluster_connected_triangles()
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return {"components": int(len(np.unique(np.asarray(clusters)))), "boundary_edges": int((counts == 1).sum())}


def objects(work, out_dir):
    """octstore with no flags at all against TSDF at its best voxel and truncation and screened
    Poisson with outlier removal, on the bunny and the dragon in empty space (OBJECT_SCALES,
    OBJECT_NOISES); measured uncropped, with the meshes' components and boundary edges, and a
    picture of each octstore mesh."""
    import numpy as np
    import open3d as o3d

    rows = []
    for name, source in GT_MESHES.items():
        original = read_object_mesh(work, name, source)
        extent = np.asarray(original.get_max_bound()) - np.asarray(original.get_min_bound())
        for scale_name, spec in OBJECT_SCALES.items():
            factor = spec["size"] / extent.max()
            diagonal = float(np.linalg.norm(extent)) * factor
            truth = work / f"{name}-{spec['size']}.ply"
            write_scaled(original, factor, truth)
            for noise, outliers in OBJECT_NOISES:
                case = work / f"object-{name}-{spec['size']}-{noise}"
                views = case / "views"
                render = [str(BIN / "octstore-gt-render"), str(source), "--out", str(views), "--views", "60",
                          "--width", "320", "--height", "240", "--room", "0", "--scale", str(factor),
                          "--distance", str(spec["near"] / diagonal), "--noise", str(noise), "--outliers",
                          str(outliers)]
                if spec["far"]:
                    render += ["--far", str(spec["far"] / diagonal)]
                if spec["seven_scenes"]:
                    render += ["--seven-scenes"]
                subprocess.run(render, check=True, capture_output=True)
                source_path = views if spec["seven_scenes"] else views / "scene.json"
                results = {}
                mesh = case / "octstore.ply"
                wall, cpu, peak, _ = octstore(case / "store", source_path, [], [], mesh)
                results["octstore (no flags)"] = (mesh, wall, cpu, peak, {})
                # The other solvers, with no flag but the choice of one (a second row each): the
                # default picks ssd for an object against empty background.
                for solver in ("tgv", "hybrid"):
                    mesh = case / f"octstore-{solver}.ply"
                    wall, cpu, peak, _ = octstore(case / f"store-{solver}", source_path, [],
                                                  ["--method", solver], mesh)
                    results[f"octstore --method {solver}"] = (mesh, wall, cpu, peak, {})
                # The observed surface alone, which the default replaces by the watertight one
                # for objects against empty background (a second row).
                mesh = case / "octstore-open.ply"
                wall, cpu, peak, _ = octstore(case / "store-open", source_path, [], [], mesh, args_extract=["--open"])
                results["octstore extract --open"] = (mesh, wall, cpu, peak, {})
                best = None
                for fraction in OBJECT_TSDF_VOXELS:
                    for truncation in OBJECT_TSDF_TRUNCATIONS:
                        candidate = case / f"tsdf-{fraction}-{truncation}.ply"
                        measured = run_worker("tsdf", source_path, candidate, fraction * diagonal, 1e6, truncation)
                        f1 = evaluate(candidate, truth)["f_score"]
                        if best is None or f1 > best[0]:
                            best = (f1, candidate, measured, {"voxel": fraction, "truncation": truncation})
                _, candidate, measured, chosen = best
                results["tsdf (best voxel)"] = (candidate, *measured, chosen)
                mesh = case / "poisson.ply"
                results["poisson (outliers removed)"] = (mesh, *run_worker("poisson", source_path, mesh, 9,
                                                                            "remove-outliers"), {})
                for method, (mesh, wall, cpu, peak, extra) in results.items():
                    row = {"mesh": name, "scale": scale_name, "noise": noise, "outliers": outliers,
                           "method": method, "wall_s": wall, "cpu_s": cpu, "peak_mb": peak, **extra,
                           **evaluate(mesh, truth), **mesh_topology(mesh)}
                    if method == "octstore (no flags)":
                        png = out_dir / f"object-{name}-{spec['size']}-{noise}.png"
                        subprocess.run([str(BIN / "octstore"), "--quiet", "render", str(mesh), "-o", str(png)],
                                       check=True, capture_output=True)
                        row["picture"] = png.name
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    return rows


def interior(work, out_dir):
    """The furnished room seen from inside (`octstore-gt-render --layout interior`, 60 views of
    320x240): octstore (observed surface, the default, and `--closed`), TSDF and Poisson at the
    same cube size, measured over the whole ground truth (no crop: what lies behind the walls
    counts) with completeness over the faces some camera saw; pictures from two of the views."""
    case = work / "interior"
    views = case / "views"
    subprocess.run(
        [str(BIN / "octstore-gt-render"), "--layout", "interior", "--out", str(views), "--views", "60",
         "--width", "320", "--height", "240", "--fov", "70", "--noise", "0.002"],
        check=True, capture_output=True,
    )
    manifest, truth = views / "scene.json", views / "ground-truth.ply"
    extra = ["--no-crop", "--gt-faces", str(views / "seen-faces.txt")]
    # What a user gets with no flags first; then `--max-depth 9`, whose cube side gives TSDF its
    # voxel (at the default's finest cubes, TSDF's grid over the room would not fit in memory).
    default = case / "octstore-no-flags.ply"
    default_run = octstore(case / "store-no-flags", manifest, [], [], default)
    mesh = case / "octstore.ply"
    wall, cpu, peak, _ = octstore(case / "store", manifest, ["--max-depth", "9"], [], mesh)
    closed = case / "octstore-closed.ply"
    subprocess.run([str(BIN / "octstore"), "--quiet", "extract", str(case / "store"), "-o", str(closed), "--closed"],
                   check=True, capture_output=True)
    info = json.loads(subprocess.run(
        [str(BIN / "octstore"), "info", str(case / "store"), "--json"], check=True, capture_output=True, text=True
    ).stdout)
    voxel = info["finest_cube_side"]
    results = {"octstore (no flags)": (default, *default_run[:3]), "octstore --max-depth 9": (mesh, wall, cpu, peak),
               "octstore --max-depth 9 --closed": (closed, wall, cpu, peak)}
    results["tsdf"] = (case / "tsdf.ply", *run_worker("tsdf", manifest, case / "tsdf.ply", voxel, 100.0))
    results["poisson"] = (case / "poisson.ply", *run_worker("poisson", manifest, case / "poisson.ply", 9))
    spec = json.loads(manifest.read_text())
    focal = spec["depth_maps"][0]["intrinsics"]["fx"] * 2.0
    rows = []
    for method, (mesh, wall, cpu, peak) in results.items():
        row = {"scene": "interior", "method": method, "wall_s": wall, "cpu_s": cpu, "peak_mb": peak, "voxel": voxel,
               **evaluate(mesh, truth, extra), "pictures": []}
        for view in (6, 31):
            pose = case / f"pose-{view}.txt"
            pose.write_text(" ".join(map(str, spec["depth_maps"][view]["pose"]["camera_to_world"])))
            slug = "-".join(part for part in re.split(r"[^a-z0-9]+", method.lower()) if part)
            png = out_dir / f"interior-view{view}-{slug}.png"
            subprocess.run([str(BIN / "octstore"), "--quiet", "render", str(mesh), "-o", str(png), "--pose", str(pose),
                            "--focal", str(focal), "--width", "640", "--height", "480"], check=True, capture_output=True)
            row["pictures"].append(png.name)
        rows.append(row)
        print(json.dumps(rows[-1]), flush=True)
    return rows


def invented_area(mesh, frames, voxel):
    """The fraction of the mesh's area farther than 3 finest cubes from every input sample (the
    RedKitchen frames' pixels, every second one), from 200,000 area-uniform samples, drawn with a
    fixed seed so that the same mesh gives the same figure (unseeded, one mesh's figure moved by
    about a tenth between runs: 0.69 and 0.62 %)."""
    import numpy as np
    import open3d as o3d

    points = []
    for depth, intrinsic, pose in read_redkitchen(frames):
        h, w = depth.shape
        jj, ii = np.mgrid[0:h:2, 0:w:2]
        z = depth[jj, ii]
        keep = z > 0
        x = (ii[keep] - intrinsic[0, 2]) * z[keep] / intrinsic[0, 0]
        y = (jj[keep] - intrinsic[1, 2]) * z[keep] / intrinsic[1, 1]
        points.append((pose @ np.stack([x, y, z[keep], np.ones_like(x)]))[:3].T)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(points)))
    o3d.utility.random.seed(1)
    samples = o3d.io.read_triangle_mesh(str(mesh)).sample_points_uniformly(200000)
    distances = np.asarray(samples.compute_point_cloud_distance(cloud))
    return float((distances > 3 * voxel).mean())


def flat_normal_deviation(mesh, radius=0.06):
    """Ridges on a flat surface, as a number: the area-weighted mean angle (degrees) between the
    mesh's face normals and the plane fitted to frame 500's depth pixels on the kitchen's table
    top (rows 380-440, columns 250-400), over the faces within `radius` of the patch's centre
    and 2 cm of the plane. A smooth mesh of the (slightly uneven, noisily posed) table scores a
    few degrees; terraces or ridges one cube high score far more."""
    import numpy as np
    import open3d as o3d

    folder = SHARED / "7scenes-redkitchen"
    depth = np.asarray(o3d.io.read_image(str(folder / f"frame-{CLOSE_FRAME:06d}.depth.png"))).astype(np.float64) / 1000.0
    pose = np.loadtxt(folder / f"frame-{CLOSE_FRAME:06d}.pose.txt")
    rows, cols = np.mgrid[380:440:2, 250:400:2]
    z = depth[rows, cols]
    keep = (z > 0) & (z < 60)  # 65535 marks a missing depth
    k = np.loadtxt(folder / "camera-intrinsics.txt")
    camera = np.stack([(cols[keep] - k[0, 2]) * z[keep] / k[0, 0], (rows[keep] - k[1, 2]) * z[keep] / k[1, 1], z[keep],
                       np.ones(keep.sum())])
    points = (pose @ camera)[:3].T
    center = points.mean(0)
    normal = np.linalg.svd(points - center)[2][2]
    m = o3d.io.read_triangle_mesh(str(mesh))
    v, t = np.asarray(m.vertices), np.asarray(m.triangles)
    offsets = v[t].mean(1) - center
    along = offsets @ normal
    near = (np.linalg.norm(offsets - np.outer(along, normal), axis=1) < radius) & (np.abs(along) < 0.02)
    n = np.cross(v[t[near, 1]] - v[t[near, 0]], v[t[near, 2]] - v[t[near, 0]])
    area = np.linalg.norm(n, axis=1)
    angles = np.degrees(np.arccos(np.clip(np.abs(n @ normal) / np.maximum(area, 1e-30), 0, 1)))
    return float(np.average(angles, weights=area)) if area.sum() > 0 else None


# The groundtruth section's methods: octstore's three solvers (`octstore` is TGV, the
# default) and the peers. `--gt-methods` runs a subset; rows of the others stay.
GT_METHODS = ["octstore", "octstore-ssd", "octstore-hybrid", "tsdf", "poisson"]


def groundtruth(work, quick, noises=GT_NOISE, outlier_levels=GT_OUTLIERS, methods=GT_METHODS):
    rows = []
    meshes = {"bunny": GT_MESHES["bunny"]} if quick else GT_MESHES
    for name, truth in meshes.items():
        for noise in noises[:1] if quick else noises:
            for outliers in outlier_levels:
                case = work / f"{name}-{noise}-{outliers}"
                views = case / "views"
                subprocess.run(
                    [
                        str(BIN / "octstore-gt-render"),
                        str(truth),
                        "--out",
                        str(views),
                        "--views",
                        "24",
                        "--width",
                        "320",
                        "--height",
                        "240",
                        "--noise",
                        str(noise),
                        "--outliers",
                        str(outliers),
                    ],
                    check=True,
                    capture_output=True,
                )
                manifest = views / "scene.json"
                # One resolution for all: octstore's finest cubes at depth 9 of a root about
                # 1.2 x the scene; TSDF voxels of the same size; Poisson at octree depth 9.
                results = {}
                voxel = None
                for method in [m for m in methods if m.startswith("octstore")]:
                    solver = method.removeprefix("octstore").removeprefix("-") or "tgv"
                    mesh = case / f"{method}.ply"
                    store = case / f"store-{solver}"
                    # SSD and hybrid read the samples' sums, which ingest gathers on request.
                    sums = [] if solver == "tgv" else ["--sample-sums"]
                    wall, cpu, peak, _ = octstore(store, manifest, ["--max-depth", "9", *sums],
                                                  ["--iterations", "100", "--method", solver], mesh)
                    results[method] = (mesh, wall, cpu, peak)
                    info = json.loads(subprocess.run(
                        [str(BIN / "octstore"), "info", str(store), "--json"], check=True, capture_output=True, text=True
                    ).stdout)
                    voxel = info["finest_cube_side"]
                if "tsdf" in methods:
                    if voxel is None:
                        raise SystemExit("tsdf runs at octstore's finest cube size: include an octstore method")
                    mesh = case / "tsdf.ply"
                    results["tsdf"] = (mesh, *run_worker("tsdf", manifest, mesh, voxel, 100.0))
                if "poisson" in methods:
                    mesh = case / "poisson.ply"
                    results["poisson"] = (mesh, *run_worker("poisson", manifest, mesh, 9))
                for method, (mesh, wall, cpu, peak) in results.items():
                    metrics = evaluate(mesh, truth)
                    rows.append(
                        {
                            "mesh": name,
                            "noise": noise,
                            "outliers": outliers,
                            "method": method,
                            "wall_s": wall,
                            "cpu_s": cpu,
                            "peak_mb": peak,
                            **metrics,
                        }
                    )
                    print(json.dumps(rows[-1]), flush=True)
    return rows


# The camera all RedKitchen pictures are taken from: frame 0's pose, pulled 1 m back along its
# viewing axis so that more of the kitchen is in view (7-Scenes poses are camera-to-world,
# OpenCV axes; the depth camera's focal length is 585 px).
PICTURE_FRAME = 0
PICTURE_PULLBACK_M = 1.0


def picture_pose(out_dir):
    import numpy as np

    pose = np.loadtxt(SHARED / "7scenes-redkitchen" / f"frame-{PICTURE_FRAME:06d}.pose.txt")
    pose[:3, 3] -= PICTURE_PULLBACK_M * pose[:3, 2]
    path = out_dir / "redkitchen-picture.pose.txt"
    np.savetxt(path, pose)
    return path


def picture(mesh, pose, png, focal=585):
    subprocess.run(
        [str(BIN / "octstore"), "--quiet", "render", str(mesh), "-o", str(png), "--pose", str(pose),
         "--focal", str(focal), "--width", "640", "--height", "480"],
        check=True,
        capture_output=True,
    )


# Frame 500 looks down at the kitchen's table top, a flat surface seen at the finest cubes:
# terraces show there first. The close view is the same camera with 3 times the focal length.
CLOSE_FRAME = 500


def table_pose(out_dir):
    """Frame 500's camera turned down (about its x axis) to look at pixel row 410, the middle of
    the table-top patch `flat_normal_deviation` measures: a close view of the table itself."""
    import numpy as np

    pose = np.loadtxt(SHARED / "7scenes-redkitchen" / f"frame-{CLOSE_FRAME:06d}.pose.txt")
    angle = np.arctan2(410 - 240, 585)
    c, s = np.cos(angle), np.sin(angle)
    turn = np.array([[1, 0, 0, 0], [0, c, s, 0], [0, -s, c, 0], [0, 0, 0, 1]])
    path = out_dir / "redkitchen-table.pose.txt"
    np.savetxt(path, pose @ turn)
    return path


def close_pictures(mesh, prefix, out_dir):
    pose = SHARED / "7scenes-redkitchen" / f"frame-{CLOSE_FRAME:06d}.pose.txt"
    names = []
    for label, view, focal in (("frame500", pose, 585), ("frame500-close", pose, 1755),
                               ("table-close", table_pose(out_dir), 1755)):
        png = out_dir / f"{prefix}-{label}.png"
        picture(mesh, view, png, focal)
        names.append(png.name)
    return names


def redkitchen(work, frames_list, max_depth, out_dir, budget="512MiB", tsdf_voxel=None):
    """octstore and TSDF on evenly strided RedKitchen frames. `max_depth` (None: ingest's
    default, cubes sized by the sensor's noise) caps octstore's finest cube; TSDF uses
    `tsdf_voxel`, else the same voxel as octstore's finest cube."""
    rows = []
    pose = picture_pose(out_dir)
    depth_args = ["--max-depth", str(max_depth)] if max_depth else []
    tag = f"-d{max_depth}" if max_depth else ""
    for frames in frames_list:
        case = work / f"redkitchen-{frames}{tag}"
        case.mkdir(parents=True, exist_ok=True)
        mesh = case / "octstore.ply"
        stride = 1000 // frames
        wall, cpu, peak, stages = octstore(
            case / "store",
            SHARED / "7scenes-redkitchen",
            ["--stride", str(stride), "--limit", str(frames), *depth_args],
            [],
            mesh,
            budget=budget,
        )
        info = json.loads(subprocess.run(
            [str(BIN / "octstore"), "info", str(case / "store"), "--json"], check=True, capture_output=True, text=True
        ).stdout)
        voxel = tsdf_voxel or info["finest_cube_side"]
        png = out_dir / f"redkitchen-{frames}{tag}-octstore.png"
        picture(mesh, pose, png)
        rows.append({"frames": frames, "max_depth": max_depth, "method": "octstore", "wall_s": wall, "cpu_s": cpu, "peak_mb": peak,
                     "budget": budget, "voxel_m": info["finest_cube_side"], "mesh_mb": mesh.stat().st_size / 1e6, "cubes": info["cubes"],
                     "stages": stages, "picture": png.name, "invented_area": invented_area(mesh, frames, voxel),
                     "table_normal_deviation_deg": flat_normal_deviation(mesh),
                     "close_pictures": close_pictures(mesh, f"redkitchen-{frames}{tag}-octstore", out_dir)})
        print(json.dumps(rows[-1]), flush=True)
        tsdf_mesh = case / "tsdf.ply"
        try:
            wall, cpu, peak = run_worker("tsdf", frames, tsdf_mesh, voxel, 4.0)
        except subprocess.CalledProcessError as error:
            # Recorded, not hidden: at octstore's finest cube size Open3D can run out of blocks.
            rows.append({"frames": frames, "max_depth": max_depth, "method": "tsdf", "voxel_m": voxel,
                         "error": f"worker failed: {error}"})
            print(json.dumps(rows[-1]), flush=True)
            continue
        png = out_dir / f"redkitchen-{frames}{tag}-tsdf.png"
        picture(tsdf_mesh, pose, png)
        rows.append({"frames": frames, "max_depth": max_depth, "method": "tsdf", "wall_s": wall, "cpu_s": cpu, "peak_mb": peak,
                     "voxel_m": voxel, "mesh_mb": tsdf_mesh.stat().st_size / 1e6, "picture": png.name,
                     "invented_area": invented_area(tsdf_mesh, frames, voxel),
                     "table_normal_deviation_deg": flat_normal_deviation(tsdf_mesh),
                     "close_pictures": close_pictures(tsdf_mesh, f"redkitchen-{frames}{tag}-tsdf", out_dir)})
        print(json.dumps(rows[-1]), flush=True)
    return rows


# Cube-size rules of RGB-D frames (docs/parameters.md, "Cube sizes and depth noise"): the footprint capped at --max-depth 10
# (the rule before noise models), k sigma of the Kinect table for three k, and the default,
# the noise measured from each frame.
CUBE_SIZE_RULES = (
    ("footprint, `--max-depth 10`", ["--depth-noise", "none", "--max-depth", "10"]),
    ("Kinect table, k = 0.5", ["--depth-noise", "kinect", "--noise-sigmas", "0.5"]),
    ("Kinect table, k = 1", ["--depth-noise", "kinect"]),
    ("Kinect table, k = 2", ["--depth-noise", "kinect", "--noise-sigmas", "2"]),
    ("measured (`auto`, the default)", []),
)


def cube_sizes(work, frames, budget):
    """octstore alone on evenly strided RedKitchen frames under each rule of CUBE_SIZE_RULES:
    time, cubes, finest cube, invented area farther than 15 mm and 3 cm, the table's normal
    deviation."""
    rows = []
    for index, (rule, args) in enumerate(CUBE_SIZE_RULES):
        case = work / f"cube-sizes-{frames}-{index}"
        case.mkdir(parents=True, exist_ok=True)
        mesh = case / "octstore.ply"
        wall, cpu, peak, _ = octstore(
            case / "store", SHARED / "7scenes-redkitchen",
            ["--stride", str(1000 // frames), "--limit", str(frames), *args], [], mesh, budget=budget)
        info = json.loads(subprocess.run(
            [str(BIN / "octstore"), "info", str(case / "store"), "--json"], check=True, capture_output=True, text=True
        ).stdout)
        rows.append({"frames": frames, "rule": rule, "args": args, "wall_s": wall, "cpu_s": cpu, "peak_mb": peak,
                     "budget": budget, "cubes": info["cubes"], "finest_m": info["finest_cube_side"],
                     "invented_area": invented_area(mesh, frames, 0.005),
                     "invented_area_3cm": invented_area(mesh, frames, 0.01),
                     "table_normal_deviation_deg": flat_normal_deviation(mesh)})
        print(json.dumps(rows[-1]), flush=True)
    # The same frames in the TUM RGB-D layout (tools/tum-layout.py: depth at 5000 units per metre,
    # quaternion poses), ingested with one command at the default rule.
    case = work / f"cube-sizes-{frames}-tum"
    sequence = case / "sequence"
    subprocess.run([sys.executable, str(ROOT / "tools" / "tum-layout.py"), str(SHARED / "7scenes-redkitchen"),
                    str(sequence), "--stride", str(1000 // frames), "--limit", str(frames)], check=True)
    mesh = case / "octstore.ply"
    args = ["--intrinsics", str(sequence / "intrinsics.txt")]
    wall, cpu, peak, _ = octstore(case / "store", sequence, args, [], mesh, budget=budget)
    info = json.loads(subprocess.run(
        [str(BIN / "octstore"), "info", str(case / "store"), "--json"], check=True, capture_output=True, text=True
    ).stdout)
    rows.append({"frames": frames, "rule": "measured, TUM-layout copy", "args": ["--intrinsics", "intrinsics.txt"],
                 "wall_s": wall, "cpu_s": cpu, "peak_mb": peak, "budget": budget, "cubes": info["cubes"],
                 "finest_m": info["finest_cube_side"], "invented_area": invented_area(mesh, frames, 0.005),
                 "invented_area_3cm": invented_area(mesh, frames, 0.01),
                 "table_normal_deviation_deg": flat_normal_deviation(mesh)})
    print(json.dumps(rows[-1]), flush=True)
    return rows


# ---------------------------------------------------------------------------------------------
# Scale: a synthetic city of boxes, seen from above by 8 cameras per block

CITY_BLOCK_M = 20.0
CITY_VIEW = (320, 240, 60.0)  # width, height, horizontal field of view in degrees


def city(n, seed=1):
    """Boxes (min, max) of an n x n city: per block 2 x 2 buildings of random footprint and
    height, streets between blocks, and the ground (a thin slab under the whole city)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    boxes = []
    for bx in range(n):
        for by in range(n):
            x0, y0 = bx * CITY_BLOCK_M, by * CITY_BLOCK_M
            for ix in range(2):
                for iy in range(2):
                    lo_x = x0 + 2.0 + ix * 8.0 + rng.uniform(0.0, 1.5)
                    lo_y = y0 + 2.0 + iy * 8.0 + rng.uniform(0.0, 1.5)
                    size_x, size_y = rng.uniform(4.0, 6.5, size=2)
                    height = rng.uniform(4.0, 25.0)
                    boxes.append(((lo_x, lo_y, 0.0), (lo_x + size_x, lo_y + size_y, height)))
    extent = n * CITY_BLOCK_M
    boxes.append(((-5.0, -5.0, -1.0), (extent + 5.0, extent + 5.0, 0.0)))
    return np.array(boxes, dtype=np.float64)


def look_at(eye, target):
    """Camera-to-world with OpenCV axes (x right, y down, z forward), world z up."""
    import numpy as np

    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
    return pose


def cast(boxes, origin, directions):
    """Distance along each (unit) direction to the nearest box, inf where none is hit."""
    import numpy as np

    nearest = np.full(len(directions), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = 1.0 / directions
    for lo, hi in boxes:
        t1 = (lo - origin) * inverse
        t2 = (hi - origin) * inverse
        near = np.nanmax(np.minimum(t1, t2), axis=1)
        far = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (far >= np.maximum(near, 0.0)) & (near > 0.0)
        nearest = np.where(hit & (near < nearest), near, nearest)
    return nearest


def cast_view(boxes, pose, focal, width, height, directions):
    """`cast` for one pinhole view (pixel (i, j) looks through u = i, v = j, centre at half the
    size), testing each box only on the pixels its projected corners span. Gives exactly
    `cast`'s distances: each pixel's arithmetic is the same, boxes out of its span miss it."""
    import numpy as np

    eye, rotation = pose[:3, 3], pose[:3, :3]
    nearest = np.full((height, width), np.inf)
    grid = directions.reshape(height, width, 3)
    for lo, hi in boxes:
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        local = (corners - eye) @ rotation
        if np.all(local[:, 2] > 1e-9):
            u = focal * local[:, 0] / local[:, 2] + width / 2.0
            v = focal * local[:, 1] / local[:, 2] + height / 2.0
            i0, i1 = max(int(np.floor(u.min())) - 1, 0), min(int(np.ceil(u.max())) + 2, width)
            j0, j1 = max(int(np.floor(v.min())) - 1, 0), min(int(np.ceil(v.max())) + 2, height)
        elif np.all(local[:, 2] <= 0.0):
            continue
        else:
            i0, i1, j0, j1 = 0, width, 0, height
        if i0 >= i1 or j0 >= j1:
            continue
        window = grid[j0:j1, i0:i1].reshape(-1, 3)
        t = cast(np.array([[lo, hi]]), eye, window).reshape(j1 - j0, i1 - i0)
        nearest[j0:j1, i0:i1] = np.minimum(nearest[j0:j1, i0:i1], t)
    return nearest.reshape(-1)


def write_city(n, folder):
    """Renders the n x n city into PFM depth maps plus an octstore manifest; returns the
    manifest and the number of depth maps."""
    import numpy as np

    folder.mkdir(parents=True, exist_ok=True)
    boxes = city(n)
    width, height, fov = CITY_VIEW
    focal = width / 2.0 / np.tan(np.radians(fov) / 2.0)
    jj, ii = np.mgrid[0:height, 0:width]
    local = np.stack([(ii - width / 2.0) / focal, (jj - height / 2.0) / focal, np.ones_like(ii, float)], -1)
    local = local.reshape(-1, 3)
    entries = []
    for bx in range(n):
        for by in range(n):
            center = np.array([(bx + 0.5) * CITY_BLOCK_M, (by + 0.5) * CITY_BLOCK_M, 8.0])
            for k in range(8):
                angle = 2.0 * np.pi * (k + 0.5 * (bx + by) % 2) / 8.0
                radius = 18.0 if k % 2 == 0 else 10.0
                eye = center + np.array([radius * np.cos(angle), radius * np.sin(angle), 40.0 + 4.0 * (k % 3)])
                pose = look_at(eye, center)
                directions = local @ pose[:3, :3].T
                lengths = np.linalg.norm(directions, axis=1)
                # Only boxes near the block can be in view: the views look steeply down.
                reach = np.all((boxes[:, 0, :2] < center[:2] + 70.0) & (boxes[:, 1, :2] > center[:2] - 70.0), axis=1)
                t = cast_view(boxes[reach], pose, focal, width, height, directions / lengths[:, None])
                depth = (t / lengths).reshape(height, width).astype(np.float32)
                depth[~np.isfinite(depth)] = np.nan
                name = f"view-{len(entries):05d}.pfm"
                with open(folder / name, "wb") as f:
                    f.write(f"Pf\n{width} {height}\n-1.0\n".encode())
                    f.write(np.flipud(depth).astype("<f4").tobytes())
                entries.append({
                    "image": name,
                    "width": width,
                    "height": height,
                    "kind": "photo",
                    "intrinsics": {"fx": focal, "fy": focal, "cx": width / 2.0, "cy": height / 2.0},
                    "pose": {"camera_to_world": pose.reshape(-1).tolist(), "axes": "opencv"},
                })
    manifest = folder / "scene.json"
    manifest.write_text(json.dumps({"depth_maps": entries}))
    return manifest, len(entries)


def scale(work, sizes, budget):
    rows = []
    for n in sizes:
        case = work / f"city-{n}"
        manifest, maps = write_city(n, case / "views")
        mesh = case / "city.ply"
        with DiskPeak(case) as disk:
            wall, cpu, peak, stages = octstore(case / "store", manifest, ["--max-depth", "20"], [], mesh, budget=budget)
        info = json.loads(subprocess.run(
            [str(BIN / "octstore"), "info", str(case / "store"), "--json"], check=True, capture_output=True, text=True
        ).stdout)
        levels = [v for k, v in stages.items() if k.startswith("solution-")]
        rows.append({"blocks": n * n, "depth_maps": maps, "samples": maps * CITY_VIEW[0] * CITY_VIEW[1],
                     "cut_cubes": sum(v.get("cubes", 0) for v in levels),
                     "cube_iterations": sum(v.get("cubes", 0) * v.get("iterations", 0) for v in levels),
                     "solve_s": sum(v["seconds"] for v in levels),
                     "cubes": info["cubes"], "cube_data_mb": info["cubes"] * CUBE_BYTES / 1e6, "budget": budget,
                     "wall_s": wall, "cpu_s": cpu, "peak_mb": peak, "stages": stages,
                     "solve_peak_mb": max(v["peak_mb"] for k, v in stages.items() if "peak_mb" in v and k != "extract"),
                     "extract_peak_mb": stages.get("extract", {}).get("peak_mb", 0.0),
                     "disk_peak_gb": disk.peak_bytes / 1e9, "store_gb": tree_bytes(case / "store") / 1e9,
                     "views_gb": tree_bytes(case / "views") / 1e9, "triangles": mesh_triangles(mesh)})
        print(json.dumps(rows[-1]), flush=True)
        shutil.rmtree(case)
    return rows


# Bytes of one cube's data in the solve: key (16), r_c sum and count (12), 8 histogram bins (32),
# u, v (3), p (3), q (6) as f32 (52).
CUBE_BYTES = 16 + 12 + 32 + 52


def parse_budget(text):
    units = {"KiB": 1 << 10, "MiB": 1 << 20, "GiB": 1 << 30}
    for suffix, factor in units.items():
        if text.endswith(suffix):
            return float(text[: -len(suffix)]) * factor
    return float(text)


def figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def groundtruth_plots(rows, out_dir):
    plt = figure()
    written = []
    for name in sorted({r["mesh"] for r in rows}):
        for noise in sorted({r["noise"] for r in rows if r["mesh"] == name}):
            fig, axis = plt.subplots(figsize=(5, 3.5))
            for method in GT_METHODS:
                points = sorted(
                    (r["outliers"], r["f_score"]) for r in rows if (r["mesh"], r["noise"], r["method"]) == (name, noise, method)
                )
                if points:
                    axis.plot([100 * p[0] for p in points], [p[1] for p in points], marker="o", label=method)
            axis.set_xlabel("outlier pixels (%)")
            axis.set_ylabel("F-score (tau = 1 % of the diagonal)")
            axis.set_ylim(0, 1.02)
            axis.set_title(f"{name}, depth noise {100 * noise:g} %")
            axis.legend()
            fig.tight_layout()
            path = out_dir / f"fscore-{name}-{noise}.png"
            fig.savefig(path, dpi=110)
            plt.close(fig)
            written.append(path)
    return written


def scale_plot(rows, out_dir, name="scale.png"):
    plt = figure()
    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.5))
    samples = [r["samples"] / 1e6 for r in rows]
    left.plot(samples, [r["solve_peak_mb"] for r in rows], marker="o", label="ingest + solve")
    left.plot(samples, [r["extract_peak_mb"] for r in rows], marker="o", label="extract")
    left.axhline(parse_budget(rows[0]["budget"]) / 1e6, color="grey", linestyle="--", label=f"--memory-budget {rows[0]['budget']}")
    left.set_xlabel("input samples (millions)")
    left.set_ylabel("peak RSS (MB)")
    left.set_ylim(bottom=0)
    left.legend()
    right.plot(samples, [r["wall_s"] for r in rows], marker="o", label="wall")
    right.plot(samples, [r["cpu_s"] for r in rows], marker="o", label="CPU")
    right.set_xlabel("input samples (millions)")
    right.set_ylabel("seconds")
    right.set_ylim(bottom=0)
    right.legend()
    fig.tight_layout()
    path = out_dir / name
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def stage_breakdown(stages):
    """Table-1 rows (name, seconds, peak RSS in MB or None) from octstore's per-stage summary
    lines. The octree's parts share the octree stage's peak; the levels' peak is the largest."""
    parts = stages.get("octree-parts", {})
    levels = [v for k, v in stages.items() if k.startswith("solution-")]
    solve = sum(v["seconds"] for v in levels)
    peak = lambda name: stages.get(name, {}).get("peak_mb")
    rows = [("Depth maps to sorted runs (ingest)", stages.get("ingest", {}).get("seconds", 0.0), peak("ingest"))]
    if parts:
        rows += [
            ("Linear octree: k-way merge of the runs", parts["merge"], peak("octree")),
            ("Balance octree", parts["balance"], peak("octree")),
            ("Complete octree (nodes)", parts["nodes"], peak("octree")),
            ("Index treetop", parts["treetop"], peak("octree")),
        ]
    else:
        rows.append(("Octree + treetop", stages.get("octree", {}).get("seconds", 0.0), peak("octree")))
    rows += [
        ("Histograms (CPU)", stages.get("histograms", {}).get("seconds", 0.0), peak("histograms")),
        ("Primal-dual method, all levels (CPU)", solve, max((v["peak_mb"] for v in levels), default=None)),
        ("Marching cubes (extract)", stages.get("extract", {}).get("seconds", 0.0), peak("extract")),
    ]
    return rows


def table_one(stages, run, row, heading):
    """Markdown lines: the stage breakdown of one run in the paper's Table 1 format, with each
    stage's peak RSS (a process's high-water mark: ingest, solve and extract are one process
    each, so a stage's peak is the most its process held by the time it ended)."""
    breakdown = stage_breakdown(stages)
    total = sum(seconds for _, seconds, _ in breakdown) or 1.0
    lines = ["", f"{heading} Stage breakdown of the largest run, {run} (the paper's Table 1 format)", "",
             f"{row['cubes']:,} cubes; {row['wall_s'] / 60:.1f} min in all on this machine, peak RSS "
             f"{row['peak_mb']:.0f} MB. A stage's peak RSS is its process's high-water mark when it ended (ingest, "
             "solve and extract run as one process each, so a solve stage's figure includes the stages before it).",
             "", "| processing stage | time | time in % | peak RSS MB |", "|---|---|---|---|"]
    for name, seconds, peak in breakdown:
        lines.append(f"| {name} | {seconds:.1f} s | {100 * seconds / total:.0f} % | {'-' if peak is None else f'{peak:.0f}'} |")
    return lines + [""]


def machine():
    model = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return f"{os.cpu_count()} cores ({model}), {memory:.0f} GiB RAM"


def commit():
    out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    return out.stdout.strip() or "unknown"


def commits(rows):
    return ", ".join(sorted({r.get("commit", "unknown") for r in rows}))


def fmt(row, key, digits=3, spec=None):
    """A figure older runs did not record shows as a dash; `spec` replaces the fixed-point
    format of `digits` (`","` for a count)."""
    return format(row[key], spec or f".{digits}f") if key in row else "-"


def write_markdown(results, out_dir, path):
    gt_rows, rk_rows, scale_rows = results["groundtruth"], results["redkitchen"], results["scale"]
    lines = ["# Benchmarks", "",
             "Written by `tools/bench/run.sh` (see docs/quality.md); raw figures in `benchmarks/results-*.json`. "
             f"Machine: {machine()}. Generated {time.strftime('%Y-%m-%d')}.", ""]
    object_rows = results.get("objects", [])
    if object_rows:
        lines += ["## Objects seen from all around in empty space, no flags", "",
                  "The bunny and the dragon rendered by `octstore-gt-render --room 0` (no room, no ground: the "
                  "background pixels are 0) from 60 views of 320x240 on a sphere, at two scales: 0.3 m seen from "
                  "0.6 m (PFM files and a manifest, metres) and 3 units seen from 4 to 8 units (a 7-Scenes folder, "
                  "16-bit PNG in thousandths of a unit); clean, and with 0.5 % depth noise plus 10 % outlier pixels. "
                  "octstore: `ingest`, `solve`, `extract` with no flags at all (the maps see the object against "
                  "empty background, so `solve` fits smooth signed distance and the mesh is watertight); second "
                  "rows: the same with `solve --method tgv` (the paper's solver, a scene's default) or `hybrid` and "
                  "no other flag, and with `extract --open` (the observed surface alone). TSDF: Open3D's VoxelBlockGrid at the "
                  "best of voxels 0.25, 0.5, 1 % of the diagonal and truncations 4 and 8 voxels by F at 1 %. "
                  "Poisson: Open3D's screened Poisson at depth 9 after statistical outlier removal (20 neighbours, "
                  "2 deviations), the 2 % least dense vertices trimmed. Measured uncropped (`tools/bench/run.sh "
                  f"--sections objects`, octstore commit {commits(object_rows)}).", "",
                  "| mesh | scale | noise / outliers | method | F@1 % | F@0.5 % | F@0.2 % | normal consistency | "
                  "Chamfer | components | boundary edges | wall s |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in object_rows:
            chosen = f" ({r['voxel'] * 100:g} %, {r['truncation']:g} voxels)" if "voxel" in r else ""
            lines.append(
                f"| {r['mesh']} | {r['scale']} | {100 * r['noise']:g} % / {100 * r['outliers']:g} % | "
                f"{r['method']}{chosen} | {r['f_score']:.4f} | {fmt(r, 'f_score_0.005', 4)} | "
                f"{fmt(r, 'f_score_0.002', 4)} | {r['normal_consistency']:.3f} | {r['chamfer']:.5f} | "
                f"{r['components']} | {r['boundary_edges']} | {r['wall_s']:.1f} |")
        lines += [""]
        pictures = [r for r in object_rows if "picture" in r]
        if pictures:
            lines += ["octstore's meshes, no flags (clean, then noisy; 0.3 m, then 3 units):", ""]
            lines += [f"![{r['mesh']} {r['scale']} noise {r['noise']}](benchmarks/{r['picture']})" for r in pictures]
            lines += [""]
    unit_rows = results.get("units", [])
    if unit_rows:
        # How far the triangle counts of one object's meshes in the three units spread.
        spread = 0.0
        for key in {(r["mesh"], r["noise"]) for r in unit_rows}:
            counts = [r["triangles"] for r in unit_rows if (r["mesh"], r["noise"]) == key]
            spread = max(spread, max(counts) / min(counts) - 1.0)
        lines += ["### The same objects in other units, no flags", "",
                  "The 0.3 m objects at 0.6 m of the table above, their depths and poses multiplied by 10 and by "
                  "1000 (PFM files and a manifest), each mesh scaled back to metres: F at 0.2 % of the diagonal "
                  "against the mesh made in metres (1.0000: every sample of each within 0.2 % of the diagonal of the "
                  "other; the meshes are not identical: their triangle counts differ by up to "
                  f"{100 * spread:.1f} %), and F at 1 % and 0.2 % against the ground truth (`tools/bench/run.sh --sections units`, octstore commit "
                  f"{commits(unit_rows)}).", "",
                  "| mesh | noise / outliers | units | F@0.2 % against metres | F@1 % (truth) | F@0.2 % (truth) | "
                  "triangles | components | boundary edges | wall s |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for r in unit_rows:
            lines.append(
                f"| {r['mesh']} | {100 * r['noise']:g} % / {100 * r['outliers']:g} % | {r['units']} | "
                f"{r['f_score_0.002_vs_metres']:.4f} | {r['truth_f_score']:.4f} | {r['truth_f_score_0.002']:.4f} | "
                f"{r['triangles']:,} | {r['components']} | {r['boundary_edges']} | {r['wall_s']:.1f} |")
        lines += [""]
    interior_rows = results.get("interior", [])
    if interior_rows:
        lines += ["## Interior: a furnished room seen from inside", "",
                  "`octstore-gt-render --layout interior` renders 60 views of 320x240 (70 degrees) from a camera "
                  "walking a 0.67 m circle in a 6 x 5 x 3 m room with a table on thin legs, a cabinet 10 cm from a "
                  "wall, a sofa, a 2 cm plate and a sphere; depth noise 0.2 %. Nothing behind the walls is ever "
                  "observed. octstore with no flags, and with `--max-depth 9` (1.4 cm cubes); TSDF at that voxel, "
                  "truncation 4 voxels; Poisson depth 9 as above. Measured over the whole ground truth, uncropped, "
                  "with completeness, recall and the ground truth's half of normal consistency over the faces some "
                  f"camera saw (`--gt-faces`). tau = 1 % of the diagonal (8.4 cm). octstore commit {commits(interior_rows)}.", "",
                  "| method | precision | recall | F@1 % | F@0.5 % | F@0.2 % | accuracy | completeness | Chamfer | normal consistency | boundary edges | wall s | peak MB |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in interior_rows:
            lines.append(f"| {r['method']} | {r['precision']:.3f} | {r['recall']:.3f} | {r['f_score']:.3f} | "
                         f"{fmt(r, 'f_score_0.005')} | {fmt(r, 'f_score_0.002')} | {r['accuracy']:.4f} | "
                         f"{r['completeness']:.4f} | {r['chamfer']:.4f} | {fmt(r, 'normal_consistency')} | {r['boundary_edges']:,} | "
                         f"{r['wall_s']:.1f} | {r['peak_mb']:.0f} |")
        lines += ["", "| view | " + " | ".join(r["method"] for r in interior_rows) + " |",
                  "|---|" + "---|" * len(interior_rows)]
        for index, view in enumerate((6, 31)):
            cells = [f"![{r['method']}]({(out_dir / r['pictures'][index]).relative_to(path.parent)})" for r in interior_rows]
            lines.append(f"| {view} | " + " | ".join(cells) + " |")
        lines.append("")
    if gt_rows:
        lines += ["## Ground truth: bunny and dragon", "",
                  "`octstore-gt-render` renders 24 views of 320x240 around each mesh inside a room (so every ray "
                  "ends on a surface), with Gaussian depth noise (a fraction of the depth) and outlier pixels (a "
                  "random depth between 0.2 and 2 times the true one). All three methods read the same depth maps. "
                  "octstore: `--max-depth 9`, 100 iterations per level (TGV); octstore-ssd and octstore-hybrid: "
                  "`ingest --sample-sums`, `solve --method ssd|hybrid`, the default SSD settings (ssd and hybrid rows measured "
                  "at a later commit than the others: the smoothness that follows the measured noise). TSDF: Open3D "
                  "VoxelBlockGrid at octstore's "
                  "finest cube size, truncation 4 voxels. Poisson: Open3D screened Poisson, depth 9, on the "
                  "back-projected pixels (every second one) with normals oriented to their camera, lowest 2 % "
                  "density trimmed. `octstore-evaluate` measures each mesh against the ground truth: tau = 1 % of "
                  "the diagonal, reconstruction cropped to the ground truth's box grown by 5 %; accuracy, "
                  "completeness and Chamfer are mean distances in the mesh's units; boundary edges (holes) are "
                  f"counted on the whole mesh. octstore commit {commits(gt_rows)}.", "",
                  "| mesh | depth noise | outliers | method | precision | recall | F@1 % | F@0.5 % | F@0.2 % | accuracy | completeness | Chamfer | normal consistency | boundary edges | wall s | CPU s | peak MB |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in gt_rows:
            lines.append(
                f"| {r['mesh']} | {100 * r['noise']:g} % | {100 * r['outliers']:g} % | {r['method']} | {r['precision']:.3f} | "
                f"{r['recall']:.3f} | {r['f_score']:.3f} | {fmt(r, 'f_score_0.005')} | {fmt(r, 'f_score_0.002')} | "
                f"{r['accuracy']:.5f} | {r['completeness']:.5f} | {r['chamfer']:.5f} | {fmt(r, 'normal_consistency')} | "
                f"{r['boundary_edges']:,} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['peak_mb']:.0f} |"
            )
        images = groundtruth_plots(gt_rows, out_dir)
        lines += [""] + [f"![{p.stem}]({p.relative_to(path.parent)})" for p in images] + [""]
    if rk_rows:
        lines += ["## RedKitchen (7-Scenes), real RGB-D frames", "",
                  "Evenly strided subsets of the 1000 frames. octstore runs ingest, solve (at most 200 iterations "
                  "per level, stopping at `--tolerance`) and extract with the `--memory-budget` given; TSDF (Open3D VoxelBlockGrid, CPU) integrates the same "
                  "frames, truncation 4 voxels, depth cut at 4 m, at octstore's finest cube size where `--max-depth` "
                  "caps it (10: 5.7 mm) and at 5 mm for octstore's default (`tools/bench/run.sh --sections redkitchen "
                  "--redkitchen-max-depth 0 --tsdf-voxel 0.005`), whose cubes follow the sensor's noise (docs/parameters.md, "
                  "\"Cube sizes and depth noise\": 2.9 mm near the camera, coarser farther away). Peak is each "
                  f"process's own peak RSS; for octstore the largest over its three commands. octstore commit "
                  f"{commits(rk_rows)}.", "",
                  "The last column is octstore's wall time over TSDF's on the same frames, measured one after "
                  "the other in the same run.", "",
                  "| frames | `--max-depth` | method | voxel (m) | cubes | budget | wall s | CPU s | peak MB | mesh MB | wall / TSDF's |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in rk_rows:
            depth = r.get("max_depth") or "default"
            if "error" in r:
                lines.append(f"| {r['frames']} | {depth} | {r['method']} | {r['voxel_m']:.4f} | - | | {r['error']} | | | | |")
                continue
            cubes = f"{r['cubes']:,}" if "cubes" in r else "-"
            tsdf_row = next((t for t in rk_rows if t["method"] == "tsdf" and "wall_s" in t
                             and (t["frames"], t.get("max_depth")) == (r["frames"], r.get("max_depth"))), None)
            ratio = f"{r['wall_s'] / tsdf_row['wall_s']:.2f}" if tsdf_row else "-"
            lines.append(f"| {r['frames']} | {depth} | {r['method']} | {r['voxel_m']:.4f} | {cubes} | {r.get('budget', '-')} | "
                         f"{r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['peak_mb']:.0f} | {r['mesh_mb']:.1f} | {ratio} |")
        invented = [r for r in rk_rows if "invented_area" in r]
        if invented:
            lines += ["", "Invented area: the fraction of each mesh's area farther than 3 finest cubes from every input "
                      "sample (every second pixel of the frames), from 200,000 area-uniform samples. Table normal "
                      "deviation: the area-weighted mean angle between the faces on the table top (frame 500, 6 cm "
                      "around the patch its pixels rows 380-440, columns 250-400 see) and the plane fitted to those "
                      "pixels; ridges or terraces raise it.", "",
                      "| frames | `--max-depth` | method | invented area | table normal deviation |", "|---|---|---|---|---|"]
            for r in invented:
                deviation = r.get("table_normal_deviation_deg")
                deviation = f"{deviation:.1f} deg" if deviation is not None else "-"
                lines.append(f"| {r['frames']} | {r.get('max_depth') or 'default'} | {r['method']} | {100 * r['invented_area']:.2f} % | {deviation} |")
            lines += ["", f"Frame {CLOSE_FRAME}'s own camera; the same camera with 3 times the focal length (a close "
                      "view of the cabinet front and its handle); and that close camera turned down 16 degrees onto the "
                      "table top at the bottom of the frame, the surface the normal deviation measures, where terraces "
                      "and ridges show first:", "",
                      "| frames | method | frame 500 | close | table, close |", "|---|---|---|---|---|"]
            for r in invented:
                pictures = [f"![{r['method']}]({(out_dir / name).relative_to(path.parent)})" for name in r["close_pictures"]]
                pictures += ["-"] * (3 - len(pictures))
                lines.append(f"| {r['frames']} | {r['method']} | {pictures[0]} | {pictures[1]} | {pictures[2]} |")
        lines += ["", f"Pictures: the same camera for every mesh (frame {PICTURE_FRAME}'s pose pulled {PICTURE_PULLBACK_M:g} m "
                  "back, `octstore render --pose`).", "", "| frames | `--max-depth` | octstore | TSDF |", "|---|---|---|---|"]
        for frames, depth in sorted({(r["frames"], r.get("max_depth") or 99) for r in rk_rows}):
            cells = []
            for method in ("octstore", "tsdf"):
                row = next((r for r in rk_rows if (r["frames"], r.get("max_depth") or 99, r["method"]) == (frames, depth, method)), None)
                cells.append(f"![{method} {frames}]({(out_dir / row['picture']).relative_to(path.parent)})" if row and "picture" in row else "-")
            lines.append(f"| {frames} | {'default' if depth == 99 else depth} | {cells[0]} | {cells[1]} |")
        largest = max((r for r in rk_rows if r["method"] == "octstore" and r.get("stages")),
                      key=lambda r: (r["cubes"], r["frames"]), default=None)
        if largest:
            lines += table_one(largest["stages"], f"{largest['frames']} frames, `--max-depth` "
                               f"{largest.get('max_depth') or 'default'}", largest, "###")
        lines.append("")
    size_rows = results.get("cube-sizes", [])
    if size_rows:
        lines += ["## Cube sizes of RGB-D frames", "",
                  "`tools/bench/run.sh --sections cube-sizes --frames 100`: octstore alone on every 10th RedKitchen "
                  "frame under each cube-size rule (docs/parameters.md, \"Cube sizes and depth noise\"), `--memory-budget "
                  f"{size_rows[0]['budget']}`. Invented area: the mesh's area farther than 15 mm (3 cm) from every "
                  "input sample; table: the mean normal deviation on the table top. octstore commit "
                  f"{commits(size_rows)}.", "",
                  "| frames | rule | cubes | finest cube (mm) | wall s | CPU s | peak MB | invented > 15 mm | > 3 cm | table |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for r in size_rows:
            lines.append(f"| {r['frames']} | {r['rule']} | {r['cubes']:,} | {1000 * r['finest_m']:.1f} | {r['wall_s']:.1f} | "
                         f"{r['cpu_s']:.1f} | {r['peak_mb']:.0f} | {100 * r['invented_area']:.2f} % | "
                         f"{100 * r['invented_area_3cm']:.2f} % | {r['table_normal_deviation_deg']:.1f} deg |")
        lines.append("")
    budgets = sorted({r["budget"] for r in scale_rows}, key=parse_budget, reverse=True)
    for budget in budgets:
        rows = [r for r in scale_rows if r["budget"] == budget]
        peaks = [r["peak_mb"] for r in rows]
        per_sample = [r["wall_s"] / r["samples"] * 1e6 for r in rows]
        per_cube = [r["wall_s"] / r["cubes"] * 1e6 for r in rows]
        title = "## Scale: a synthetic city larger than the memory budget"
        lines += [title if budget == budgets[0] else f"### The same cities with `--memory-budget {budget}`", "",
                  f"A city of n x n blocks (20 m, 2 x 2 boxes each, random heights) on a ground slab, 8 views of "
                  f"{CITY_VIEW[0]}x{CITY_VIEW[1]} per block from 40-48 m up, rendered by `bench.py` itself. Each size "
                  f"runs ingest, solve and extract end to end with `--memory-budget {budget}` and `--max-depth 20` "
                  "(the sample radii set the resolution; cube sides snap to the root's side over a power of two, "
                  "and the root grows with the city, so cubes per sample vary a little between sizes). Cube data is "
                  f"cubes x {CUBE_BYTES} bytes (key, radius sums, 8 histogram bins, u, v, p, q). octstore commit "
                  f"{commits(rows)}.", "",
                  "Disk: the most the file system gained during the run (the store and ingest's scratch files), "
                  "and the store at the end; the depth maps (PFM) apart. A dash: not measured by that run.", "",
                  "| blocks | depth maps | samples | cubes | cube data MB | x budget | wall s | CPU s | peak MB, ingest + solve "
                  "| peak MB, extract | triangles | disk GB, peak | store GB | depth maps GB |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]

        for r in rows:
            ratio = r["cube_data_mb"] * 1e6 / parse_budget(r["budget"])
            lines.append(f"| {r['blocks']} | {r['depth_maps']} | {r['samples']:,} | {r['cubes']:,} | {r['cube_data_mb']:.0f} | "
                         f"{ratio:.1f} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['solve_peak_mb']:.0f} | {r['extract_peak_mb']:.0f} | "
                         f"{fmt(r, 'triangles', spec=',')} | {fmt(r, 'disk_peak_gb', 1)} | "
                         f"{fmt(r, 'store_gb', 1)} | {fmt(r, 'views_gb', 1)} |")
        solve_peaks = [r["solve_peak_mb"] for r in rows]
        lines += ["", f"Peak RSS of ingest and solve ranges from {min(solve_peaks):.0f} to {max(solve_peaks):.0f} MB across "
                  f"sizes; with extract, from {min(peaks):.0f} to {max(peaks):.0f} MB (the budget is "
                  f"{parse_budget(budget) / 1e6:.0f} MB). Wall time per million samples, smallest size to largest: "
                  f"{', '.join(f'{x:.1f}' for x in per_sample)} s ({per_sample[-1] / per_sample[0]:.2f} times the "
                  f"smallest's at the largest); per million cubes, {', '.join(f'{x:.1f}' for x in per_cube)} s."]
        runs = {r.get("commit", "unknown") for r in rows}
        if len(runs) > 1:
            lines[-1] += (f" The rows come from {len(runs)} runs (commits {commits(rows)}), on days when this machine's "
                          "speed may differ: compare times within one run.")
        worked = [r for r in rows if r.get("cube_iterations")]
        if worked:
            lines += ["", "The solve's work is the sum over levels of the cut's cubes times the iterations; "
                      "coarse leaves belong to every finer level's cut, so work per cube grows with the number of levels:", "",
                      "| blocks | cubes | levels | cut cubes, all levels | cut cubes per cube | solve s | million cube-iterations/s |",
                      "|---|---|---|---|---|---|---|"]
            for r in worked:
                levels = sum(1 for k in r["stages"] if k.startswith("solution-"))
                lines.append(f"| {r['blocks']} | {r['cubes']:,} | {levels} | {r['cut_cubes']:,} | "
                             f"{r['cut_cubes'] / r['cubes']:.2f} | {r['solve_s']:.0f} | "
                             f"{r['cube_iterations'] / max(r['solve_s'], 1e-9) / 1e6:.1f} |")
        seams = [r for r in rows if "extract-seams" in r.get("stages", {})]
        if seams:
            lines += ["", "Extraction streams the leaves and holds the vertices and triangles along the seams between "
                      "leaves meshed and leaves still to come, the most of them at once below (the held MB are its log's "
                      "own estimate of its tables). In key (Morton) order they grow with the city's area, not its side: "
                      "the root, a cube around the city, splits first across the city's height, so the lower half of "
                      "every building is meshed before any upper half.", "",
                      "| blocks | seam vertices open | seam edges open | held MB | of which the weld | peak MB, extract |",
                      "|---|---|---|---|---|---|"]
            for r in seams:
                seam = r["stages"]["extract-seams"]
                lines.append(f"| {r['blocks']} | {seam['vertices']:,} | {seam['edges']:,} | {seam['held_mb']} | "
                             f"{fmt(seam, 'weld_mb', 0)} | {r['extract_peak_mb']:.0f} |")
        name = "scale.png" if budget == budgets[0] else f"scale-{budget}.png"
        lines += ["", f"![scale]({scale_plot(rows, out_dir, name).relative_to(path.parent)})", ""]
        largest = max((r for r in rows if r.get("stages")), key=lambda r: r["cubes"], default=None)
        if largest:
            lines += table_one(largest["stages"], f"{largest['blocks']} blocks, `--memory-budget {budget}`",
                               largest, "####" if budget != budgets[0] else "###")
    import divide_bench

    lines += divide_bench.markdown(results.get("divide", []))
    import simplify_bench

    lines += simplify_bench.markdown(results.get("simplify", []), commits)
    path.write_text("\n".join(lines))


def main():
    if len(sys.argv) > 1 and sys.argv[1] == "worker":
        return worker(sys.argv[2:])
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sections", nargs="*",
                        default=["objects", "units", "groundtruth", "interior", "redkitchen", "scale", "cube-sizes", "simplify"],
                        help="sections to run; none (a bare --sections) only rewrites BENCHMARKS.md")
    parser.add_argument("--frames", nargs="+", type=int, default=[100, 300, 1000])
    parser.add_argument("--redkitchen-max-depth", type=int, default=10,
                        help="octstore --max-depth of the RedKitchen runs; 10 gives 5.6 mm cubes, at which "
                             "Open3D's TSDF fits in memory; 0 keeps ingest's default (1.4 mm)")
    parser.add_argument("--quick", action="store_true", help="bunny only, one noise level")
    parser.add_argument("--gt-noise", nargs="+", type=float, default=GT_NOISE, help="depth noise levels of groundtruth")
    parser.add_argument("--gt-outliers", nargs="+", type=float, default=GT_OUTLIERS, help="outlier levels of groundtruth")
    parser.add_argument("--gt-methods", nargs="+", default=GT_METHODS, choices=GT_METHODS,
                        help="methods of groundtruth (octstore is TGV); rows of the others stay")
    parser.add_argument("--scale-budget", default="1GiB", help="--memory-budget of the scale section")
    parser.add_argument("--redkitchen-budget", default="512MiB", help="--memory-budget of the redkitchen section")
    parser.add_argument("--tsdf-voxel", type=float, default=None,
                        help="TSDF voxel (m) of the redkitchen section (default: octstore's finest cube side)")
    parser.add_argument("--scale-sizes", nargs="+", type=int, default=[4, 13, 26, 45],
                        help="city sizes (blocks per side, squared) of the scale section: 10 M, 104 M, 415 M and "
                             "1,244 M samples; the rows of other sizes stay")
    parser.add_argument("--divide-points", type=int, default=1_000_000_000,
                        help="points of the generated cloud of the divide section")
    parser.add_argument("--divide-budgets", nargs="+", default=["256MiB", "1GiB"],
                        help="--memory-budget values of the divide section")
    parser.add_argument("--divide-cases", nargs="+", default=["synthetic", "incremental", "bunny"],
                        choices=["synthetic", "incremental", "bunny"],
                        help="cases of the divide section to run; the others keep their rows")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks", help="plots and raw results")
    parser.add_argument("--markdown", type=Path, default=ROOT / "BENCHMARKS.md")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    # Each section keeps its own results file, so sections can be run (and re-run) separately
    # and BENCHMARKS.md always shows the latest run of every section.
    with tempfile.TemporaryDirectory() as scratch:
        work = Path(scratch)
        for section in args.sections:
            if section == "groundtruth":
                rows = groundtruth(work, args.quick, args.gt_noise, args.gt_outliers, args.gt_methods)
            elif section == "interior":
                rows = interior(work, args.out)
            elif section == "objects":
                rows = objects(work, args.out)
            elif section == "units":
                rows = object_units(work)
            elif section == "redkitchen":
                rows = redkitchen(work, args.frames, args.redkitchen_max_depth or None, args.out, args.redkitchen_budget,
                                  args.tsdf_voxel)
            elif section == "scale":
                rows = scale(work, args.scale_sizes, args.scale_budget)
            elif section == "cube-sizes":
                rows = [row for frames in args.frames for row in cube_sizes(work, frames, args.redkitchen_budget)]
            elif section == "simplify":
                import simplify_bench

                rows = simplify_bench.run(sys.modules[__name__], work, args.out)
            elif section == "divide":
                import divide_bench

                rows = []
                if "synthetic" in args.divide_cases:
                    rows += [divide_bench.synthetic(BIN, work, args.divide_points, budget, 10_000_000, run_measured)
                             for budget in args.divide_budgets]
                if "incremental" in args.divide_cases:
                    rows += [divide_bench.incremental(BIN, work, 10_000_000, max_points, region, run_measured)
                             for max_points, region in ((500_000, 1.0), (200_000, 1.0), (200_000, 0.2))]
                if "bunny" in args.divide_cases:
                    rows.append(divide_bench.bunny_merge(BIN, work, GT_MESHES["bunny"], octstore, evaluate,
                                                         read_manifest))
                for row in rows:
                    print(json.dumps(row), flush=True)
            else:
                raise SystemExit(f"unknown section {section}")
            for row in rows:
                row["commit"] = commit()
            path = args.out / f"results-{section}.json"
            if section == "divide" and path.exists():
                # Cases this run did not make stay, with the commit that measured them.
                made = {r["case"] for r in rows}
                rows = [r for r in json.loads(path.read_text()) if r["case"] not in made] + rows
                rows.sort(key=lambda r: r["case"] != "synthetic")
            if section == "scale" and path.exists():
                # Sweeps at other budgets and sizes this run did not make stay, so the largest
                # size can run on its own.
                made = {(r["budget"], r["blocks"]) for r in rows}
                rows = [r for r in json.loads(path.read_text()) if (r["budget"], r["blocks"]) not in made] + rows
                rows.sort(key=lambda r: (r["budget"], r["blocks"]))
            if section == "groundtruth" and path.exists():
                # Cases and methods this run did not make stay.
                made = {(r["mesh"], r["noise"], r["outliers"], r["method"]) for r in rows}
                rows = [r for r in json.loads(path.read_text())
                        if (r["mesh"], r["noise"], r["outliers"], r["method"]) not in made] + rows
                order = {m: i for i, m in enumerate(GT_METHODS)}
                rows.sort(key=lambda r: (r["mesh"], r["noise"], r["outliers"], order.get(r["method"], 99)))
            if section == "redkitchen" and path.exists():
                # Runs of other frame counts or cube sizes stay: the 1000-frame run can be made
                # on its own.
                depth = args.redkitchen_max_depth or None
                rows = [r for r in json.loads(path.read_text())
                        if (r["frames"] not in args.frames or r.get("max_depth") != depth)] + rows
                rows.sort(key=lambda r: (r.get("max_depth") or 99, r["frames"], r["method"] != "octstore"))
            path.write_text(json.dumps(rows, indent=1))
    results = {}
    for section in ("objects", "units", "groundtruth", "interior", "redkitchen", "scale", "cube-sizes", "divide", "simplify"):
        path = args.out / f"results-{section}.json"
        results[section] = json.loads(path.read_text()) if path.exists() else []
    write_markdown(results, args.out, args.markdown)
    print(f"wrote {args.markdown}")


if __name__ == "__main__":
    main()
