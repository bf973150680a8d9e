//! Generators: one body template repeated on a grid, along a row, or as a stack of turned
//! layers, so that a 192-block tower is a few lines of TOML.
//!
//! A generator's layout (counts, spacing, turn) is fixed; only the template's own fields are
//! sampled, independently for every instance. The template's `position` is the position of
//! instance 0 (for `stack`, the centre of the bottom layer), so a distribution there jitters
//! every instance separately.

use super::model::{IDENTITY, Quat, Vec3};
use super::template::{axis_angle, rotate};

/// Most bodies plus statics one scene may expand to: a guard against a typo such as
/// `count = [400, 1200, 400]` allocating without bound.
pub const MAX_INSTANCES: u64 = 100_000;

/// Where one instance of a template goes, relative to the template's sampled pose.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Placement {
    /// `name` for a single body, `name[i]`, `name[i,j]` or `name[i,j,k]` for generated ones.
    pub name: String,
    /// Added to the sampled `position`.
    pub offset: Vec3,
    /// Applied after the sampled rotation (world frame): the layer turn of a stack.
    pub turn: Quat,
}

/// The layout of a `[[body]]` / `[[static]]` entry.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Layout {
    /// A single body (no generator key).
    Single,
    /// `grid = { count = [nx, ny, nz], spacing = [sx, sy, sz] }`: instance `[i,j,k]` at
    /// `(i·sx, j·sy, k·sz)`.
    Grid { count: [u32; 3], spacing: Vec3 },
    /// `row = { count = n, spacing = [dx, dy, dz] }`: instance `[i]` at `i·spacing`.
    Row { count: u32, spacing: Vec3 },
    /// `stack = { layers, per_layer, spacing, layer_height, turn_deg }`: layer `l` holds
    /// `per_layer` instances `[l,i]` side by side along x, centred, spaced `spacing`, raised
    /// `l·layer_height`, and the whole layer turned `l·turn_deg` about +y (90° by default: the
    /// alternating courses of a block tower).
    Stack {
        layers: u32,
        per_layer: u32,
        spacing: f64,
        layer_height: f64,
        turn_deg: f64,
    },
}

impl Layout {
    /// Number of instances, saturating (the caller compares it with [`MAX_INSTANCES`]).
    pub fn count(&self) -> u64 {
        match self {
            Layout::Single => 1,
            Layout::Grid {
                count: [a, b, c], ..
            } => u64::from(*a)
                .saturating_mul(u64::from(*b))
                .saturating_mul(u64::from(*c)),
            Layout::Row { count, .. } => u64::from(*count),
            Layout::Stack {
                layers, per_layer, ..
            } => u64::from(*layers).saturating_mul(u64::from(*per_layer)),
        }
    }

    /// All placements in index order (last index fastest). Call only after checking
    /// [`Layout::count`] against [`MAX_INSTANCES`].
    pub fn placements(&self, name: &str) -> Vec<Placement> {
        let mut out = Vec::with_capacity(usize::try_from(self.count()).unwrap_or(0));
        match self {
            Layout::Single => out.push(Placement {
                name: name.to_owned(),
                offset: [0.0; 3],
                turn: IDENTITY,
            }),
            Layout::Grid {
                count: [nx, ny, nz],
                spacing: s,
            } => {
                for i in 0..*nx {
                    for j in 0..*ny {
                        for k in 0..*nz {
                            out.push(Placement {
                                name: format!("{name}[{i},{j},{k}]"),
                                offset: [
                                    f64::from(i) * s[0],
                                    f64::from(j) * s[1],
                                    f64::from(k) * s[2],
                                ],
                                turn: IDENTITY,
                            });
                        }
                    }
                }
            }
            Layout::Row { count, spacing: s } => {
                for i in 0..*count {
                    let t = f64::from(i);
                    out.push(Placement {
                        name: format!("{name}[{i}]"),
                        offset: [t * s[0], t * s[1], t * s[2]],
                        turn: IDENTITY,
                    });
                }
            }
            Layout::Stack {
                layers,
                per_layer,
                spacing,
                layer_height,
                turn_deg,
            } => {
                let centre = 0.5 * (f64::from(*per_layer) - 1.0);
                for l in 0..*layers {
                    let turn_deg = (f64::from(l) * turn_deg) % 360.0;
                    let turn = axis_angle([0.0, 1.0, 0.0], turn_deg.to_radians());
                    for i in 0..*per_layer {
                        let across = rotate(turn, [(f64::from(i) - centre) * spacing, 0.0, 0.0]);
                        out.push(Placement {
                            name: format!("{name}[{l},{i}]"),
                            offset: [across[0], f64::from(l) * layer_height, across[2]],
                            turn,
                        });
                    }
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_names_and_offsets_in_index_order() {
        let g = Layout::Grid {
            count: [2, 3, 2],
            spacing: [1.0, 2.0, 3.0],
        };
        let p = g.placements("b");
        assert_eq!(p.len(), 12);
        assert_eq!(p[0].name, "b[0,0,0]");
        assert_eq!(p[1].name, "b[0,0,1]");
        assert_eq!(p[11].name, "b[1,2,1]");
        assert_eq!(p[11].offset, [1.0, 4.0, 3.0]);
    }

    #[test]
    fn stack_alternates_layers() {
        let g = Layout::Stack {
            layers: 2,
            per_layer: 3,
            spacing: 0.25,
            layer_height: 0.15,
            turn_deg: 90.0,
        };
        let p = g.placements("j");
        assert_eq!(p.len(), 6);
        assert_eq!(p[0].name, "j[0,0]");
        assert!((p[0].offset[0] + 0.25).abs() < 1e-12);
        assert_eq!(p[1].offset, [0.0, 0.0, 0.0]);
        // Layer 1 is turned 90° about +y: its row runs along z and it sits one layer up.
        assert!(p[3].offset[0].abs() < 1e-12);
        assert!((p[3].offset[2].abs() - 0.25).abs() < 1e-12);
        assert!((p[3].offset[1] - 0.15).abs() < 1e-12);
        let s = std::f64::consts::FRAC_1_SQRT_2;
        assert!((p[3].turn[1] - s).abs() < 1e-12 && (p[3].turn[3] - s).abs() < 1e-12);
    }
}
