//! The solver's parameters: the TGV weights, the data term's weight and when a unit's
//! iterations stop.

use serde::{Deserialize, Serialize};

/// Solver parameters, recorded with every level's run. alpha1 and alpha0 multiply h and h^2
/// (h the cube side, in units of the root side), which makes the result invariant to the
/// scene's scale; v is likewise in units of 1 / root side.
///
/// lambda is 0.5: at 0.1 the data term of a cube that only a few depth maps see (3 or 4 votes,
/// the usual count on a floor seen at a slant) was too weak against the regulariser, and u's
/// zero set sat up to 3.5 finest cubes off the measured surface; extraction, which keeps only
/// surface near samples, then tore holes there. 0.5 follows such surfaces and is as robust to
/// outliers (BENCHMARKS.md, "Ground truth").
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq)]
pub struct SolveParams {
    /// TGV's weight on the first-order term |grad u - v| (the paper's alpha_1).
    pub alpha1: f32,
    /// TGV's weight on the second-order term |e(v)| (the paper's alpha_0).
    pub alpha0: f32,
    /// The data term's weight against the regulariser (the paper's lambda).
    pub lambda: f32,
    /// The most primal-dual iterations a unit runs at each level.
    pub iterations: u32,
    /// A unit stops early at the first check where its energy moved by at most this fraction
    /// since the check before (`crate::kernels::tgv::Stopping`); 0 runs every iteration.
    pub tolerance: f32,
}

/// The default stopping tolerance (see [`SolveParams::tolerance`]).
pub const DEFAULT_TOLERANCE: f32 = 1e-4;

impl Default for SolveParams {
    fn default() -> Self {
        SolveParams {
            alpha1: 1.0,
            alpha0: 2.0,
            lambda: 0.5,
            iterations: 200,
            tolerance: DEFAULT_TOLERANCE,
        }
    }
}

impl SolveParams {
    /// When each unit's iterations stop.
    pub(crate) fn stopping(&self) -> crate::kernels::tgv::Stopping {
        crate::kernels::tgv::Stopping {
            max_iterations: self.iterations as usize,
            tolerance: f64::from(self.tolerance),
        }
    }
}

/// Which energy a solve minimises on the level cuts (docs/parameters.md, "Solvers").
#[derive(Serialize, Deserialize, Clone, Copy, Debug, Default, PartialEq)]
pub enum Method {
    /// TGV with the histogram data term (the paper's method): robust to outliers.
    #[default]
    Tgv,
    /// Smooth signed distance (`kernels::ssd`): the samples' positions and normals, with
    /// sub-cube accuracy on clean data.
    Ssd(SsdParams),
    /// SSD whose samples count only in cubes where the histograms' votes measured a surface
    /// (`stages::solve::ssd::evidence`): outliers in space the depth maps saw as free or as
    /// hidden behind a surface pull nothing, as under TGV.
    Hybrid(SsdParams),
}

impl Method {
    /// The method's name on the command line.
    pub fn name(&self) -> &'static str {
        match self {
            Method::Tgv => "tgv",
            Method::Ssd(_) => "ssd",
            Method::Hybrid(_) => "hybrid",
        }
    }

    /// The SSD parameters of `ssd` and `hybrid`.
    pub fn ssd(&self) -> Option<&SsdParams> {
        match self {
            Method::Tgv => None,
            Method::Ssd(params) | Method::Hybrid(params) => Some(params),
        }
    }
}

/// Which solver `solve` runs, as asked for: `--method`, or the default's decision from the
/// capture.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum MethodChoice {
    /// SSD with these parameters for an object seen against empty background, TGV for a scene
    /// ([`MethodChoice::resolve`]).
    Auto(SsdParams),
    /// This method, whatever the capture.
    Exactly(Method),
}

impl Default for MethodChoice {
    fn default() -> Self {
        MethodChoice::Auto(SsdParams::default())
    }
}

impl From<Method> for MethodChoice {
    fn from(method: Method) -> MethodChoice {
        MethodChoice::Exactly(method)
    }
}

impl MethodChoice {
    /// The method to run at `snapshot`: the one asked for, or for `Auto` SSD when the capture
    /// is an object against empty background (`stages::capture`), else TGV.
    ///
    /// Why: such an object is closed, and every part of it that no map measured (its crevices,
    /// its underside) lies inside the background's free space. SSD fits one smooth implicit
    /// surface to the samples' positions and normals and closes those parts as the surface
    /// around them continues; TGV's histograms there hold only the votes from the occluded
    /// band behind nearby surfaces (eta, 18 sample radii deep, the paper's choice), which in
    /// narrow gaps outvote the few rays that pass through and leave webs and shards. A scene
    /// has space behind its walls that no map saw, where SSD would extrapolate surface and
    /// TGV's robust data term keeps it honest. docs/parameters.md, "Solvers", has the figures.
    pub fn resolve(self, snapshot: &crate::store::Snapshot<'_>) -> crate::store::Result<Method> {
        Ok(match self {
            MethodChoice::Exactly(method) => method,
            MethodChoice::Auto(ssd) => {
                let capture = crate::stages::capture::Capture::of(snapshot, "solve")?;
                let method = if capture.is_object() {
                    Method::Ssd(ssd)
                } else {
                    Method::Tgv
                };
                tracing::info!(
                    "solve: {}: the {} solver{}",
                    capture.describe(),
                    method.name(),
                    if capture.is_object() {
                        " (an object: --method tgv for the paper's)"
                    } else {
                        " (a scene: --method ssd for smooth signed distance)"
                    }
                );
                method
            }
        })
    }
}

/// The SSD solver's default residual target. 1e-3 rather than 1e-4: each level starts from
/// the coarser level's f, so the finest levels need far fewer iterations to place the surface
/// (RedKitchen's finest level 22 per cube instead of 36, `solve` about 8 % faster), and on the
/// groundtruth bunny and dragon the meshes moved by at most 2 % in Chamfer distance, except for
/// the bunny at 1 % depth noise without outliers (5 %; docs/parameters.md, "Solvers").
pub const DEFAULT_SSD_TOLERANCE: f64 = 1e-3;

/// The SSD solver's weights and when its conjugate gradients stop.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq)]
pub struct SsdParams {
    /// lambda1, relative to the position term (`kernels::ssd`).
    pub normal_weight: f64,
    /// lambda2, relative to the position term.
    pub smoothness: f64,
    /// A unit stops when its residual |A f - b| is at most this fraction of |b|.
    pub tolerance: f64,
    /// The most conjugate-gradient iterations a unit runs at each level.
    pub iterations: u32,
}

impl Default for SsdParams {
    fn default() -> Self {
        SsdParams {
            normal_weight: crate::kernels::ssd::DEFAULT_NORMAL_WEIGHT,
            smoothness: crate::kernels::ssd::DEFAULT_SMOOTHNESS,
            tolerance: DEFAULT_SSD_TOLERANCE,
            iterations: 500,
        }
    }
}
