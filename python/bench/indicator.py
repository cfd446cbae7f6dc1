"""Indicator reads per second from Python (issue: >= 5 M points/s on 2 cores).

Builds the demo's scene (a sphere on a box in a room, 16 views of 160x120) into a store at
`--max-depth 8`, solves it, and times `snap.indicator` on 1 M points spread over the scene
(random, so the batches are not pre-sorted), best of 5. Run: python python/bench/indicator.py
"""

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import octstore

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_octstore import SPHERE_CENTER, views  # noqa: E402


def main():
    with tempfile.TemporaryDirectory() as tmp:
        store = octstore.Store.create(Path(tmp) / "store")
        depths, K, poses = views(count=16, width=160, height=120)
        octstore.ingest_arrays(store, depths, K, poses, max_depth=8, quiet=True)
        started = time.perf_counter()
        octstore.solve(store, iterations=100, device="cpu", quiet=True)
        solve_seconds = time.perf_counter() - started
        snap = store.snapshot()
        cubes = snap.cubes([-10, -10, -10, 10, 10, 10])
        rng = np.random.default_rng(7)
        points = SPHERE_CENTER + rng.uniform(-1.5, 1.5, size=(1_000_000, 3))
        best = float("inf")
        for _ in range(5):
            started = time.perf_counter()
            u = snap.indicator(points)
            best = min(best, time.perf_counter() - started)
        inside = int(np.sum(u < 0))
        print(f"scene: {len(cubes['u'])} finest-cut cubes (solved in {solve_seconds:.1f} s)")
        print(f"indicator: {len(points)} points in {best:.3f} s = {len(points) / best / 1e6:.2f} M points/s ({inside} inside)")


if __name__ == "__main__":
    main()
