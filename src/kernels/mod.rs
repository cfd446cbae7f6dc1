//! CPU reference kernels that need no store: the TGV solver on one unit ([`tgv`]), the smooth
//! signed distance solver on one unit ([`ssd`]), the
//! histogram vote math ([`votes`]) and its occlusion culling ([`occlusion`]), and the deterministic random numbers of the synthetic
//! inputs ([`random`]). The GPU engine (`gpu`) runs twins of `tgv` and `votes` and tests
//! against them; stages call them on what they read from the store.

// A private layer: its `pub` items are the crate's own API and, with the `testing` feature, its
// integration tests' and benches' (`octstore::testing`). Some exist only for those (reference
// kernels, the GPU tests' reading helpers), so a build without the feature sees them unused.
#![cfg_attr(not(feature = "testing"), allow(dead_code, unused_imports))]
// `octstore::testing` is not the documented public surface: its items need no docs there.
#![cfg_attr(feature = "testing", allow(missing_docs))]

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
