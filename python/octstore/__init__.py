"""octstore from Python: build a store from depth maps (files or numpy arrays), solve it, read
the indicator field and the mesh as numpy arrays.

>>> import octstore
>>> store = octstore.Store.create("scene.octstore")
>>> octstore.ingest_arrays(store, depth, K, camera_to_world, kind="rgbd")
>>> octstore.solve(store, iterations=100)
>>> snap = store.snapshot()
>>> u = snap.indicator(points)                    # (N,) float32, NaN outside the root
>>> vertices, faces, normals = snap.extract()

`ingest` and `solve` take the command line's options as keywords (``max_depth=10`` is
``--max-depth 10``, ``resume=True`` is ``--resume``), checked by the command line's own parser,
so defaults and error messages are the same. Long work releases the GIL and shows progress bars
on stderr (``quiet=True`` turns them off). Errors raise `OctstoreError` with the message the
command line prints; arrays of the wrong dtype or shape raise `TypeError` / `ValueError`.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any, NamedTuple, Optional, Sequence, Tuple, Union

import numpy as np

# Before the extension loads: Mesa's device-select layer otherwise prints "error:" lines about
# Wayland while `device="auto"` probes for a GPU (the command line sets the same).
os.environ.setdefault("NODEVICE_SELECT", "1")

from . import _native  # noqa: E402
from ._native import OctstoreError

__all__ = [
    "OctstoreError",
    "Report",
    "Snapshot",
    "Store",
    "demo_views",
    "ingest",
    "ingest_arrays",
    "solve",
]

PathLike = Union[str, "os.PathLike[str]"]


class Report(NamedTuple):
    """What one stage run did: its stage, the version it committed (None when nothing was to
    do) and the summary line the command line prints."""

    stage: str
    version: Optional[int]
    summary: str


class Snapshot:
    """One version of a store, read-only. Taken from a read-only handle, it pins its version
    while it lives, so `octstore gc` in a writer keeps the version's segments."""

    def __init__(self, native: Any) -> None:
        self._native = native

    @property
    def version(self) -> int:
        """The version this snapshot reads."""
        return self._native.version

    def method(self) -> Optional[str]:
        """The solver of the finest level: 'tgv' (u in [-1, 1], negative inside), 'ssd' or
        'hybrid' (u a signed distance in root units); None before a solve."""
        return self._native.method()

    def levels(self) -> list:
        """The solved levels, coarse to fine."""
        return self._native.levels()

    def indicator(self, points: Any) -> np.ndarray:
        """u at each point: `points` is (N, 3) (any real dtype); returns (N,) float32, NaN
        outside the root cube. Runs on every core without the GIL."""
        array = _real_array(points, "points", np.float64)
        if array.ndim != 2 or array.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), not {array.shape}")
        return self._native.indicator(np.ascontiguousarray(array))

    def cubes(self, bbox: Sequence[float], level: Optional[int] = None) -> dict:
        """The cubes of the level-`level` cut (default: the finest) that meet `bbox` =
        (minx, miny, minz, maxx, maxy, maxz): a dict of arrays `center` (N, 3), `size`,
        `depth`, `u`, `histogram` (N, 8), `observed` (a depth map saw the cube), `sampled`,
        and the list `key`."""
        return self._native.cubes(_box(bbox, "bbox"), level)

    def extract(
        self,
        region: Optional[Sequence[float]] = None,
        decimate: Optional[float] = None,
        closed: Optional[bool] = None,
        path: Optional[PathLike] = None,
        max_error: Optional[float] = None,
    ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The surface as `octstore extract` makes it: vertices (V, 3) float32, faces (F, 3)
        uint32, vertex normals (V, 3) float32. `region` clips to a box; the mesh is simplified
        within `max_error` finest cube sides (default 0.25, 0 for every triangle), or to about
        the fraction `decimate` of its triangles; `closed=True` meshes the whole zero set
        (`--closed`), `closed=False` only the observed surface (`--open`), and None lets the
        capture decide as the command line does; `path` also writes the PLY (byte for byte the
        command line's)."""
        box = None if region is None else _box(region, "region")
        return self._native.extract(
            box, decimate, closed, None if path is None else os.fspath(path), max_error
        )

    def __repr__(self) -> str:
        return f"octstore.Snapshot(version={self.version})"


class Store:
    """An octstore store, held open. `Store.create` / `Store.open` write (one writer at a
    time); `Store.open_read_only` reads, also while another handle or process writes."""

    def __init__(self, native: Any) -> None:
        self._native = native

    @staticmethod
    def create(path: PathLike) -> "Store":
        """Creates an empty store in the new folder `path`."""
        return Store(_native.Store.create(os.fspath(path)))

    @staticmethod
    def open(path: PathLike) -> "Store":
        """Opens an existing store for writing."""
        return Store(_native.Store.open(os.fspath(path)))

    @staticmethod
    def open_read_only(path: PathLike) -> "Store":
        """Opens an existing store for reading only."""
        return Store(_native.Store.open_read_only(os.fspath(path)))

    @property
    def path(self) -> Path:
        """The store's folder."""
        return Path(self._native.path)

    @property
    def read_only(self) -> bool:
        """Whether this handle only reads."""
        return self._native.read_only

    def log(self) -> list:
        """Every committed version, oldest first, as (version, what made it, summary)."""
        return self._native.log()

    def versions(self) -> list:
        """Every committed version number, oldest first."""
        return [version for version, _, _ in self._native.log()]

    def snapshot(self, v: Optional[int] = None) -> Snapshot:
        """A view of version `v` (default: the latest)."""
        return Snapshot(self._native.snapshot(v))

    def __repr__(self) -> str:
        return repr(self._native)


def demo_views() -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The depth maps of `octstore demo` (a sphere on a box in a room: 16 views of 160x120
    with depth noise and 2 % outlier pixels) as (depths (16, 120, 160) float32 in metres,
    K (3, 3), camera_to_world (16, 4, 4) with OpenCV axes): input for `ingest_arrays`."""
    return _native.demo_views()


def _flags(options: dict) -> list:
    """Keywords as command-line flags: ``max_depth=10`` -> ``--max-depth 10``, ``True`` -> the
    bare flag, ``False`` / ``None`` -> left out, sequences joined by commas."""
    argv = []
    for name, value in options.items():
        flag = "--" + name.replace("_", "-")
        if value is None or value is False:
            continue
        if value is True:
            argv.append(flag)
            continue
        if isinstance(value, (list, tuple, np.ndarray)):
            value = ",".join(repr(float(v)) if isinstance(v, float) else str(v) for v in value)
        argv += [flag, str(value)]
    return argv


def ingest(store: Store, inputs: Union[PathLike, Sequence[PathLike]], **options: Any) -> Report:
    """Registers the depth maps `inputs` names (files, folders, manifests, as the command line
    reads them) and writes their cubes, as one new version. Keywords are `octstore ingest`'s
    options (``max_depth``, ``root_margin``, ``root=(x, y, z, side)``, ``format``, ``stride``,
    ``limit``, ``intrinsics``, ``depth_noise``, ``sample_sums=True`` for a store that will be
    solved with ``method="ssd"`` or ``"hybrid"``, ``resume``, ``memory_budget``, ``threads``,
    ``quiet``)."""
    if isinstance(inputs, (str, os.PathLike)):
        inputs = [inputs]
    argv = ["octstore", "ingest", *_flags(options), "--", str(store.path), *map(os.fspath, inputs)]
    return Report(*_native.ingest(store._native, argv))


def solve(store: Store, **options: Any) -> list:
    """Brings the octree, the histograms and every level of the solution up to date; returns
    a `Report` per stage. Keywords are `octstore solve`'s options (``resume``, ``method``,
    ``iterations``, ``until``, ``device``, ``leaf_cubes``, ``memory_budget``, ``threads``,
    ``quiet``, the solver weights)."""
    argv = ["octstore", "solve", *_flags(options), "--", str(store.path)]
    return [Report(*r) for r in _native.solve(store._native, argv)]


def _real_array(value: Any, name: str, dtype: Any) -> np.ndarray:
    array = np.asarray(value)
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise TypeError(f"{name} must hold real numbers, not {array.dtype}")
    return array.astype(dtype, copy=False)


def _box(values: Sequence[float], name: str) -> list:
    box = _real_array(values, name, np.float64).reshape(-1)
    if box.shape != (6,) or not np.all(np.isfinite(box)) or np.any(box[:3] >= box[3:]):
        raise ValueError(f"{name} must be (minx, miny, minz, maxx, maxy, maxz) with min < max, not {values!r}")
    return [float(v) for v in box]


def ingest_arrays(
    store: Store,
    depth: Any,
    K: Any,
    camera_to_world: Any,
    kind: str = "rgbd",
    **options: Any,
) -> Report:
    """Ingests depth maps already in memory (a live capture, a renderer, a network), as one
    new version.

    `depth` is (H, W) or (N, H, W) float (metres; 0, NaN or negative marks a missing pixel),
    `K` the pinhole intrinsics (3, 3) or (N, 3, 3) in pixels with OpenCV axes, and
    `camera_to_world` the pose (4, 4) or (N, 4, 4). `kind` is 'rgbd', 'photo' or 'lidar' (it
    picks the vote weight; the depth noise is measured from the maps unless ``depth_noise``
    says otherwise). The maps are saved in the store's
    `arrays/` folder, named by their content (later stages read them again; the same map
    twice is ingested once), and ingested with `ingest`'s keywords."""
    depth = np.asarray(depth)
    if not np.issubdtype(depth.dtype, np.floating):
        raise TypeError(
            f"depth must be a float array of metres, not {depth.dtype} (divide integer depths by their scale first)"
        )
    if depth.ndim == 2:
        depth = depth[None]
    if depth.ndim != 3 or depth.shape[1] < 2 or depth.shape[2] < 2:
        raise ValueError(f"depth must have shape (H, W) or (N, H, W), not {np.shape(depth)}")
    count, height, width = depth.shape
    K = _per_map(K, (3, 3), count, "K")
    poses = _per_map(camera_to_world, (4, 4), count, "camera_to_world")
    if kind not in ("rgbd", "photo", "lidar"):
        raise ValueError(f"kind must be 'rgbd', 'photo' or 'lidar', not {kind!r}")
    folder = store.path / "arrays"
    folder.mkdir(exist_ok=True)
    entries = []
    for index in range(count):
        image = np.ascontiguousarray(depth[index], dtype="<f4")
        k, pose = K[index], poses[index]
        if k[2, 0] != 0 or k[2, 1] != 0 or k[2, 2] != 1 or k[0, 1] != 0 or k[1, 0] != 0:
            raise ValueError(f"K[{index}] must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], not {k.tolist()}")
        digest = hashlib.sha256()
        for part in (image.tobytes(), k.tobytes(), pose.tobytes(), kind.encode()):
            digest.update(part)
        name = digest.hexdigest()[:24] + ".npy"
        if not (folder / name).exists():
            partial = folder / (name + ".partial")
            with open(partial, "wb") as out:
                np.save(out, image)
                out.flush()
                os.fsync(out.fileno())
            os.replace(partial, folder / name)
        entries.append(
            {
                "image": name,
                "width": width,
                "height": height,
                "intrinsics": {"fx": float(k[0, 0]), "fy": float(k[1, 1]), "cx": float(k[0, 2]), "cy": float(k[1, 2])},
                "pose": {"camera_to_world": [float(v) for v in pose.reshape(-1)], "axes": "opencv"},
                "kind": kind,
            }
        )
    manifest_text = json.dumps({"depth_maps": entries}, indent=1)
    manifest = folder / (hashlib.sha256(manifest_text.encode()).hexdigest()[:24] + ".json")
    manifest.write_text(manifest_text)
    return ingest(store, [manifest], **options)


def _per_map(value: Any, shape: tuple, count: int, name: str) -> np.ndarray:
    array = _real_array(value, name, np.float64)
    if array.shape == shape:
        array = np.broadcast_to(array, (count, *shape))
    if array.shape != (count, *shape):
        raise ValueError(f"{name} must have shape {shape} or ({count}, {shape[0]}, {shape[1]}), not {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} has non-finite entries (NaN or infinity)")
    return array
