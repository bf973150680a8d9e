//! A top-level bounding-volume hierarchy over the paths of one object index across all worlds,
//! so that a new constraint visits only the paths near its frustum instead of every world.
//!
//! §4.4.2 indexes each path with a shallow OBB tree; testing a constraint still touches every
//! world's tree. Here the box of every path (its root box, grown by the path's never-miss
//! radius) goes into an axis-aligned BVH per object index; a query walks it with the frustum's
//! planes and vertices and returns the worlds whose box may meet the frustum, which then get
//! the exact per-path test. Worlds that arrive after the last build wait in a pending list
//! (tested one by one) until it is a quarter of the built part, then the hierarchy is rebuilt:
//! ingest stays O(1) and queries stay O(paths near the frustum + pending).
//!
//! Each entry also keeps a copy of the path's root OBB and radius, and a query runs the root's
//! plane test on it right there, in the entries' contiguous memory: in a compact scene, where
//! the boxes of most paths overlap the frustum's, that test still rejects about half the paths
//! without touching their worlds (counted over `mwb bench query`'s tumble worlds), and for the
//! rest it hands over the planes the root box is wholly inside of, so the tree below need not
//! repeat it.

use mwb_core::browse::{ALL_PLANES, Frustum, Obb};

type Vec3 = [f64; 3];

/// An axis-aligned box.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Aabb {
    pub min: Vec3,
    pub max: Vec3,
}

impl Aabb {
    pub fn of_points(points: &[Vec3], grow: f64) -> Option<Aabb> {
        let first = *points.first()?;
        let mut b = Aabb {
            min: first,
            max: first,
        };
        for p in points {
            for (k, &v) in p.iter().enumerate() {
                b.min[k] = b.min[k].min(v);
                b.max[k] = b.max[k].max(v);
            }
        }
        // A hair more than `grow`, so rounding in the tests below can never lose a path.
        let pad = grow
            + 1e-9
                * (1.0
                    + b.max
                        .iter()
                        .chain(&b.min)
                        .fold(0.0f64, |m, v| m.max(v.abs())));
        for k in 0..3 {
            b.min[k] -= pad;
            b.max[k] += pad;
        }
        Some(b)
    }

    fn union(&self, o: &Aabb) -> Aabb {
        let mut b = *self;
        for k in 0..3 {
            b.min[k] = b.min[k].min(o.min[k]);
            b.max[k] = b.max[k].max(o.max[k]);
        }
        b
    }

    fn centre(&self, k: usize) -> f64 {
        0.5 * (self.min[k] + self.max[k])
    }

    /// True only if the box (a path's box grown by its radius `r`) provably holds no point of
    /// `frustum` inflated by `r`: one plane of `frustum` has the whole box outside (the box is
    /// grown by `r` along the axes, so this implies the same of the plane moved out by `r`), or
    /// the box misses `region_box` — the bounding box of the vertices of `frustum` inflated by
    /// at least every radius in the hierarchy (see [`region_box`]): a separating-axis test on
    /// the coordinate axes, which are the box's own.
    pub fn apart(&self, frustum: &Frustum, region_box: Option<&Aabb>) -> bool {
        let c = [self.centre(0), self.centre(1), self.centre(2)];
        let e = [
            0.5 * (self.max[0] - self.min[0]),
            0.5 * (self.max[1] - self.min[1]),
            0.5 * (self.max[2] - self.min[2]),
        ];
        let by_plane = frustum.planes().iter().any(|p| {
            let reach: f64 = (0..3).map(|k| p.normal[k].abs() * e[k]).sum();
            p.distance(c) > reach
        });
        by_plane
            || region_box
                .is_some_and(|r| (0..3).any(|k| r.min[k] > self.max[k] || r.max[k] < self.min[k]))
    }
}

/// The bounding box of `region`'s vertices, grown by a millionth of their scale (the vertex
/// set's own rounding); `None` when the region has no vertex set.
pub fn region_box(region: &Frustum) -> Option<Aabb> {
    let hull = region.hull()?;
    let mut b = Aabb::of_points(hull, 0.0)?;
    let size = b
        .min
        .iter()
        .chain(&b.max)
        .fold(0.0f64, |m, v| m.max(v.abs()));
    let margin = 1e-6 * (1.0 + size);
    for k in 0..3 {
        b.min[k] -= margin;
        b.max[k] += margin;
    }
    Some(b)
}

#[derive(Debug, Clone)]
struct Node {
    bounds: Aabb,
    /// Leaf: `entries[first..first + count]`; inner: children at `first` and `first + 1`.
    first: u32,
    count: u32,
}

/// Leaves hold at most this many paths.
const LEAF: usize = 8;

/// One path: its box grown by its radius, its tree's root box and radius, and its world.
#[derive(Debug, Clone)]
struct Entry {
    bounds: Aabb,
    root: Obb,
    /// The never-miss radius as [`Frustum::inflated`] uses it: ≥ 0, NaN taken as +∞.
    radius: f64,
    world: u32,
}

/// The paths of one object index across worlds.
#[derive(Debug, Clone, Default)]
pub struct PathBvh {
    /// In leaf order.
    entries: Vec<Entry>,
    nodes: Vec<Node>,
    pending: Vec<Entry>,
    /// The largest path radius inserted (never lowered on removal: only ever conservative).
    max_radius: f64,
}

impl PathBvh {
    /// Adds a world's path: `bounds` is its box grown by the path's never-miss `radius`,
    /// `root` its tree's root box (goes to the pending list; rebuilt in batches).
    pub fn insert(&mut self, bounds: Aabb, root: Obb, world: u32, radius: f64) {
        let radius = if radius.is_nan() {
            f64::INFINITY
        } else {
            radius.max(0.0)
        };
        self.max_radius = self.max_radius.max(radius);
        self.pending.push(Entry {
            bounds,
            root,
            radius,
            world,
        });
        if self.pending.len() >= 64 && self.pending.len() * 4 >= self.entries.len() {
            self.rebuild();
        }
    }

    /// Removes a world (rebuilds; worlds leave rarely).
    pub fn remove(&mut self, world: u32) {
        let before = self.entries.len() + self.pending.len();
        self.entries.retain(|e| e.world != world);
        self.pending.retain(|e| e.world != world);
        if self.entries.len() + self.pending.len() != before {
            self.rebuild();
        }
    }

    pub fn len(&self) -> usize {
        self.entries.len() + self.pending.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn heap_bytes(&self) -> usize {
        (self.entries.capacity() + self.pending.capacity()) * std::mem::size_of::<Entry>()
            + self.nodes.capacity() * std::mem::size_of::<Node>()
    }

    fn rebuild(&mut self) {
        self.entries.append(&mut self.pending);
        self.nodes.clear();
        if self.entries.is_empty() {
            return;
        }
        self.nodes.push(Node {
            bounds: self.entries[0].bounds,
            first: 0,
            count: 0,
        });
        let n = self.entries.len();
        self.build(0, 0, n);
    }

    /// Builds node `at` over `entries[lo..hi]`: median split on the widest axis of the centres.
    fn build(&mut self, at: usize, lo: usize, hi: usize) {
        let bounds = self.entries[lo + 1..hi]
            .iter()
            .fold(self.entries[lo].bounds, |b, e| b.union(&e.bounds));
        if hi - lo <= LEAF {
            self.nodes[at] = Node {
                bounds,
                first: lo as u32,
                count: (hi - lo) as u32,
            };
            return;
        }
        let (mut cmin, mut cmax) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        for e in &self.entries[lo..hi] {
            for k in 0..3 {
                cmin[k] = cmin[k].min(e.bounds.centre(k));
                cmax[k] = cmax[k].max(e.bounds.centre(k));
            }
        }
        let axis = (0..3)
            .max_by(|&a, &b| (cmax[a] - cmin[a]).total_cmp(&(cmax[b] - cmin[b])))
            .unwrap_or(0);
        let mid = lo + (hi - lo) / 2;
        self.entries[lo..hi].select_nth_unstable_by(mid - lo, |a, b| {
            a.bounds.centre(axis).total_cmp(&b.bounds.centre(axis))
        });
        let left = self.nodes.len();
        for _ in 0..2 {
            self.nodes.push(Node {
                bounds,
                first: 0,
                count: 0,
            });
        }
        self.nodes[at] = Node {
            bounds,
            first: left as u32,
            count: 0,
        };
        self.build(left, lo, mid);
        self.build(left + 1, mid, hi);
    }

    /// Calls `visit(world, mask)` for every world whose path may come within its radius of
    /// `frustum` (all pending ones included): never skips a world whose path the exact test on
    /// the inflated frustum would accept. `mask` is the root box's plane test against the
    /// frustum inflated by the path's radius ([`Obb::classify_inflated`] from
    /// [`ALL_PLANES`]), for [`PathTree::intersects_region_masked`](mwb_core::browse::PathTree::intersects_region_masked).
    pub fn query(&self, frustum: &Frustum, mut visit: impl FnMut(u32, u8)) {
        let region = region_box(&frustum.inflated_bounded(self.max_radius));
        let apart = |b: &Aabb| b.apart(frustum, region.as_ref());
        let mut leaf = |e: &Entry| {
            if !apart(&e.bounds)
                && let Some(mask) = e
                    .root
                    .classify_inflated(frustum.planes(), e.radius, ALL_PLANES)
            {
                visit(e.world, mask);
            }
        };
        if !self.nodes.is_empty() {
            let mut stack = vec![0usize];
            while let Some(i) = stack.pop() {
                let node = &self.nodes[i];
                if apart(&node.bounds) {
                    continue;
                }
                if node.count > 0 {
                    let (a, n) = (node.first as usize, node.count as usize);
                    self.entries[a..a + n].iter().for_each(&mut leaf);
                } else {
                    stack.push(node.first as usize + 1);
                    stack.push(node.first as usize);
                }
            }
        }
        self.pending.iter().for_each(&mut leaf);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mwb_core::rng::{Stream, WorldRng};

    /// Every box that truly overlaps the query box is visited, whatever the insertion order and
    /// the rebuild points; boxes far away are mostly not.
    #[test]
    fn query_returns_every_overlapping_box() {
        let mut rng = WorldRng::new(3, Stream::Scene);
        let mut bvh = PathBvh::default();
        let mut boxes = Vec::new();
        for w in 0..3000u32 {
            let c = [
                rng.uniform(-20.0, 20.0),
                rng.uniform(0.0, 5.0),
                rng.uniform(-20.0, 20.0),
            ];
            let h = [
                rng.uniform(0.01, 2.0),
                rng.uniform(0.01, 1.0),
                rng.uniform(0.01, 2.0),
            ];
            let b = Aabb {
                min: [c[0] - h[0], c[1] - h[1], c[2] - h[2]],
                max: [c[0] + h[0], c[1] + h[1], c[2] + h[2]],
            };
            boxes.push(b);
            let corners: Vec<Vec3> = (0..8)
                .map(|k| {
                    let pick = |i: usize| if k >> i & 1 == 1 { b.max[i] } else { b.min[i] };
                    [pick(0), pick(1), pick(2)]
                })
                .collect();
            bvh.insert(b, Obb::fit(&corners), w, 0.0);
        }
        bvh.remove(17);
        assert_eq!(bvh.len(), 2999);
        for _ in 0..200 {
            let c = [
                rng.uniform(-20.0, 20.0),
                rng.uniform(0.0, 5.0),
                rng.uniform(-20.0, 20.0),
            ];
            let h = rng.uniform(0.1, 4.0);
            let q = Frustum::aabb(
                [c[0] - h, c[1] - h, c[2] - h],
                [c[0] + h, c[1] + h, c[2] + h],
            )
            .unwrap_or_else(|e| panic!("{e}"));
            let mut seen = std::collections::BTreeSet::new();
            bvh.query(&q, |w, _| {
                seen.insert(w);
            });
            let mut truth = 0;
            for (w, b) in boxes.iter().enumerate() {
                let overlap = (0..3).all(|k| b.min[k] <= c[k] + h && b.max[k] >= c[k] - h);
                if overlap && w != 17 {
                    truth += 1;
                    assert!(seen.contains(&(w as u32)), "box {w} missed");
                }
            }
            // Boxes and queries are both axis-aligned here, so the test is exact.
            assert_eq!(seen.len(), truth);
            assert!(!seen.contains(&17));
        }
    }
}
