//! Deterministic pseudo-random numbers (splitmix64): the same seed gives the same synthetic
//! inputs, samples and noise on every machine.

/// The next splitmix64 output of `state`.
pub fn splitmix(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A uniform number in [0, 1) with 53 random bits.
pub fn uniform(state: &mut u64) -> f64 {
    (splitmix(state) >> 11) as f64 / (1u64 << 53) as f64
}

/// A standard normal number (Box-Muller, cosine branch).
pub fn gaussian(state: &mut u64) -> f64 {
    let u1 = uniform(state).max(1e-300);
    let u2 = uniform(state);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}
