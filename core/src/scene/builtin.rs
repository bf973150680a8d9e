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

/// A synthetic scene of `bodies` small boxes, each its own `[[body]]` table (no generator: the
/// file an exporter from a modelling tool writes), placed 100 × 100 to a layer. For measuring
/// the parser on big files (`mwb bench scene`) and testing it; at most
/// [`MAX_INSTANCES`](super::MAX_INSTANCES) bodies make a valid scene. About 120 bytes a body.
pub fn many_bodies(bodies: usize) -> String {
    use std::fmt::Write as _;
    let mut s = String::with_capacity(64 + bodies * 128);
    s.push_str("name = \"many_bodies\"\n\n[[material]]\nname = \"wood\"\n");
    for i in 0..bodies {
        let (x, y, z) = (i % 100, i / 10_000, (i / 100) % 100);
        // Writing to a String cannot fail.
        let _ = write!(
            s,
            "\n[[body]]\nname = \"b{i}\"\nshape = \"box\"\nsize = [0.1, 0.1, 0.1]\n\
             material = \"wood\"\nposition = [{x}, {y}, {z}]\n"
        );
    }
    s
}
