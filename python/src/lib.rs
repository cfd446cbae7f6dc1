//! `octstore._native`: the Python extension behind the `octstore` package (`python/octstore/`).
//!
//! It holds a store open (`Store`), reads pinned versions (`Snapshot`) into numpy arrays, and
//! runs `ingest` and `solve` from a command line that the `octstore` command's own parser
//! checks (`octstore::cli::library_call`), so options, defaults and error messages are the
//! command line's. Long work releases the GIL; errors are `OctstoreError` with the message the
//! command line prints after "error: ".

#![allow(
    clippy::result_large_err,
    reason = "each store error crosses into Python once per call, where it becomes a message"
)]

use std::path::PathBuf;
use std::sync::Arc;

use glam::DVec3;
use numpy::{IntoPyArray, PyArray1, PyArray2, PyArray3, PyArrayMethods, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::PyException;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use octstore::cli::{LibraryCall, library_call};
use octstore::{BoundingBox, ExtractOptions, IndicatorField, RunReport, Simplify, SurfaceChoice};

pyo3::create_exception!(
    octstore,
    OctstoreError,
    PyException,
    "An octstore error: bad input, a damaged or busy store, a version gc removed. The message is the command line's."
);

fn error(e: impl std::fmt::Display) -> PyErr {
    OctstoreError::new_err(e.to_string())
}

/// An octstore store, held open (writable, or read-only beside a writer in another handle).
#[pyclass(frozen, module = "octstore._native")]
struct Store {
    inner: Arc<octstore::Store>,
    path: PathBuf,
    read_only: bool,
}

fn held(store: octstore::Store, path: PathBuf, read_only: bool) -> Store {
    Store {
        inner: Arc::new(store),
        path,
        read_only,
    }
}

#[pymethods]
impl Store {
    /// Creates an empty store at `path` (a new folder) and opens it for writing.
    #[staticmethod]
    fn create(py: Python<'_>, path: PathBuf) -> PyResult<Store> {
        let store = py.detach(|| octstore::Store::create(&path)).map_err(error)?;
        Ok(held(store, path, false))
    }

    /// Opens an existing store for writing (one writer at a time; readers may open it too).
    #[staticmethod]
    fn open(py: Python<'_>, path: PathBuf) -> PyResult<Store> {
        let store = py.detach(|| octstore::Store::open(&path)).map_err(error)?;
        Ok(held(store, path, false))
    }

    /// Opens an existing store for reading only; works while a writer runs.
    #[staticmethod]
    fn open_read_only(py: Python<'_>, path: PathBuf) -> PyResult<Store> {
        let store = py.detach(|| octstore::Store::open_read_only(&path)).map_err(error)?;
        Ok(held(store, path, true))
    }

    /// The store's folder.
    #[getter]
    fn path(&self) -> PathBuf {
        self.path.clone()
    }

    /// Whether this handle only reads.
    #[getter]
    fn read_only(&self) -> bool {
        self.read_only
    }

    /// Every committed version, oldest first, as (version, what made it, summary).
    fn log(&self, py: Python<'_>) -> PyResult<Vec<(u64, String, String)>> {
        let store = self.inner.clone();
        let log = py.detach(move || store.log()).map_err(error)?;
        Ok(log
            .into_iter()
            .map(|(version, record, _)| (version, record.kind, record.summary))
            .collect())
    }

    /// A pinned view of `version` (default: the latest).
    #[pyo3(signature = (version = None))]
    fn snapshot(&self, py: Python<'_>, version: Option<u64>) -> PyResult<Snapshot> {
        let store = self.inner.clone();
        let (version, pin) = py
            .detach(move || {
                let mut snapshot = match version {
                    Some(v) => store.snapshot(v)?,
                    None => store.latest()?,
                };
                Ok::<_, octstore::StoreError>((snapshot.version(), snapshot.take_pin()))
            })
            .map_err(error)?;
        Ok(Snapshot {
            store: self.inner.clone(),
            version,
            _pin: pin,
        })
    }

    fn __repr__(&self) -> String {
        format!(
            "octstore.Store('{}'{})",
            self.path.display(),
            if self.read_only { ", read_only=True" } else { "" }
        )
    }
}

/// One version of a store. From a read-only handle it pins its version while it lives, so a
/// writer's `gc` keeps the version's segments (a writer's own snapshots need no pin: gc runs
/// in the writer).
#[pyclass(frozen, module = "octstore._native")]
struct Snapshot {
    store: Arc<octstore::Store>,
    version: u64,
    _pin: Option<octstore::store::ReaderPin>,
}

/// Rows of an (N, 3) float64 array as points.
fn points_of(array: &PyReadonlyArray2<'_, f64>, what: &str) -> PyResult<Vec<DVec3>> {
    let shape = array.shape();
    if shape.get(1) != Some(&3) {
        return Err(pyo3::exceptions::PyValueError::new_err(format!(
            "{what} must have shape (N, 3), not {shape:?}"
        )));
    }
    // Contiguous (the Python side asks for it): one pass over the buffer.
    if let Ok(flat) = array.as_slice() {
        return Ok(flat.chunks_exact(3).map(|r| DVec3::new(r[0], r[1], r[2])).collect());
    }
    let view = array.as_array();
    Ok(view.rows().into_iter().map(|r| DVec3::new(r[0], r[1], r[2])).collect())
}

#[pymethods]
impl Snapshot {
    /// The version this snapshot reads.
    #[getter]
    fn version(&self) -> u64 {
        self.version
    }

    /// The solver of the finest level (`tgv`, `ssd` or `hybrid`), or None before a solve.
    fn method(&self, py: Python<'_>) -> PyResult<Option<String>> {
        let (store, version) = (self.store.clone(), self.version);
        py.detach(move || {
            let snapshot = store.snapshot(version)?;
            Ok::<_, octstore::StoreError>(snapshot.method()?.map(str::to_string))
        })
        .map_err(error)
    }

    /// The solved levels, coarse to fine.
    fn levels(&self, py: Python<'_>) -> PyResult<Vec<u8>> {
        let (store, version) = (self.store.clone(), self.version);
        py.detach(move || store.snapshot(version).map(|s| s.levels()))
            .map_err(error)
    }

    /// u at each row of `points` (float64, shape (N, 3)); NaN outside the root cube.
    fn indicator<'py>(
        &self,
        py: Python<'py>,
        points: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray1<f32>>> {
        let points = points_of(&points, "points")?;
        let (store, version) = (self.store.clone(), self.version);
        let values = py
            .detach(move || {
                let snapshot = store.snapshot(version)?;
                octstore::query::indicator_at_points(&snapshot, &points)
            })
            .map_err(error)?;
        Ok(values.into_pyarray(py))
    }

    /// The cubes of the level-`level` cut (default: the finest) that meet the box
    /// (minx, miny, minz, maxx, maxy, maxz), as a dict of arrays.
    #[pyo3(signature = (bbox, level = None))]
    fn cubes<'py>(&self, py: Python<'py>, bbox: [f64; 6], level: Option<u8>) -> PyResult<Bound<'py, PyDict>> {
        let [a, b, c, d, e, f] = bbox;
        let region = BoundingBox {
            min: DVec3::new(a, b, c),
            max: DVec3::new(d, e, f),
        };
        let (store, version) = (self.store.clone(), self.version);
        let cubes = py
            .detach(move || {
                let snapshot = store.snapshot(version)?;
                let level = level.or_else(|| snapshot.finest_level()).unwrap_or(0);
                snapshot.cubes_in(&region, level)
            })
            .map_err(error)?;
        let n = cubes.len();
        let dict = PyDict::new(py);
        dict.set_item("center", rows(py, cubes.iter().flat_map(|c| c.center).collect(), n, 3)?)?;
        dict.set_item(
            "size",
            cubes.iter().map(|c| c.size).collect::<Vec<_>>().into_pyarray(py),
        )?;
        dict.set_item(
            "depth",
            cubes.iter().map(|c| c.depth).collect::<Vec<_>>().into_pyarray(py),
        )?;
        dict.set_item("u", cubes.iter().map(|c| c.u).collect::<Vec<_>>().into_pyarray(py))?;
        let histogram: Vec<f32> = cubes.iter().flat_map(|c| c.histogram).collect();
        dict.set_item("histogram", rows(py, histogram, n, octstore::query::HISTOGRAM_BINS)?)?;
        dict.set_item(
            "observed",
            cubes.iter().map(|c| c.seen).collect::<Vec<_>>().into_pyarray(py),
        )?;
        dict.set_item(
            "sampled",
            cubes.iter().map(|c| c.sampled).collect::<Vec<_>>().into_pyarray(py),
        )?;
        dict.set_item("key", cubes.iter().map(|c| c.key.clone()).collect::<Vec<_>>())?;
        Ok(dict)
    }

    /// The surface, as `octstore extract` writes it (to `path` too when given): vertices
    /// (V, 3) float32, faces (F, 3) uint32 and vertex normals (V, 3) float32. `closed`: True
    /// for the whole zero set (`--closed`), False for only the observed surface (`--open`),
    /// None (the default) to let the capture decide as `extract` does.
    #[pyo3(signature = (region = None, decimate = None, closed = None, path = None, max_error = None))]
    #[expect(clippy::type_complexity, reason = "the three arrays Python receives as a tuple")]
    fn extract<'py>(
        &self,
        py: Python<'py>,
        region: Option<[f64; 6]>,
        decimate: Option<f32>,
        closed: Option<bool>,
        path: Option<PathBuf>,
        max_error: Option<f32>,
    ) -> PyResult<(
        Bound<'py, PyArray2<f32>>,
        Bound<'py, PyArray2<u32>>,
        Bound<'py, PyArray2<f32>>,
    )> {
        let options = ExtractOptions {
            region: region.map(|[a, b, c, d, e, f]| BoundingBox {
                min: DVec3::new(a, b, c),
                max: DVec3::new(d, e, f),
            }),
            simplify: match (decimate, max_error) {
                (Some(fraction), _) => Simplify::Fraction(fraction),
                (None, Some(error)) if error <= 0.0 => Simplify::Full,
                (None, Some(error)) => Simplify::MaxError(error),
                (None, None) => Simplify::default(),
            },
            surface: match closed {
                None => SurfaceChoice::Auto,
                Some(true) => SurfaceChoice::Whole,
                Some(false) => SurfaceChoice::Observed,
            },
        };
        let (store, version) = (self.store.clone(), self.version);
        let mesh = py
            .detach(move || -> Result<octstore::Mesh, String> {
                let scratch = tempfile::tempdir().map_err(|e| format!("temporary folder: {e}"))?;
                let output = path.unwrap_or_else(|| scratch.path().join("mesh.ply"));
                // The CLI's default --memory-budget (1 GiB) bounds the pieces computed ahead.
                octstore::pipeline::extract(&store, &output, &options, Some(version), 1 << 30)
                    .map_err(|e| e.to_string())?;
                octstore::mesh::read_mesh(&output).map_err(|e| e.to_string())
            })
            .map_err(error)?;
        let (v, f) = (mesh.positions.len(), mesh.triangles.len());
        let normals = if mesh.normals.len() == v {
            mesh.normals
        } else {
            vec![[0.0; 3]; v]
        };
        Ok((
            rows(py, mesh.positions.concat(), v, 3)?,
            rows(py, mesh.triangles.concat(), f, 3)?,
            rows(py, normals.concat(), v, 3)?,
        ))
    }

    fn __repr__(&self) -> String {
        format!("octstore.Snapshot(version={})", self.version)
    }
}

/// `values` (`n` rows of `width`, row-major) as an (n, width) array.
fn rows<T: numpy::Element>(py: Python<'_>, values: Vec<T>, n: usize, width: usize) -> PyResult<Bound<'_, PyArray2<T>>> {
    values
        .into_pyarray(py)
        .reshape([n, width])
        .map_err(|e| error(format!("an array of {n} rows of {width}: {e}")))
}

fn report_tuple(report: &RunReport) -> (String, Option<u64>, String) {
    (report.stage.clone(), report.version, report.summary.clone())
}

/// Runs `argv` (`["octstore", "ingest", STORE, INPUT..., options]`) on `store`; returns the
/// run's (stage, version, summary).
#[pyfunction]
fn ingest(py: Python<'_>, store: &Store, argv: Vec<String>) -> PyResult<(String, Option<u64>, String)> {
    let call = library_call(&argv).map_err(error)?;
    let LibraryCall::Ingest {
        inputs,
        discover,
        options,
        run,
    } = call
    else {
        return Err(error("not an ingest command line"));
    };
    let inner = store.inner.clone();
    let report = py
        .detach(move || octstore::pipeline::ingest(&inner, &inputs, &discover, &options, &run))
        .map_err(error)?;
    Ok(report_tuple(&report))
}

/// Runs `argv` (`["octstore", "solve", STORE, options]`) on `store`; returns each stage's
/// (stage, version, summary).
#[pyfunction]
fn solve(py: Python<'_>, store: &Store, argv: Vec<String>) -> PyResult<Vec<(String, Option<u64>, String)>> {
    let call = library_call(&argv).map_err(error)?;
    let LibraryCall::Solve(options) = call else {
        return Err(error("not a solve command line"));
    };
    let inner = store.inner.clone();
    py.detach(move || {
        let mut reports = Vec::new();
        octstore::pipeline::solve(&inner, &options, |r| reports.push(report_tuple(r))).map(|()| reports)
    })
    .map_err(error)
}

/// The demo's depth maps (`octstore demo`: a sphere on a box in a room, 16 noisy views with
/// 2 % outlier pixels) as (depths (N, H, W) float32, K (3, 3), camera_to_world (N, 4, 4)).
#[pyfunction]
#[expect(clippy::type_complexity, reason = "the three arrays Python receives as a tuple")]
fn demo_views(
    py: Python<'_>,
) -> PyResult<(
    Bound<'_, PyArray3<f32>>,
    Bound<'_, PyArray2<f64>>,
    Bound<'_, PyArray3<f64>>,
)> {
    let spec = octstore::SceneSpec::demo();
    let poses = spec.poses();
    let images: Vec<octstore::inputs::DepthImage> = py.detach(|| {
        poses
            .iter()
            .enumerate()
            .map(|(index, pose)| spec.render(index, pose))
            .collect()
    });
    let (n, h, w) = (images.len(), spec.height as usize, spec.width as usize);
    let depth: Vec<f32> = images.into_iter().flat_map(|image| image.depth).collect();
    let f = spec.focal();
    let k = vec![
        f,
        0.0,
        f64::from(spec.width) * 0.5,
        0.0,
        f,
        f64::from(spec.height) * 0.5,
        0.0,
        0.0,
        1.0,
    ];
    // glam is column-major; numpy rows are the matrix's rows.
    let pose_rows: Vec<f64> = poses.iter().flat_map(|p| p.transpose().to_cols_array()).collect();
    let shape_error = |e: PyErr| error(format!("demo arrays: {e}"));
    Ok((
        depth.into_pyarray(py).reshape([n, h, w]).map_err(shape_error)?,
        rows(py, k, 3, 3)?,
        pose_rows.into_pyarray(py).reshape([n, 4, 4]).map_err(shape_error)?,
    ))
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Store>()?;
    m.add_class::<Snapshot>()?;
    m.add_function(wrap_pyfunction!(ingest, m)?)?;
    m.add_function(wrap_pyfunction!(solve, m)?)?;
    m.add_function(wrap_pyfunction!(demo_views, m)?)?;
    m.add("OctstoreError", m.py().get_type::<OctstoreError>())?;
    Ok(())
}
