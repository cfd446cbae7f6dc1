"""The `divide` section of bench.py: `octstore divide` on a generated cloud of a billion points
(rate and peak RSS at two memory budgets), and the bunny divided, reconstructed part by part by
octstore and merged (`octstore merge`), against the undivided reconstruction."""

import json
import re
import subprocess
from pathlib import Path

DIVIDE_LINE = re.compile(r"divide\s+(\d+) points -> (\d+) subspaces .*?\((\d+) files written, (\d+) points with "
                         r"overlaps; largest core (\d+) points; counted (\d+) levels a pass, (\d+) nodes divided again\)"
                         r" \| ([\d.]+)s.*peak memory (\d+) MB")
MERGE_LINE = re.compile(r"merge\s+(\d+) meshes -> (\d+) vertices, (\d+) triangles \((\d+) cut away, (\d+) vertices "
                        r"welded\), (\d+) boundary edges")


def synthetic(bin_dir, work, points, budget, max_points, run_measured):
    out = work / f"synthetic-{budget}"
    stdout, _, wall, cpu, _ = run_measured(
        [str(bin_dir / "octstore"), "--quiet", "--memory-budget", budget, "divide", "--synthetic", str(points),
         "-o", str(out), "--max-points", str(max_points)])
    match = DIVIDE_LINE.search(stdout)
    if not match:
        raise SystemExit(f"octstore divide printed no summary: {stdout}")
    subprocess.run(["rm", "-rf", str(out)], check=True)
    # octstore's own peak: the children's ru_maxrss is the largest child so far.
    peak = float(match.group(9))
    return {"case": "synthetic", "points": int(match.group(1)), "subspaces": int(match.group(2)),
            "points_written": int(match.group(4)), "largest_core": int(match.group(5)),
            "counting_depth": int(match.group(6)), "divided_again": int(match.group(7)),
            "budget": budget, "max_points": max_points, "wall_s": wall, "cpu_s": cpu, "peak_mb": peak,
            "points_per_s": points / wall}


def incremental(bin_dir, work, points, max_points, region, run_measured):
    """A later divide into a folder: a cloud of `points` (points on a rolling surface 100 units
    square with a random spread, float x, y, z) divided, then `points` / 4 more in a square of
    `region` times the side added to the folder, against all of them divided afresh."""
    import numpy as np

    rng = np.random.default_rng(7)

    def cloud(path, count, corners, side):
        xy = rng.random((count, 2)) * 100.0 * side
        z = np.clip(5.0 * np.sin(xy[:, 0] / 7.0) * np.cos(xy[:, 1] / 11.0) + rng.normal(0.0, 0.05, count), -5.5, 5.5)
        if corners:
            box = np.array([[x, y, z] for x in (0.0, 100.0) for y in (0.0, 100.0) for z in (-6.0, 6.0)])
            xy[:8], z[:8] = box[:, :2], box[:, 2]
        record = np.zeros(count, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
        record["x"], record["y"], record["z"] = xy[:, 0], xy[:, 1], z
        header = ("ply\nformat binary_little_endian 1.0\n"
                  f"element vertex {count}\nproperty float x\nproperty float y\nproperty float z\nend_header\n")
        path.write_bytes(header.encode() + record.tobytes())

    # The first cloud spans the corners of the region, so the second lies inside its root.
    first, second = work / "incremental-first.ply", work / "incremental-second.ply"
    cloud(first, points, True, 1.0)
    cloud(second, points // 4, False, region)
    later, fresh = work / "incremental-later", work / "incremental-fresh"
    subprocess.run(["rm", "-rf", str(later), str(fresh)], check=True)
    octstore = [str(bin_dir / "octstore"), "--quiet", "divide", "--max-points", str(max_points)]
    _, _, first_wall, _, _ = run_measured(octstore + [str(first), "-o", str(later)])
    before = len(list(later.glob("*.ply")))
    stdout, _, later_wall, _, _ = run_measured(octstore + [str(second), "-o", str(later)])
    match = DIVIDE_LINE.search(stdout)
    if not match:
        raise SystemExit(f"octstore divide printed no summary: {stdout}")
    stdout, _, fresh_wall, _, _ = run_measured(octstore + [str(first), str(second), "-o", str(fresh)])
    fresh_match = DIVIDE_LINE.search(stdout)
    if not fresh_match:
        raise SystemExit(f"octstore divide printed no summary: {stdout}")
    row = {"case": "incremental", "points": points, "added": points // 4, "region": region,
           "max_points": max_points, "subspaces_before": before,
           "subspaces": int(match.group(2)), "files_rewritten": int(match.group(3)), "first_wall_s": first_wall,
           "later_wall_s": later_wall, "later_peak_mb": float(match.group(9)), "fresh_wall_s": fresh_wall,
           "fresh_peak_mb": float(fresh_match.group(9)), "fresh_subspaces": int(fresh_match.group(2))}
    subprocess.run(["rm", "-rf", str(later), str(fresh), str(first), str(second)], check=True)
    return row


def write_cloud(views, path):
    """The views' valid pixels as points, with the view and pixel they came from (so a subspace's
    file says which pixels to keep)."""
    import numpy as np

    chunks = []
    for index, (depth, intrinsic, pose) in enumerate(views):
        h, w = depth.shape
        jj, ii = np.mgrid[0:h, 0:w]
        keep = depth > 0
        z = depth[keep].astype(np.float64)
        x = (ii[keep] - intrinsic[0, 2]) * z / intrinsic[0, 0]
        y = (jj[keep] - intrinsic[1, 2]) * z / intrinsic[1, 1]
        world = (pose @ np.stack([x, y, z, np.ones_like(z)])).T[:, :3]
        record = np.zeros(len(z), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("view", "<u2"), ("pixel", "<u4")])
        record["x"], record["y"], record["z"] = world[:, 0], world[:, 1], world[:, 2]
        record["view"] = index
        record["pixel"] = (jj[keep] * w + ii[keep]).astype(np.uint32)
        chunks.append(record)
    cloud = np.concatenate(chunks)
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(cloud)}\nproperty double x\nproperty double y\nproperty double z\n"
              "property ushort view\nproperty uint pixel\nend_header\n")
    path.write_bytes(header.encode() + cloud.tobytes())
    return len(cloud)


def read_pixels(path):
    import numpy as np

    data = path.read_bytes()
    body = data.index(b"end_header\n") + len(b"end_header\n")
    return np.frombuffer(data[body:], dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("view", "<u2"),
                                             ("pixel", "<u4")])


def off_bounds(path):
    """The bounding box of an OFF mesh's vertices."""
    import numpy as np

    tokens = Path(path).read_text().split()
    start = 1 if tokens[0] == "OFF" else 0
    vertices = int(tokens[start])
    first = start + 3
    xyz = np.array(tokens[first:first + 3 * vertices], dtype=np.float64).reshape(-1, 3)
    return xyz.min(axis=0), xyz.max(axis=0)


def write_pfm(path, image):
    import numpy as np

    h, w = image.shape
    path.write_bytes(f"Pf\n{w} {h}\n-1\n".encode() + np.flipud(image).astype("<f4").tobytes())


def pixels_through(depth, intrinsic, pose, low, high):
    """The valid pixels whose ray, from the camera to the pixel's point, meets the box
    [low, high]: what a depth-map method needs of a part (its points, and the free space in
    front of the surfaces behind it)."""
    import numpy as np

    h, w = depth.shape
    jj, ii = np.mgrid[0:h, 0:w]
    flat = depth.reshape(-1)
    valid = np.nonzero(flat > 0)[0]
    z = flat[valid].astype(np.float64)
    x = (ii.reshape(-1)[valid] - intrinsic[0, 2]) * z / intrinsic[0, 0]
    y = (jj.reshape(-1)[valid] - intrinsic[1, 2]) * z / intrinsic[1, 1]
    end = (pose @ np.stack([x, y, z, np.ones_like(z)]))[:3].T
    start = pose[:3, 3]
    direction = end - start
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (low - start) / direction
        t1 = (high - start) / direction
    near = np.nanmax(np.minimum(t0, t1), axis=1)
    far = np.nanmin(np.maximum(t0, t1), axis=1)
    meets = (near <= far) & (far >= 0) & (near <= 1)
    return valid[meets]


def bunny_merge(bin_dir, work, truth, octstore_run, evaluate, read_manifest, parts=8, overlap=0.1, rays=True):
    """The bunny (0.2 % noise, 24 views) reconstructed whole and part by part: the cloud of
    all pixels divided into about `parts` subspaces; each part's store ingests only the pixels
    in its grown cube, in the whole store's root cube (same cubes), is solved and extracted;
    `octstore merge` cuts and welds the part meshes."""
    import numpy as np

    octstore = str(bin_dir / "octstore")
    views_dir = work / "bunny-views"
    subprocess.run([str(bin_dir / "octstore-gt-render"), str(truth), "--out", str(views_dir), "--views", "24",
                    "--width", "320", "--height", "240", "--noise", "0.002", "--outliers", "0"],
                   check=True, capture_output=True)
    manifest = views_dir / "scene.json"
    whole_mesh = work / "bunny-whole.ply"
    whole_store = work / "bunny-whole"
    wall_whole = octstore_run(whole_store, manifest, ["--max-depth", "9"], ["--iterations", "100"], whole_mesh)[0]
    info = json.loads(subprocess.run([octstore, "info", str(whole_store), "--json"], check=True,
                                     capture_output=True, text=True).stdout)
    root = ",".join(str(v) for v in [*info["root_min"], info["root_side"]])
    views = read_manifest(manifest)
    cloud = work / "bunny-cloud.ply"
    points = write_cloud(views, cloud)
    division = work / "bunny-division"
    out = subprocess.run([octstore, "--quiet", "divide", str(cloud), "-o", str(division), "--max-points",
                          str(points // parts), "--overlap", str(overlap)], check=True, capture_output=True, text=True).stdout
    subspaces = json.loads((division / "subspaces.json").read_text())["subspaces"]
    spec = json.loads(manifest.read_text())
    meshes = []
    wall_parts = 0.0
    for subspace in subspaces:
        stem = subspace["file"].removesuffix(".ply")
        part = work / f"bunny-part-{stem}"
        part.mkdir()
        records = read_pixels(division / subspace["file"])
        grown = subspace["grown"]
        low = np.array(grown["min"])
        high = low + grown["size"]
        entries = []
        for index, (depth, intrinsic, pose) in enumerate(views):
            if rays:
                pixels = pixels_through(depth, intrinsic, pose, low, high)
            else:
                pixels = records["pixel"][records["view"] == index]
            if len(pixels) == 0:
                continue
            masked = np.zeros(depth.size, dtype=np.float32)
            masked[pixels] = depth.reshape(-1)[pixels]
            image = f"view-{index:03d}.pfm"
            write_pfm(part / image, masked.reshape(depth.shape))
            entries.append({**spec["depth_maps"][index], "image": image})
        (part / "scene.json").write_text(json.dumps({**spec, "depth_maps": entries}))
        mesh = work / f"{stem}.mesh.ply"
        wall_parts += octstore_run(part / "store", part / "scene.json", ["--max-depth", "9", f"--root={root}"],
                                   ["--iterations", "100"], mesh)[0]
        meshes.append(str(mesh))
    merged = work / "bunny-merged.ply"
    out = subprocess.run([octstore, "merge", str(division / "subspaces.json"), *meshes, "-o", str(merged)],
                         check=True, capture_output=True, text=True).stdout
    match = MERGE_LINE.search(out)
    against_whole = evaluate(merged, whole_mesh)
    # The same near the object only: the whole mesh cut to the true bunny's box (5 % margin),
    # so tau is a fraction of the bunny's diagonal, not the room's.
    low, high = off_bounds(truth)
    margin = 0.05 * float(np.linalg.norm(high - low))
    region = ",".join(str(v) for v in [*(low - margin), *(high + margin)])
    whole_near = work / "bunny-whole-near.ply"
    subprocess.run([octstore, "extract", str(whole_store), "-o", str(whole_near), f"--region={region}"], check=True,
                   capture_output=True)
    against_near = evaluate(merged, whole_near)
    against_truth = evaluate(merged, truth)
    whole_truth = evaluate(whole_mesh, truth)
    return {"case": "bunny-merge", "points": points, "subspaces": len(subspaces), "overlap": overlap, "rays": rays,
            "max_points": points // parts, "merge_boundary_edges": int(match.group(6)) if match else None,
            "merge_welded": int(match.group(5)) if match else None,
            "f_vs_whole_0.01": against_whole["f_score"], "f_vs_whole_0.005": against_whole["f_score_0.005"],
            "f_vs_whole_0.002": against_whole["f_score_0.002"],
            "f_vs_whole_near_0.01": against_near["f_score"], "f_vs_whole_near_0.005": against_near["f_score_0.005"],
            "f_vs_whole_near_0.002": against_near["f_score_0.002"],
            "f_truth_0.005_merged": against_truth["f_score_0.005"], "f_truth_0.005_whole": whole_truth["f_score_0.005"],
            "chamfer_merged": against_truth.get("chamfer"), "chamfer_whole": whole_truth.get("chamfer"),
            "wall_whole_s": wall_whole, "wall_parts_s": wall_parts}


def markdown(rows):
    if not rows:
        return []
    lines = ["", "## Division of point clouds (`octstore divide`, `octstore merge`)", "",
             "A generated cloud (a rolling terrain 1000 units square, density falling a hundredfold along x; "
             "`octstore divide --synthetic N`, nothing read from disk) divided into subspaces of at most "
             "`--max-points`, overlap 0.1; the subspace files (float x, y, z) are written to the local disk. "
             "Kuhn and Mayer's anchor: 1.5 G points in 18 min on 8 cores, 0.17 M points/s per core.", "",
             "| points | --memory-budget | --max-points | subspaces | points written | levels a pass | wall s | "
             "M points/s | M points/s per core | peak MB |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in (r for r in rows if r["case"] == "synthetic"):
        lines.append(f"| {r['points']:,} | {r['budget']} | {r['max_points']:,} | {r['subspaces']} | "
                     f"{r['points_written']:,} | {r['counting_depth']} | {r['wall_s']:.0f} | "
                     f"{r['points_per_s'] / 1e6:.1f} | {r['points_per_s'] / 2e6:.1f} | {r['peak_mb']:.0f} |")
    later = [r for r in rows if r["case"] == "incremental"]
    if later:
        lines += ["", "A later divide into the same folder (`octstore divide NEW -o FOLDER`): a cloud of N points on a "
                  "rolling surface 100 units square (binary PLY) divided, N / 4 more added in a square of the "
                  "given share of the side, against all of them divided afresh into a new folder (the folders may "
                  "differ: the later divide rewrites only what the new points touch, or divides everything afresh "
                  "when the subspaces to divide again hold half the points).", "",
                  "| N | added | in a square of | --max-points | subspaces before | after | files rewritten | "
                  "first s | later s | afresh s | later peak MB | afresh peak MB |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in later:
            lines.append(f"| {r['points']:,} | {r['added']:,} | {r['region']} | {r['max_points']:,} | "
                         f"{r['subspaces_before']} | {r['subspaces']} | "
                         f"{r['files_rewritten']} | {r['first_wall_s']:.2f} | {r['later_wall_s']:.2f} | "
                         f"{r['fresh_wall_s']:.2f} | {r['later_peak_mb']:.0f} | {r['fresh_peak_mb']:.0f} |")
    merges = [r for r in rows if r["case"] == "bunny-merge"]
    if merges:
        lines += ["", "The bunny in its room (24 views of 320x240, 0.2 % depth noise) reconstructed whole and part by "
                  "part: the cloud of all its pixels divided (`--max-points` an eighth of them), each part's store "
                  "fed the pixels whose ray from the camera meets the part's grown cube (its points, and the free "
                  "space in front of what lies behind it; `--root` of the whole store, `--max-depth 9`, 100 "
                  "iterations), the part meshes merged. "
                  "F of the merged mesh against the whole one at 1 / 0.5 / 0.2 % of the diagonal (of the room; "
                  "near the bunny: both cut to its box, tau a fraction of its diagonal), and both against the "
                  "true bunny at 0.5 %:", "",
                  "| points | subspaces | F vs whole 1 % | 0.5 % | 0.2 % | near bunny 0.5 % | 0.2 % | F truth merged | "
                  "F truth whole | boundary edges after merge | whole s | parts s |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in merges:
            near = [r.get(f"f_vs_whole_near_{t}") for t in ("0.005", "0.002")]
            near = " | ".join("-" if v is None else f"{v:.4f}" for v in near)
            lines.append(f"| {r['points']:,} | {r['subspaces']} | {r['f_vs_whole_0.01']:.4f} | "
                         f"{r['f_vs_whole_0.005']:.4f} | {r['f_vs_whole_0.002']:.4f} | {near} | "
                         f"{r['f_truth_0.005_merged']:.4f} | "
                         f"{r['f_truth_0.005_whole']:.4f} | {r['merge_boundary_edges']} | {r['wall_whole_s']:.0f} | "
                         f"{r['wall_parts_s']:.0f} |")
    return lines + [""]
