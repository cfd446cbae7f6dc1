//! What the benches share.

/// The setting `name` from the environment, parsed, or `default` when it is absent or does not
/// parse.
pub fn setting<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}
