//! A bounding-volume hierarchy over the path *pieces* of one object index across all worlds, so
//! that a new constraint visits only the parts of paths near its frustum instead of every world.
//!
//! §4.4.2 indexes each path with a shallow OBB tree; testing a constraint still touches every
//! world's tree, and in a compact scene (every world throws the same boxes at the same spot)
//! nearly every path's box meets a frustum drawn through the scene. A frustum is thin, though,
//! and most of a path is far from it. So each path enters the hierarchy as pieces of
//! [`PIECE_SEGMENTS`] segments: per piece the box of its vertices grown by the path's
//! never-miss radius (f32, rounded outward), its time range, its world and which segments it
//! covers; the exact test ([`segment_entry`](mwb_core::browse::segment_entry), the same
//! function brute force runs) reads them from the world's [`IndexedObject`]. A query walks the hierarchy with the frustum's planes — plane masking as in the
//! trees: a node wholly inside a plane spares everything below it that plane — and the
//! bounding box of the inflated frustum's vertices, skips pieces whose time range misses the
//! window, and clips the segments of the pieces that remain. A path's last piece reaches to
//! +∞ in time: its world has ended and the body stays at its final pose, which the piece's box
//! holds (it is the last vertex), so windows past the end still reach it
//! ([`rest_entry`](mwb_core::browse::rest_entry)).
//!
//! The work of one query comes in [`Part`]s (subtrees near the top, runs of the pending list)
//! that threads take one at a time. Pieces that arrive after the last build wait in a pending
//! list (tested one by one) until it is a quarter of the built part, then the hierarchy is
//! rebuilt: ingest stays amortised O(log n) per piece and queries O(pieces near the frustum +
//! pending). The pieces used to carry f64 copies of their vertices (no lookup into the world
//! for a surviving piece), at 232 bytes a piece the largest part of the store; they refer to
//! the one compact copy now (see docs/performance.md for what that costs a query).

use crate::index::IndexedObject;
use mwb_core::browse::{ALL_PLANES, Frustum, Plane, TimeWindow};

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

    /// The plane test of Assarsson and Möller on a box grown by a path's radius `r`, against
    /// the planes of a frustum in `mask` (bit k = plane k). `None`: one plane has the whole box
    /// outside; since the box holds every path point grown by `r` along each axis, every point
    /// is then more than `r` outside that plane, i.e. outside the frustum inflated by `r`.
    /// Otherwise the planes the whole box is inside of (with a margin far above rounding) are
    /// cleared from the returned mask: every path point is then more than `r` inside them, so
    /// segments clipped against the inflated frustum need not test them again.
    pub fn classify(&self, planes: &[Plane; 6], mask: u8) -> Option<u8> {
        let mut out = mask;
        for (k, p) in planes.iter().enumerate() {
            if mask & (1 << k) == 0 {
                continue;
            }
            // Signed distances of the corner nearest to the inside (`near`) and of the one
            // farthest out (`far`): n·x is smallest at min where n ≥ 0, at max elsewhere.
            let (mut near, mut far) = (-p.offset, -p.offset);
            for i in 0..3 {
                let n = p.normal[i];
                let (lo, hi) = if n >= 0.0 {
                    (self.min[i], self.max[i])
                } else {
                    (self.max[i], self.min[i])
                };
                near += n * lo;
                far += n * hi;
            }
            if near > 0.0 {
                return None;
            }
            if far < -1e-9 * (1.0 + p.offset.abs() + far.abs()) {
                out &= !(1 << k);
            }
        }
        Some(out)
    }

    /// Whether the two boxes are disjoint (a separating-axis test on the coordinate axes).
    fn disjoint(&self, o: &Aabb) -> bool {
        (0..3).any(|k| o.min[k] > self.max[k] || o.max[k] < self.min[k])
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

/// Leaves hold at most this many pieces.
const LEAF: usize = 16;

/// Segments per piece: a path enters the hierarchy as runs of this many segments, each with its
/// own box, so that a query reaches the parts of a path near the frustum rather than whole
/// paths (in a compact scene nearly every path's box meets a frustum drawn through it, but few
/// of its pieces do). Measured with `mwb bench query` (see docs/performance.md).
pub const PIECE_SEGMENTS: usize = 4;

/// One piece of a path: the box of its vertices grown by the path's radius (f32, rounded
/// outward), its world, and which segments of the path it covers. The vertices themselves stay
/// in the world's [`IndexedObject`] (the store's only copy of them): a query looks the object
/// up for the few pieces whose box meets the frustum. 44 bytes, against 232 when each piece
/// carried f64 copies of its vertices and times (`mwb bench query`, docs/performance.md).
#[derive(Debug, Clone)]
struct Entry {
    min: [f32; 3],
    max: [f32; 3],
    /// The piece's time range, rounded outward to f32; `t1` is +∞ for a path's last piece (the
    /// final pose is held after the end). Windows that miss it skip the piece unseen.
    t0: f32,
    t1: f32,
    world: u32,
    /// First segment of the path in the piece.
    first: u32,
    /// Segments in the piece, 1..=[`PIECE_SEGMENTS`].
    count: u8,
    /// Whether the piece ends the path: its last vertex is the final pose, held after the end.
    last: bool,
}

/// `v` rounded down (`up` false) or up to an f32, so that a box stored in f32 still holds
/// every point the f64 box held.
fn f32_outward(v: f64, up: bool) -> f32 {
    let f = v as f32;
    match (up, f64::from(f).partial_cmp(&v)) {
        (true, Some(std::cmp::Ordering::Less)) => f.next_up(),
        (false, Some(std::cmp::Ordering::Greater)) => f.next_down(),
        _ => f,
    }
}

impl Entry {
    fn bounds(&self) -> Aabb {
        Aabb {
            min: self.min.map(f64::from),
            max: self.max.map(f64::from),
        }
    }
}

/// A piece that may meet the frustum, as a query hands it over.
#[derive(Debug, Clone, Copy)]
pub struct Piece<'a> {
    entry: &'a Entry,
    /// Planes still to clip against (bit k = plane k): the piece's box is wholly inside the
    /// others, by more than the radius.
    mask: u8,
}

impl Piece<'_> {
    /// The world whose path this is a piece of.
    pub fn world(&self) -> u32 {
        self.entry.world
    }

    /// Whether this piece ends its path (and so holds the final pose).
    pub fn is_last(&self) -> bool {
        self.entry.last
    }

    /// Whether the piece's box (grown by the radius) is inside every plane: then every point of
    /// the piece is inside the inflated frustum, and without a time window the exact test
    /// answers "inside" from its first segment — the caller need not read the path.
    pub fn inside_all(&self) -> bool {
        self.mask == 0
    }

    /// The exact test ([`segment_entry`](mwb_core::browse::segment_entry), as brute force runs
    /// it) of the piece's segments of `path` — the world's object this piece was cut from —
    /// against `region` — the query's frustum inflated by the path's radius — during `window`,
    /// then, for a path's last piece, of the final pose held after the end: the earliest time
    /// inside, if any.
    pub fn first_entry(
        &self,
        path: &IndexedObject,
        region: &Frustum,
        window: Option<TimeWindow>,
    ) -> Option<f64> {
        path.entry_in(
            self.entry.first as usize,
            usize::from(self.entry.count),
            self.entry.last,
            region,
            self.mask,
            window,
        )
    }

    /// Whether the piece ends its path and the path's final pose is inside `region` (the
    /// query's frustum inflated by the path's radius).
    pub fn final_pose_inside(&self, path: &IndexedObject, region: &Frustum) -> bool {
        let (p, _) = path.vertex(path.len() - 1);
        self.entry.last
            && region
                .clip_segment_masked(p, p, 0.0, 1.0, self.mask)
                .is_some()
    }
}

/// A share of a query's work: a subtree of the hierarchy, or a run of the pending pieces.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Part {
    Subtree(u32),
    Pending { start: u32, end: u32 },
}

/// The hierarchy over the path pieces of one object index.
#[derive(Debug, Clone, Default)]
pub struct PathBvh {
    /// Built part, in hierarchy order.
    entries: Vec<Entry>,
    nodes: Vec<Node>,
    /// Inserted since the last build.
    pending: Vec<Entry>,
    /// Largest radius inserted (for the vertex box of the inflated frustum).
    max_radius: f64,
}

impl PathBvh {
    /// Adds `world`'s path with its never-miss radius (NaN: unknown, taken as +∞, so the path is
    /// never pruned), cut into pieces of [`PIECE_SEGMENTS`] segments. A one-vertex path is one
    /// degenerate segment, as [`IndexedObject::segment_count`] counts it.
    pub fn insert(&mut self, world: u32, path: &IndexedObject) {
        let radius = if path.radius.is_nan() {
            f64::INFINITY
        } else {
            path.radius.max(0.0)
        };
        self.max_radius = self.max_radius.max(radius);
        let segments = path.segment_count();
        let mut span = Vec::with_capacity(PIECE_SEGMENTS + 1);
        for first in (0..segments).step_by(PIECE_SEGMENTS) {
            let count = PIECE_SEGMENTS.min(segments - first);
            span.clear();
            span.extend((first..=first + count).map(|i| path.vertex(i).0));
            let Some(b) = Aabb::of_points(&span, radius) else {
                continue;
            };
            let last = first + count >= segments;
            self.pending.push(Entry {
                min: b.min.map(|v| f32_outward(v, false)),
                max: b.max.map(|v| f32_outward(v, true)),
                t0: f32_outward(path.vertex(first).1, false),
                t1: if last {
                    f32::INFINITY
                } else {
                    f32_outward(path.vertex(first + count).1, true)
                },
                world,
                first: first as u32,
                count: count as u8,
                last,
            });
        }
        if self.pending.len() >= 256 && self.pending.len() * 4 >= self.entries.len() {
            self.rebuild();
        }
    }

    /// Removes every piece of `world`.
    pub fn remove(&mut self, world: u32) {
        let before = self.entries.len() + self.pending.len();
        self.entries.retain(|e| e.world != world);
        self.pending.retain(|e| e.world != world);
        if self.entries.len() + self.pending.len() != before {
            self.rebuild();
        }
    }

    /// Pieces held.
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

    /// Largest radius of any piece inserted: a query's `region_box` must bound the frustum
    /// inflated by at least this.
    pub fn max_radius(&self) -> f64 {
        self.max_radius
    }

    fn rebuild(&mut self) {
        self.entries.append(&mut self.pending);
        self.nodes.clear();
        if self.entries.is_empty() {
            return;
        }
        self.nodes.push(Node {
            bounds: self.entries[0].bounds(),
            first: 0,
            count: 0,
        });
        let n = self.entries.len();
        self.build(0, 0, n);
        // Rebuilds are rare (the pending list must reach a quarter of the built part), so the
        // spare room of the vectors' doubling is given back each time.
        self.entries.shrink_to_fit();
        self.nodes.shrink_to_fit();
        self.pending.shrink_to_fit();
    }

    /// Builds node `at` over `entries[lo..hi]`: median split along the longest axis of the
    /// entries' centres.
    fn build(&mut self, at: usize, lo: usize, hi: usize) {
        let bounds = self.entries[lo + 1..hi]
            .iter()
            .fold(self.entries[lo].bounds(), |b, e| b.union(&e.bounds()));
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
                let c = e.bounds().centre(k);
                cmin[k] = cmin[k].min(c);
                cmax[k] = cmax[k].max(c);
            }
        }
        let axis = (0..3)
            .max_by(|&a, &b| (cmax[a] - cmin[a]).total_cmp(&(cmax[b] - cmin[b])))
            .unwrap_or(0);
        let mid = lo + (hi - lo) / 2;
        self.entries[lo..hi].select_nth_unstable_by(mid - lo, |a, b| {
            a.bounds().centre(axis).total_cmp(&b.bounds().centre(axis))
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

    /// The whole hierarchy as at least `at_least` shares where it is big enough (subtrees near
    /// the top, then runs of up to 256 pending pieces), for threads to take one at a time.
    pub fn parts(&self, at_least: usize) -> Vec<Part> {
        let mut level: Vec<u32> = if self.nodes.is_empty() {
            vec![]
        } else {
            vec![0]
        };
        while level.len() < at_least {
            let mut next = Vec::with_capacity(2 * level.len());
            let mut split = false;
            for &i in &level {
                let n = &self.nodes[i as usize];
                if n.count == 0 {
                    next.extend([n.first, n.first + 1]);
                    split = true;
                } else {
                    next.push(i);
                }
            }
            level = next;
            if !split {
                break;
            }
        }
        let mut parts: Vec<Part> = level.into_iter().map(Part::Subtree).collect();
        let n = self.pending.len() as u32;
        parts.extend((0..n).step_by(256).map(|start| Part::Pending {
            start,
            end: (start + 256).min(n),
        }));
        parts
    }

    /// Calls `visit` with every piece in `part` that may hold a point inside `frustum` inflated
    /// by its path's radius during `window`, except the pieces of worlds `skip` names (e.g.
    /// worlds already found, looked up before the piece's box is tested). A piece is passed
    /// over only when its time range misses the window, when one plane has its whole box
    /// outside ([`Aabb::classify`], with plane masking down the hierarchy: a node inside a
    /// plane spares everything below it that plane), or when its box misses `region_box`
    /// ([`region_box`] of the frustum inflated by [`max_radius`](Self::max_radius) or more).
    pub fn query(
        &self,
        part: Part,
        frustum: &Frustum,
        region_box: Option<&Aabb>,
        window: Option<TimeWindow>,
        skip: impl Fn(u32) -> bool,
        mut visit: impl FnMut(Piece<'_>),
    ) {
        let planes = frustum.planes();
        let test = |b: &Aabb, mask: u8| {
            if region_box.is_some_and(|r| b.disjoint(r)) {
                return None;
            }
            b.classify(planes, mask)
        };
        let mut leaf = |entry: &Entry, mask: u8| {
            if window
                .is_some_and(|w| f64::from(entry.t1) < w.start() || f64::from(entry.t0) > w.end())
                || skip(entry.world)
            {
                return;
            }
            if let Some(mask) = test(&entry.bounds(), mask) {
                visit(Piece { entry, mask });
            }
        };
        match part {
            Part::Subtree(root) => {
                if self.nodes.get(root as usize).is_none() {
                    return;
                }
                let mut stack = vec![(root as usize, ALL_PLANES)];
                while let Some((i, mask)) = stack.pop() {
                    let node = &self.nodes[i];
                    let Some(mask) = test(&node.bounds, mask) else {
                        continue;
                    };
                    if node.count > 0 {
                        let (a, n) = (node.first as usize, node.count as usize);
                        for e in &self.entries[a..a + n] {
                            leaf(e, mask);
                        }
                    } else {
                        stack.push((node.first as usize + 1, mask));
                        stack.push((node.first as usize, mask));
                    }
                }
            }
            Part::Pending { start, end } => {
                let end = (end as usize).min(self.pending.len());
                for e in self.pending.get(start as usize..end).unwrap_or_default() {
                    leaf(e, ALL_PLANES);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mwb_core::browse::Polyline;
    use mwb_core::rng::{Stream, WorldRng};
    use std::collections::BTreeSet;

    const DT: f64 = 1.0 / 120.0;

    /// Random-walk paths of 1 to 40 vertices on a 120 Hz frame grid, radii from 0 to 5 cm (one
    /// unknown, NaN), stored as the index stores them.
    fn paths(rng: &mut WorldRng, n: u32) -> Vec<IndexedObject> {
        (0..n)
            .map(|i| {
                let mut p = [
                    rng.uniform(-10.0, 10.0),
                    rng.uniform(0.0, 3.0),
                    rng.uniform(-10.0, 10.0),
                ];
                let (mut times, mut points) = (Vec::new(), Vec::new());
                let mut frame = (rng.uniform(0.0, 120.0)) as u32;
                for _ in 0..1 + i % 40 {
                    times.push(f64::from(frame) * DT);
                    points.push(p);
                    frame += 1 + rng.uniform(0.0, 36.0) as u32;
                    for v in &mut p {
                        *v += rng.uniform(-0.4, 0.4);
                    }
                }
                let radius = if i == 77 {
                    f64::NAN
                } else {
                    rng.uniform(0.0, 0.05)
                };
                let path = Polyline::new(times, points).unwrap_or_else(|e| panic!("{e}"));
                IndexedObject::new(&path, DT, radius).unwrap_or_else(|e| panic!("{e}"))
            })
            .collect()
    }

    /// The worlds whose pieces, handed over by the query of `parts`, pass the exact test; and
    /// every handed-over piece's mask is checked: a cleared plane has each vertex more than
    /// the radius inside it.
    fn touched(
        bvh: &PathBvh,
        parts: &[Part],
        frustum: &Frustum,
        window: Option<TimeWindow>,
        paths: &[IndexedObject],
    ) -> BTreeSet<u32> {
        let region = region_box(&frustum.inflated_bounded(bvh.max_radius()));
        let mut hits = BTreeSet::new();
        for &part in parts {
            bvh.query(
                part,
                frustum,
                region.as_ref(),
                window,
                |_| false,
                |p| {
                    let path = &paths[p.world() as usize];
                    for (k, plane) in frustum.planes().iter().enumerate() {
                        if p.mask & (1 << k) == 0 {
                            let first = p.entry.first as usize;
                            for i in first..=first + usize::from(p.entry.count) {
                                let (v, _) = path.vertex(i);
                                let d = plane.distance(v);
                                assert!(d < -path.radius, "plane {k}: vertex {v:?} at {d}");
                            }
                        }
                    }
                    let inflated = frustum.inflated(path.radius);
                    if p.first_entry(path, &inflated, window).is_some() {
                        hits.insert(p.world());
                    }
                },
            );
        }
        hits
    }

    /// Pieces, hierarchy pruning (planes with masking, vertex box, time ranges) and the exact
    /// test on the entries' own copies of the vertices keep exactly the worlds a
    /// segment-by-segment test of the whole path against the inflated frustum keeps — whatever
    /// the insertion order, the rebuild points, a removal, and however the work is split.
    #[test]
    fn pieces_keep_exactly_the_worlds_brute_force_keeps() {
        let mut rng = WorldRng::new(3, Stream::Scene);
        let paths = paths(&mut rng, 3000);
        let mut bvh = PathBvh::default();
        // A removal rebuilds; the last paths then wait in the pending list.
        for (w, path) in paths.iter().enumerate() {
            if w == 2950 {
                bvh.remove(17);
            }
            bvh.insert(w as u32, path);
        }
        let pieces: usize = paths
            .iter()
            .enumerate()
            .filter(|(w, _)| *w != 17)
            .map(|(_, p)| p.segment_count().div_ceil(PIECE_SEGMENTS))
            .sum();
        assert_eq!(bvh.len(), pieces);
        assert!(
            !bvh.pending.is_empty() && !bvh.nodes.is_empty(),
            "both halves are tested"
        );
        let splits = [bvh.parts(1), bvh.parts(5), bvh.parts(64)];
        assert!(splits[2].len() >= 64);
        let (mut kept, mut windowed) = (0, 0);
        for q in 0..300 {
            let c = [
                rng.uniform(-10.0, 10.0),
                rng.uniform(0.0, 3.0),
                rng.uniform(-10.0, 10.0),
            ];
            let h = [
                rng.uniform(0.01, 3.0),
                rng.uniform(0.01, 1.0),
                rng.uniform(0.01, 3.0),
            ];
            let frustum = Frustum::aabb(
                [c[0] - h[0], c[1] - h[1], c[2] - h[2]],
                [c[0] + h[0], c[1] + h[1], c[2] + h[2]],
            )
            .unwrap_or_else(|e| panic!("{e}"));
            let window = if q % 3 == 0 {
                let a = rng.uniform(0.0, 6.0);
                windowed += 1;
                Some(
                    TimeWindow::new(a, a + rng.uniform(0.0, 2.0)).unwrap_or_else(|e| panic!("{e}")),
                )
            } else {
                None
            };
            let truth: BTreeSet<u32> = paths
                .iter()
                .enumerate()
                .filter(|(w, p)| {
                    *w != 17
                        && p.polyline()
                            .first_entry(&frustum.inflated(p.radius), window)
                            .is_some()
                })
                .map(|(w, _)| w as u32)
                .collect();
            kept += usize::from(truth.len() > 1);
            for parts in &splits {
                assert_eq!(
                    touched(&bvh, parts, &frustum, window, &paths),
                    truth,
                    "query {q}"
                );
            }
        }
        assert!(
            kept > 100 && windowed > 50,
            "kept {kept}, windowed {windowed}"
        );
    }

    /// Split any way, the parts hand over every piece exactly once (a region holding
    /// everything prunes nothing).
    #[test]
    fn parts_cover_every_piece_once() {
        let mut rng = WorldRng::new(5, Stream::Scene);
        let mut bvh = PathBvh::default();
        for (w, path) in paths(&mut rng, 700).iter_mut().enumerate() {
            path.radius = 0.01;
            bvh.insert(w as u32, path);
        }
        let all = Frustum::aabb([-100.0; 3], [100.0; 3]).unwrap_or_else(|e| panic!("{e}"));
        let region = region_box(&all.inflated_bounded(bvh.max_radius()));
        for at_least in [0, 1, 2, 7, 1000] {
            let mut seen = 0;
            for part in bvh.parts(at_least) {
                bvh.query(
                    part,
                    &all,
                    region.as_ref(),
                    None,
                    |_| false,
                    |p| {
                        assert_eq!(p.mask, 0, "inside every plane");
                        seen += 1;
                    },
                );
            }
            assert_eq!(seen, bvh.len(), "split into at least {at_least}");
        }
    }
}
