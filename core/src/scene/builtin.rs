//! The scenes shipped in `scenes/`, compiled into the binary so `mwb demo` and tests need no
//! files on disk.

/// A few boxes of mixed sizes thrown onto a plane.
pub const TUMBLE: &str = include_str!("../../../scenes/tumble.toml");
/// Spheres and boxes dropped through a staggered peg board.
pub const PACHINKO: &str = include_str!("../../../scenes/pachinko.toml");
/// A 192-block tower hit by a fast sphere.
pub const TOWER: &str = include_str!("../../../scenes/tower.toml");
/// A marble rolling down ramps into a cup.
pub const CHUTE: &str = include_str!("../../../scenes/chute.toml");

/// Names accepted by [`get`], in a stable order.
pub const NAMES: &[&str] = &["tumble", "pachinko", "tower", "chute"];

/// The TOML source of a shipped scene by name (`"tower"`; a `.toml` suffix is accepted).
pub fn get(name: &str) -> Option<&'static str> {
    match name.strip_suffix(".toml").unwrap_or(name) {
        "tumble" => Some(TUMBLE),
        "pachinko" => Some(PACHINKO),
        "tower" => Some(TOWER),
        "chute" => Some(CHUTE),
        _ => None,
    }
}
