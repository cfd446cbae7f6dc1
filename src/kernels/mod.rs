//! CPU reference kernels that need no store: the TGV solver on one unit ([`tgv`]), the smooth
//! signed distance solver on one unit ([`ssd`]), the
//! histogram vote math ([`votes`]) and its occlusion culling ([`occlusion`]), and the deterministic random numbers of the synthetic
//! inputs ([`random`]). The GPU engine (`gpu`) runs twins of `tgv` and `votes` and tests
//! against them; stages call them on what they read from the store.

pub mod background;
pub mod halving;
pub mod occlusion;
pub mod random;
pub mod ssd;
pub mod surface_depth;
pub mod tgv;
pub mod vote_batches;
pub mod vote_lanes;
pub mod votes;
