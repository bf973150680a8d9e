//! The per-object path index of §4.4.2: a low-resolution centre-of-mass polyline and a shallow
//! OBB tree over it.
//!
//! §4.4.2 keeps an uncompressed, down-sampled copy of every path in memory and evaluates queries
//! on it. Paths have no volume, so spheres bound them badly (the reference found sphere trees
//! slower than brute force); oriented boxes fitted along the path do well, and a tree of depth at
//! most three with runs of segments in its leaves keeps the memory overhead small while speeding
//! up queries about threefold. The tree owns the polyline, so the path need not be stored twice.
//!
//! **Never miss.** The index answers exactly for the polyline it holds, and a caller widens the
//! question by a radius: [`PathTree::intersects`] tests the frustum moved outward by `radius`.
//! With `radius` = the codec's e_max + [`Polyline::max_deviation_from`] the full-rate path,
//! every world whose decoded full-rate path enters the frustum is returned: at each time t the
//! decoded position is within e_max of the true one, which is within the deviation of the
//! low-resolution position at the same t, and that one lies on a tested segment inside the
//! inflated frustum. Comparing positions *at the same time* (not nearest points) is what makes
//! the bound hold for time windows too.
//!
//! **Rest.** A world ends when its bodies come to rest or its end time is reached, and from then
//! on each body stays at its final pose. A path therefore holds its last vertex for ever: a
//! window that begins after the path's last time asks whether that vertex is inside
//! ([`rest_entry`]), and a final-pose constraint asks only that ([`PathTree::final_pose_inside`]).
//! The never-miss bound holds there too: the indexed polyline's last vertex *is* the last decoded
//! frame (simplification and sub-sampling keep it), so after the end the two differ by nothing.

use super::constraint::TimeWindow;
use super::frustum::{ALL_PLANES, Frustum, RegionCache};
use super::geom::{Vec3, add, dot, lerp, norm, scale, sub, sym_eigenvectors};
use super::{BrowseError, finite};

/// Maximum depth of a [`PathTree`] (the root has depth 0), so at most 2³ = 8 leaves (§4.4.2).
pub const MAX_TREE_DEPTH: usize = 3;
/// A node with fewer segments than this stays a leaf: splitting short runs costs more in boxes
/// (memory, and a box test costs about two segment tests) than it saves; measured with
/// `mwb bench query` (4 → 16 took the index from 32 to 15 kB per 10-object world at the same
/// speed). A 3 s tumbling path of ~19 vertices gets a root and two leaves.
pub const MIN_SPLIT_SEGMENTS: usize = 16;

/// A finite start time and a positive, finite frame interval.
fn check_timing(start: f64, frame_dt: f64) -> Result<(), BrowseError> {
    finite("start", start)?;
    if finite("frame_dt", frame_dt)? <= 0.0 {
        return Err(BrowseError::OutOfRange {
            field: "frame_dt",
            value: frame_dt,
            expected: "a positive frame interval",
        });
    }
    Ok(())
}

/// A timed polyline: positions of one object's centre of mass at strictly increasing times,
/// linearly interpolated in between.
#[derive(Debug, Clone, PartialEq)]
pub struct Polyline {
    times: Vec<f64>,
    points: Vec<Vec3>,
}

impl Polyline {
    /// Checks that both vectors have the same non-zero length, every value is finite and times
    /// increase strictly.
    pub fn new(times: Vec<f64>, points: Vec<Vec3>) -> Result<Self, BrowseError> {
        if times.is_empty() {
            return Err(BrowseError::Empty {
                field: "path.times",
            });
        }
        if times.len() != points.len() {
            return Err(BrowseError::LengthMismatch {
                field: "path.points",
                expected: times.len(),
                found: points.len(),
            });
        }
        for (i, &t) in times.iter().enumerate() {
            finite("path.times", t)?;
            if i > 0 && t <= times[i - 1] {
                return Err(BrowseError::TimesNotIncreasing {
                    field: "path.times",
                    at: i,
                    value: t,
                });
            }
        }
        for p in &points {
            for &v in p {
                finite("path.points", v)?;
            }
        }
        Ok(Self { times, points })
    }

    /// Frames `points` at `start + i·frame_dt`.
    pub fn uniform(start: f64, frame_dt: f64, points: Vec<Vec3>) -> Result<Self, BrowseError> {
        check_timing(start, frame_dt)?;
        let times = (0..points.len())
            .map(|i| start + i as f64 * frame_dt)
            .collect();
        Self::new(times, points)
    }

    /// An error-bounded simplification of a full-rate path (frame `i` at `start + i·frame_dt`):
    /// vertices are kept where needed so that every frame's position lies within `tolerance` of
    /// the polyline point *at the same time*. Returns the polyline and its largest measured
    /// deviation (≤ `tolerance`; 0 for an exact copy), which is what a never-miss test must add
    /// to its radius.
    ///
    /// Greedy from the first frame: each run is grown by doubling, then narrowed by bisection to
    /// the longest run found to fit (every accepted run is checked frame by frame, so the bound
    /// holds whatever the motion), O(n log n) per object. Resting stretches collapse to one
    /// segment; a 4 Hz sub-sample of a bouncing box strays by decimetres, this by `tolerance`.
    pub fn simplify(
        start: f64,
        frame_dt: f64,
        points: &[Vec3],
        tolerance: f64,
    ) -> Result<(Polyline, f64), BrowseError> {
        check_timing(start, frame_dt)?;
        let tol = finite("tolerance", tolerance)?.max(0.0);
        if points.is_empty() {
            return Err(BrowseError::Empty {
                field: "path.points",
            });
        }
        for p in points {
            for &v in p {
                finite("path.points", v)?;
            }
        }
        // Largest same-time distance of frames a..=b from the chord a→b.
        let chord_error = |a: usize, b: usize| -> f64 {
            let (pa, pb) = (points[a], points[b]);
            let span = (b - a) as f64;
            (a + 1..b)
                .map(|f| norm(sub(points[f], lerp(pa, pb, (f - a) as f64 / span))))
                .fold(0.0, f64::max)
        };
        let last = points.len() - 1;
        let mut keep = vec![0usize];
        let mut max_dev = 0.0f64;
        let mut a = 0;
        while a < last {
            // Grow: a+1 always fits (no frame in between).
            let mut good = a + 1;
            let mut step = 1;
            let mut bad = None;
            while good < last {
                let b = (a + 2 * step).min(last);
                if chord_error(a, b) <= tol {
                    good = b;
                    step *= 2;
                } else {
                    bad = Some(b);
                    break;
                }
            }
            // Narrow between the longest fitting and the first failing end.
            if let Some(mut hi) = bad {
                let mut lo = good;
                while hi - lo > 1 {
                    let mid = lo + (hi - lo) / 2;
                    if chord_error(a, mid) <= tol {
                        lo = mid;
                    } else {
                        hi = mid;
                    }
                }
                good = lo;
            }
            max_dev = max_dev.max(chord_error(a, good));
            keep.push(good);
            a = good;
        }
        let times = keep.iter().map(|&f| start + f as f64 * frame_dt).collect();
        let verts = keep.iter().map(|&f| points[f]).collect();
        Ok((Polyline::new(times, verts)?, max_dev))
    }

    pub fn times(&self) -> &[f64] {
        &self.times
    }

    pub fn points(&self) -> &[Vec3] {
        &self.points
    }

    /// Number of vertices (at least 1).
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// Always false: a polyline has at least one vertex.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Number of segments; a single vertex counts as one degenerate segment.
    pub fn segment_count(&self) -> usize {
        self.points.len().saturating_sub(1).max(1)
    }

    /// Segment `i`: endpoints and their times.
    fn segment(&self, i: usize) -> (Vec3, Vec3, f64, f64) {
        let j = (i + 1).min(self.points.len() - 1);
        (self.points[i], self.points[j], self.times[i], self.times[j])
    }

    /// Position at time `t`, linearly interpolated, held constant outside the time range.
    pub fn position_at(&self, t: f64) -> Vec3 {
        let i = self.times.partition_point(|&x| x <= t);
        if i == 0 {
            return self.points[0];
        }
        if i == self.times.len() {
            return self.points[i - 1];
        }
        let (t0, t1) = (self.times[i - 1], self.times[i]);
        lerp(self.points[i - 1], self.points[i], (t - t0) / (t1 - t0))
    }

    /// A sub-sampled copy keeping a vertex at least every `period` seconds, always keeping the
    /// first and the last (so the low-resolution path spans the same time range). A period that
    /// is not positive keeps everything.
    pub fn subsample(&self, period: f64) -> Polyline {
        if period.is_nan() || period <= 0.0 || self.points.len() <= 2 {
            return self.clone();
        }
        let n = self.points.len();
        let mut keep = vec![0];
        let mut next = self.times[0] + period;
        for i in 1..n - 1 {
            // A relative tolerance so that 120 Hz frames land on a 4 Hz grid despite rounding.
            if self.times[i] >= next - 1e-9 * period {
                keep.push(i);
                next = self.times[i] + period;
            }
        }
        keep.push(n - 1);
        Polyline {
            times: keep.iter().map(|&i| self.times[i]).collect(),
            points: keep.iter().map(|&i| self.points[i]).collect(),
        }
    }

    /// The largest distance between this polyline and `other` *at the same time*, both linearly
    /// interpolated. Exact: the difference of two piecewise-linear paths is linear between the
    /// union of their vertex times, and a norm of a linear function peaks at an interval end, so
    /// checking every vertex time of both suffices.
    pub fn max_deviation_from(&self, other: &Polyline) -> f64 {
        let one_way = |a: &Polyline, b: &Polyline| {
            a.times
                .iter()
                .zip(&a.points)
                .map(|(&t, &p)| norm(sub(p, b.position_at(t))))
                .fold(0.0, f64::max)
        };
        one_way(self, other).max(one_way(other, self))
    }

    /// The earliest time in `window` at which the polyline is inside `frustum`, testing every
    /// segment and then the final pose held after the end (the brute-force reference for
    /// [`PathTree::first_entry`]).
    pub fn first_entry(&self, frustum: &Frustum, window: Option<TimeWindow>) -> Option<f64> {
        (0..self.segment_count())
            .find_map(|i| self.segment_entry(i, frustum, ALL_PLANES, window))
            .or_else(|| self.rest_entry(frustum, ALL_PLANES, window))
    }

    /// The last vertex and its time: the pose held after the end.
    pub fn end(&self) -> (Vec3, f64) {
        let last = self.points.len() - 1;
        (self.points[last], self.times[last])
    }

    /// Whether the final pose is inside `frustum` (on the boundary counts).
    pub fn final_pose_inside(&self, frustum: &Frustum) -> bool {
        let (p, _) = self.end();
        frustum
            .clip_segment_masked(p, p, 0.0, 1.0, ALL_PLANES)
            .is_some()
    }

    /// [`rest_entry`] of this polyline's end.
    fn rest_entry(&self, frustum: &Frustum, mask: u8, window: Option<TimeWindow>) -> Option<f64> {
        let (p, t) = self.end();
        rest_entry(p, t, frustum, mask, window)
    }

    /// Exact leaf test of segment `i` ([`segment_entry`]).
    fn segment_entry(
        &self,
        i: usize,
        frustum: &Frustum,
        mask: u8,
        window: Option<TimeWindow>,
    ) -> Option<f64> {
        let (a, b, ta, tb) = self.segment(i);
        segment_entry(a, b, ta, tb, frustum, mask, window)
    }
}

/// The exact leaf test of every path query: the part of the segment from `a` (time `ta`) to `b`
/// (time `tb`) inside `window` is clipped against the planes of `frustum` in `mask` (bit k =
/// plane k); returns the time it first is inside. Leaving out a plane the whole segment is
/// inside of changes nothing: such a plane neither rejects nor cuts. Brute force, the OBB trees
/// and the store's hierarchy all decide with this one function, so they agree bit for bit.
#[inline]
pub fn segment_entry(
    a: Vec3,
    b: Vec3,
    ta: f64,
    tb: f64,
    frustum: &Frustum,
    mask: u8,
    window: Option<TimeWindow>,
) -> Option<f64> {
    let (mut s0, mut s1) = (0.0, 1.0);
    if let Some(w) = window {
        if tb < w.start() || ta > w.end() {
            return None;
        }
        let span = tb - ta;
        if span > 0.0 {
            if w.start() > ta {
                s0 = (w.start() - ta) / span;
            }
            if w.end() < tb {
                s1 = (w.end() - ta) / span;
            }
        }
    }
    let (lo, _) = frustum.clip_segment_masked(a, b, s0, s1, mask)?;
    Some((ta + lo * (tb - ta)).clamp(ta, tb))
}

/// The held final pose: after its last vertex `end` (time `t_end`) a path stays there for ever,
/// since its world has ended. For a `window` that begins after `t_end` — the only windows the
/// path's last segment does not already answer — returns the window's start if `end` is inside
/// the planes of `frustum` in `mask`. Brute force, the OBB trees and the store's hierarchy call
/// this after the last segment, so they agree on rest poses as on segments.
#[inline]
pub fn rest_entry(
    end: Vec3,
    t_end: f64,
    frustum: &Frustum,
    mask: u8,
    window: Option<TimeWindow>,
) -> Option<f64> {
    let w = window?;
    if w.start() <= t_end {
        return None;
    }
    frustum.clip_segment_masked(end, end, 0.0, 1.0, mask)?;
    Some(w.start())
}

/// An oriented bounding box: centre, orthonormal axes and half extents along them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Obb {
    pub center: Vec3,
    pub axes: [Vec3; 3],
    pub half: [f64; 3],
}

impl Obb {
    /// The box along the principal axes of `points` (PCA of their covariance), just large enough
    /// to hold them all, padded by a hair so that rounding can never make it miss one.
    pub fn fit(points: &[Vec3]) -> Obb {
        let n = points.len().max(1) as f64;
        let mean = scale(points.iter().fold([0.0; 3], |acc, &p| add(acc, p)), 1.0 / n);
        let mut cov = [[0.0; 3]; 3];
        for p in points {
            let d = sub(*p, mean);
            for (r, row) in cov.iter_mut().enumerate() {
                for (c, v) in row.iter_mut().enumerate() {
                    *v += d[r] * d[c];
                }
            }
        }
        let axes = sym_eigenvectors(cov);
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in points {
            let d = sub(*p, mean);
            for k in 0..3 {
                let x = dot(axes[k], d);
                lo[k] = lo[k].min(x);
                hi[k] = hi[k].max(x);
            }
        }
        if points.is_empty() {
            lo = [0.0; 3];
            hi = [0.0; 3];
        }
        let magnitude = mean.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let mut center = mean;
        let mut half = [0.0; 3];
        for k in 0..3 {
            center = add(center, scale(axes[k], 0.5 * (lo[k] + hi[k])));
            let h = 0.5 * (hi[k] - lo[k]);
            half[k] = h + 1e-9 * (1.0 + magnitude + h);
        }
        Obb { center, axes, half }
    }

    /// True only if some plane of `frustum` has the whole box strictly outside: the conservative
    /// plane test of Assarsson and Möller. It may answer "overlaps" for a box that does not, but
    /// never "outside" for one that does, so pruning by it loses no hits.
    pub fn outside(&self, frustum: &Frustum) -> bool {
        frustum.planes().iter().any(|p| {
            let reach: f64 = (0..3)
                .map(|k| dot(p.normal, self.axes[k]).abs() * self.half[k])
                .sum();
            p.distance(self.center) > reach
        })
    }

    /// Whether the box is provably apart from `region` (a frustum, typically inflated with
    /// [`Frustum::inflated_bounded`]): some plane has the whole box outside (the plane test
    /// above), or, when the region carries its vertices, some box axis separates the box from
    /// them (a separating-axis test that catches the big boxes beside a thin frustum which no
    /// single plane rejects). The vertex set spans a hull containing the region, and the axis
    /// test keeps a margin of a millionth of the scale, so "apart" is only ever answered when it
    /// is true: pruning by it loses no hit of a segment test against the same region.
    ///
    /// The tree no longer uses the vertex half (see [`PathTree::intersects_region`]); the store's
    /// hierarchy tests boxes against the vertices' bounding box.
    pub fn apart(&self, region: &Frustum) -> bool {
        if self.outside(region) {
            return true;
        }
        let Some(hull) = region.hull() else {
            return false;
        };
        (0..3).any(|k| {
            let c = dot(self.axes[k], self.center);
            let h = self.half[k];
            let (lo, hi) = hull
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
                    let x = dot(self.axes[k], *v) - c;
                    (lo.min(x), hi.max(x))
                });
            // |projection of a vertex| ≤ |x| + |c|: a millionth of that scale.
            let margin = 1e-6 * (1.0 + 2.0 * c.abs() + lo.abs().max(hi.abs()));
            lo > h + margin || hi < -h - margin
        })
    }

    /// The plane test of [`outside`](Self::outside) over the planes in `mask` (bit k = plane
    /// k), which also reports the planes the whole box is inside of, with a margin far above
    /// rounding so that every point in the box is strictly inside them: those are cleared from
    /// the returned mask, and what the box holds need not be tested against them again (plane
    /// masking, Assarsson and Möller). `None`: some plane has the whole box outside.
    pub fn classify(&self, region: &Frustum, mask: u8) -> Option<u8> {
        let mut out = mask;
        for (k, p) in region.planes().iter().enumerate() {
            if mask & (1 << k) == 0 {
                continue;
            }
            let reach: f64 = (0..3)
                .map(|i| dot(p.normal, self.axes[i]).abs() * self.half[i])
                .sum();
            let d = p.distance(self.center);
            if d > reach {
                return None;
            }
            let margin = 1e-9 * (1.0 + p.offset.abs() + d.abs() + reach);
            if d + reach < -margin {
                out &= !(1 << k);
            }
        }
        Some(out)
    }

    /// Whether `x` is inside the box enlarged by `tol`.
    pub fn contains(&self, x: Vec3, tol: f64) -> bool {
        let d = sub(x, self.center);
        (0..3).all(|k| dot(d, self.axes[k]).abs() <= self.half[k] + tol)
    }
}

#[derive(Debug, Clone, PartialEq)]
struct Node {
    obb: Obb,
    t_start: f64,
    /// +∞ for the nodes holding the last segment: the final pose is held after the end.
    t_end: f64,
    /// Segments `first..end` of the polyline.
    first: u32,
    end: u32,
    /// Earlier half, later half.
    children: Option<[u32; 2]>,
}

/// One object's path index: the low-resolution polyline and an OBB tree of depth ≤
/// [`MAX_TREE_DEPTH`] over it (§4.4.2). Children split their parent's run of segments in time
/// order, which lets a query stop at the first hit and report the time of first entry.
#[derive(Debug, Clone, PartialEq)]
pub struct PathTree {
    path: Polyline,
    nodes: Vec<Node>,
}

impl PathTree {
    pub fn build(path: Polyline) -> PathTree {
        let mut tree = PathTree {
            path,
            nodes: Vec::new(),
        };
        let segments = tree.path.segment_count();
        tree.build_node(0, segments, 0);
        // Three nodes would otherwise hold room for four: 10 % of a store's index.
        tree.nodes.shrink_to_fit();
        tree
    }

    fn build_node(&mut self, first: usize, end: usize, depth: usize) -> u32 {
        let last_point = end.min(self.path.len() - 1);
        // The box holds the last vertex, so the held final pose is inside it too.
        let obb = Obb::fit(&self.path.points[first..=last_point]);
        let index = self.nodes.len();
        let t_end = if end >= self.path.segment_count() {
            f64::INFINITY
        } else {
            self.path.times[last_point]
        };
        self.nodes.push(Node {
            obb,
            t_start: self.path.times[first],
            t_end,
            first: first as u32,
            end: end as u32,
            children: None,
        });
        if depth < MAX_TREE_DEPTH && end - first >= MIN_SPLIT_SEGMENTS {
            let mid = first + (end - first) / 2;
            let left = self.build_node(first, mid, depth + 1);
            let right = self.build_node(mid, end, depth + 1);
            self.nodes[index].children = Some([left, right]);
        }
        index as u32
    }

    /// The polyline the tree was built over (the tree is its only copy, §4.4.2).
    pub fn path(&self) -> &Polyline {
        &self.path
    }

    /// Number of OBB nodes.
    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// Depth of the deepest leaf (root = 0).
    pub fn depth(&self) -> usize {
        fn go(tree: &PathTree, i: u32) -> usize {
            match tree.nodes[i as usize].children {
                Some([l, r]) => 1 + go(tree, l).max(go(tree, r)),
                None => 0,
            }
        }
        go(self, 0)
    }

    /// Heap bytes held (polyline and nodes), for memory accounting in the store.
    pub fn heap_bytes(&self) -> usize {
        self.path.times.capacity() * size_of::<f64>()
            + self.path.points.capacity() * size_of::<Vec3>()
            + self.nodes.capacity() * size_of::<Node>()
    }

    /// The earliest time in `window` at which the polyline, with its final pose held after the
    /// end, is inside `frustum` (exact for the polyline; equal to [`Polyline::first_entry`]). Subtrees whose box is outside a plane, or
    /// whose time span misses the window, are skipped; see
    /// [`intersects_region`](Self::intersects_region) for the box tests.
    pub fn first_entry(&self, frustum: &Frustum, window: Option<TimeWindow>) -> Option<f64> {
        self.visit(0, frustum, ALL_PLANES, window)
    }

    /// Never-miss test: does the polyline come within the frustum inflated by `radius` (codec
    /// e_max + the polyline's deviation from the full-rate path) during `window`? Builds the
    /// inflated region on every call; many tests of one frustum share them through
    /// [`intersects_cached`](Self::intersects_cached).
    pub fn intersects(&self, frustum: &Frustum, window: Option<TimeWindow>, radius: f64) -> bool {
        self.intersects_cached(&mut RegionCache::new(frustum), window, radius)
    }

    /// [`intersects`](Self::intersects) with the inflated region taken from `regions`.
    pub fn intersects_cached(
        &self,
        regions: &mut RegionCache<'_>,
        window: Option<TimeWindow>,
        radius: f64,
    ) -> bool {
        self.intersects_region(regions.region(radius), window)
    }

    /// Whether the polyline enters `region` (already inflated) during `window`. Boxes are
    /// pruned and segments clipped against the same region's planes, so the answer is exactly
    /// the segment-by-segment answer of [`Polyline::first_entry`] on `region`.
    ///
    /// Each box gets the plane test only ([`Obb::classify`]): a box wholly inside some planes
    /// passes the fact down, so its children and segments skip those planes, and a box wholly
    /// inside all six answers from its first segment in the window without clipping. The
    /// separating-axis test on the region's vertices ([`Obb::apart`]) is not used here: on the
    /// `mwb bench query` scenes it rejected about 0.3 % of the boxes the plane test kept and
    /// took a tenth of the query time.
    pub fn intersects_region(&self, region: &Frustum, window: Option<TimeWindow>) -> bool {
        self.visit(0, region, ALL_PLANES, window).is_some()
    }

    /// The root's box: the box of the whole path.
    pub fn root_box(&self) -> &Obb {
        &self.nodes[0].obb
    }

    /// Whether the final pose is inside `region` (for a never-miss test, the frustum inflated
    /// by the path's radius: the last vertex is the last decoded frame, which is within e_max
    /// of the simulated one).
    pub fn final_pose_inside(&self, region: &Frustum) -> bool {
        self.path.final_pose_inside(region)
    }

    fn in_window(&self, i: u32, window: Option<TimeWindow>) -> bool {
        let node = &self.nodes[i as usize];
        window.is_none_or(|w| node.t_end >= w.start() && node.t_start <= w.end())
    }

    /// `mask`: the planes of `region` the node's segments may still be outside of (its
    /// ancestors' boxes were wholly inside the others).
    fn visit(&self, i: u32, region: &Frustum, mask: u8, window: Option<TimeWindow>) -> Option<f64> {
        if !self.in_window(i, window) {
            return None;
        }
        let node = &self.nodes[i as usize];
        let mask = node.obb.classify(region, mask)?;
        // Wholly inside every plane (mask 0): the first segment in the window is the answer,
        // and the leaf loop below finds it with no plane to clip against.
        match node.children {
            // Left first: it covers earlier times, so its hit (if any) is the first entry.
            Some([left, right]) if mask != 0 => self
                .visit(left, region, mask, window)
                .or_else(|| self.visit(right, region, mask, window)),
            _ => (node.first as usize..node.end as usize)
                .find_map(|s| self.path.segment_entry(s, region, mask, window))
                .or_else(|| {
                    (node.end as usize >= self.path.segment_count())
                        .then(|| self.path.rest_entry(region, mask, window))
                        .flatten()
                }),
        }
    }

    #[cfg(test)]
    fn check_boxes(&self) {
        for node in &self.nodes {
            let last = (node.end as usize).min(self.path.len() - 1);
            for p in &self.path.points[node.first as usize..=last] {
                assert!(node.obb.contains(*p, 0.0), "{p:?} outside {:?}", node.obb);
            }
        }
    }
}

#[cfg(test)]
mod tests;
