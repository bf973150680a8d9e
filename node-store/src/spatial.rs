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
//! **Blocks.** Pieces are built into the hierarchy in fixed-size blocks of [`BLOCK`] pieces,
//! in the order they arrive, and a block once built is never merged or rebuilt (unless a world
//! in it is replaced): a new piece waits in a pending list (tested one by one) until the list
//! holds a block's worth, which is then built on its own — a few hundred microseconds, so
//! ingest never pauses for a rebuild of everything held. The price: every block's root is tested
//! by every query, and the upper levels of one global tree (which would separate far-apart
//! pieces) are missing; in a compact scene they pruned nothing anyway, in a spread one a
//! block's own top levels do it. The gain beyond ingest: a block holds the pieces of a few
//! thousand consecutively stored worlds, so the exact tests a query runs in one block read
//! those worlds' paths, which lie near each other in memory, rather than paths scattered over
//! every world held (with one global tree each piece tested cost a few cache misses from main
//! memory). The work of one query comes in [`Part`]s (blocks or subtrees of them, runs of the
//! pending list) that threads take one at a time.
//!
//! **Size.** Boxes are stored as i16 steps of one grid per block (a power-of-two step from a
//! fixed origin, rounded outward, so a stored box always holds the exact one) and times as u16
//! steps of [`TIME_STEP_S`], also rounded outward: a piece is 24 bytes and a node 20 (44 and
//! 56 with f32 and f64 boxes). A grid value never needs rounding again — building a block moves
//! pieces without re-encoding them — and when a pending piece lies beyond its grid's i16 reach
//! the pending grid's step doubles (every pending box rounded outward once more; built blocks
//! keep their own grids) up to [`BOX_GRID_MAX_EXP`]; a piece farther still gets an infinite
//! side, which prunes less but never misses. Each block starts a fresh grid, so one far piece
//! coarsens only its own block.

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

/// Finest step of a block's box grid, as a power of two (2⁻⁹ m ≈ 2 mm: i16 steps reach
/// ±64 m from the grid's origin). A box grows by less than a step on each side when rounded
/// outward to it, a fraction of the never-miss radius (~11 mm on tumble).
const BOX_GRID_EXP: i32 = -9;

/// Coarsest step the grid doubles to when pieces lie beyond its reach (2⁻⁵ m ≈ 31 mm, ±1 km).
/// Beyond that a piece's box gets an infinite side instead of coarsening every other box.
pub const BOX_GRID_MAX_EXP: i32 = -5;

/// Step of the pieces' time ranges, seconds (2⁻⁶ s: u16 steps reach 17 minutes). A range is
/// rounded outward; a start within the first step reads as −∞ and an end beyond the last one
/// as +∞, so that windows are never wrongly missed.
pub const TIME_STEP_S: f64 = 1.0 / 64.0;

/// `2^exp` for the exponents a grid can have (normal f64 numbers).
fn pow2(exp: i32) -> f64 {
    f64::from_bits(((exp + 1023) as u64) << 52)
}

/// The grid of one block's boxes: code `s` is `origin + s · 2^exp`, except [`i16::MIN`] (−∞)
/// and [`i16::MAX`] (+∞). The origin is fixed at the block's first piece (whole metres near
/// its path), the step only ever doubles.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Grid {
    origin: Vec3,
    exp: i32,
}

impl Grid {
    /// The one decoding every reader uses (so a stored box is read the same everywhere).
    #[inline]
    fn value(&self, k: usize, s: i16) -> f64 {
        match s {
            i16::MIN => f64::NEG_INFINITY,
            i16::MAX => f64::INFINITY,
            _ => self.origin[k] + f64::from(s) * pow2(self.exp),
        }
    }

    /// The largest finite code whose value is at most `v`; `None` when it is out of reach.
    /// −∞ is [`i16::MIN`].
    fn down(&self, k: usize, v: f64) -> Option<i16> {
        if v == f64::NEG_INFINITY {
            return Some(i16::MIN);
        }
        let s = ((v - self.origin[k]) / pow2(self.exp)).floor();
        if !(f64::from(i16::MIN) + 2.0..=f64::from(i16::MAX) - 1.0).contains(&s) {
            return None;
        }
        // The subtraction and division round: step down once more if they rounded up.
        let s = s as i16;
        if self.value(k, s) <= v {
            Some(s)
        } else {
            Some(s - 1).filter(|&s| self.value(k, s) <= v)
        }
    }

    /// The smallest finite code whose value is at least `v`; `None` when it is out of reach.
    /// +∞ is [`i16::MAX`].
    fn up(&self, k: usize, v: f64) -> Option<i16> {
        if v == f64::INFINITY {
            return Some(i16::MAX);
        }
        let s = ((v - self.origin[k]) / pow2(self.exp)).ceil();
        if !(f64::from(i16::MIN) + 1.0..=f64::from(i16::MAX) - 2.0).contains(&s) {
            return None;
        }
        let s = s as i16;
        if self.value(k, s) >= v {
            Some(s)
        } else {
            Some(s + 1).filter(|&s| self.value(k, s) >= v)
        }
    }

    /// `b` rounded outward to the grid, or `None` if some side is out of reach (or NaN).
    fn encode(&self, b: &Aabb) -> Option<GridBox> {
        let mut out = GridBox {
            lo: [0; 3],
            hi: [0; 3],
        };
        for k in 0..3 {
            out.lo[k] = self.down(k, b.min[k])?;
            out.hi[k] = self.up(k, b.max[k])?;
        }
        Some(out)
    }

    /// `b` rounded outward to the grid, a side out of reach (or NaN) made infinite.
    fn encode_clamped(&self, b: &Aabb) -> GridBox {
        let mut out = GridBox {
            lo: [0; 3],
            hi: [0; 3],
        };
        for k in 0..3 {
            out.lo[k] = self.down(k, b.min[k]).unwrap_or(i16::MIN);
            out.hi[k] = self.up(k, b.max[k]).unwrap_or(i16::MAX);
        }
        out
    }

    fn decode(&self, b: &GridBox) -> Aabb {
        Aabb {
            min: [0, 1, 2].map(|k| self.value(k, b.lo[k])),
            max: [0, 1, 2].map(|k| self.value(k, b.hi[k])),
        }
    }
}

/// One frustum plane rewritten on a block's grid: the signed distance of the decoded corner
/// `origin + s · step` is `c + w · s`. The signs of `w` fix, per axis, which of a box's codes
/// gives its corner nearest the inside and which its corner farthest out.
#[derive(Debug, Clone, Copy)]
struct GridPlane {
    c: f64,
    w: [f64; 3],
    /// Per axis, whether `w ≥ 0`: the near corner is then at the low code.
    up: [bool; 3],
    /// `|offset|` of the plane, for [`Aabb::classify`]'s inside margin.
    offset_abs: f64,
}

/// [`Aabb::classify`] and the region-box test of one query on one grid's boxes, read straight
/// from their codes: the planes are moved onto the grid once per query and block (a box is
/// then 6 conversions and at most 36 multiply-adds, with no decoding, and the region box is
/// compared as codes). Boxes with an infinite side take the decoded path.
///
/// The sums round differently from the decoded box's, by a few units in the last place of
/// metres; every stored box is padded by a billionth of its scale beyond its points
/// ([`Aabb::of_points`]) and the inside margin is a billionth too, so neither answer can
/// lose a path or wrongly spare a plane.
struct GridTest<'a> {
    grid: Grid,
    planes: &'a [Plane; 6],
    region: Option<&'a Aabb>,
    on_grid: [GridPlane; 6],
    /// The region box as codes: a box is apart from it when its top code is below
    /// `region_lo` or its bottom code above `region_hi`. A bound beyond the grid's reach is
    /// the extreme code that puts every finite box on the side it is on.
    region_lo: [i16; 3],
    region_hi: [i16; 3],
}

impl<'a> GridTest<'a> {
    fn new(grid: Grid, planes: &'a [Plane; 6], region: Option<&'a Aabb>) -> Self {
        let step = pow2(grid.exp);
        let on_grid = planes.map(|p| {
            let w = p.normal.map(|n| n * step);
            GridPlane {
                c: -p.offset
                    + p.normal[0] * grid.origin[0]
                    + p.normal[1] * grid.origin[1]
                    + p.normal[2] * grid.origin[2],
                w,
                up: p.normal.map(|n| n >= 0.0),
                offset_abs: p.offset.abs(),
            }
        });
        let (mut region_lo, mut region_hi) = ([i16::MIN; 3], [i16::MAX; 3]);
        if let Some(r) = region {
            for k in 0..3 {
                // The first code at or above the region's bottom, the last at or below its
                // top (a decoded box is below the region exactly when its top is below the
                // first); beyond the grid's reach every finite code is on one side.
                region_lo[k] = grid
                    .up(k, r.min[k])
                    .unwrap_or(if r.min[k] > grid.origin[k] {
                        i16::MAX
                    } else {
                        i16::MIN
                    });
                region_hi[k] = grid
                    .down(k, r.max[k])
                    .unwrap_or(if r.max[k] < grid.origin[k] {
                        i16::MIN
                    } else {
                        i16::MAX
                    });
            }
        }
        GridTest {
            grid,
            planes,
            region,
            on_grid,
            region_lo,
            region_hi,
        }
    }

    /// What `grid.decode(b)` tested against the region box and then [`Aabb::classify`]
    /// against the planes in `mask` would answer.
    #[inline]
    fn classify(&self, b: &GridBox, mask: u8) -> Option<u8> {
        if b.lo.contains(&i16::MIN) || b.hi.contains(&i16::MAX) {
            let d = self.grid.decode(b);
            if self.region.is_some_and(|r| d.disjoint(r)) {
                return None;
            }
            return d.classify(self.planes, mask);
        }
        let mut apart = false;
        for k in 0..3 {
            apart |= b.hi[k] < self.region_lo[k] || b.lo[k] > self.region_hi[k];
        }
        if apart {
            return None;
        }
        let lo = b.lo.map(f64::from);
        let hi = b.hi.map(f64::from);
        let mut out = mask;
        for (k, p) in self.on_grid.iter().enumerate() {
            if mask & (1 << k) == 0 {
                continue;
            }
            let mut near = p.c;
            let mut far = p.c;
            for i in 0..3 {
                let (a, z) = if p.up[i] {
                    (lo[i], hi[i])
                } else {
                    (hi[i], lo[i])
                };
                near += p.w[i] * a;
                far += p.w[i] * z;
            }
            if near > 0.0 {
                return None;
            }
            if far < -1e-9 * (1.0 + p.offset_abs + far.abs()) {
                out &= !(1 << k);
            }
        }
        Some(out)
    }
}

/// A box in steps of its hierarchy's [`Grid`] (12 bytes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct GridBox {
    lo: [i16; 3],
    hi: [i16; 3],
}

impl GridBox {
    fn union(&self, o: &GridBox) -> GridBox {
        GridBox {
            lo: [0, 1, 2].map(|k| self.lo[k].min(o.lo[k])),
            hi: [0, 1, 2].map(|k| self.hi[k].max(o.hi[k])),
        }
    }

    /// Twice the centre along axis `k`, in steps (for sorting; infinite sides sort outermost).
    fn centre2(&self, k: usize) -> i32 {
        i32::from(self.lo[k]) + i32::from(self.hi[k])
    }

    /// The same box on a grid of twice the step (same origin), rounded outward: code `s`
    /// becomes ⌊s/2⌋ below and ⌈s/2⌉ above, and the infinities stay. The decoded value of
    /// either is a rounding of the same exact sum, and rounding is monotonic, so the new box
    /// holds the old one.
    fn coarsened(&self) -> GridBox {
        GridBox {
            lo: self.lo.map(|s| {
                if s == i16::MIN {
                    s
                } else {
                    i32::from(s).div_euclid(2) as i16
                }
            }),
            hi: self.hi.map(|s| {
                if s == i16::MAX {
                    s
                } else {
                    (-(-i32::from(s)).div_euclid(2)) as i16
                }
            }),
        }
    }
}

#[derive(Debug, Clone)]
struct Node {
    bounds: GridBox,
    /// Leaf: `entries[first..first + count]`; inner: children at `first` and `first + 1`.
    first: u32,
    count: u32,
}

/// Leaves hold at most this many pieces.
const LEAF: usize = 16;

/// Segments per piece: a path enters the hierarchy as runs of this many segments, each with its
/// own box, so that a query reaches the parts of a path near the frustum rather than whole
/// paths (in a compact scene nearly every path's box meets a frustum drawn through it, but few
/// of its pieces do). 8 rather than 4: a tumbling path of ~18 segments is 3 pieces instead of
/// 5 (the hierarchy is 744 bytes per 10-object world on `mwb bench query`; see
/// docs/performance.md for what it costs a query).
pub const PIECE_SEGMENTS: usize = 8;

/// The bit of [`Entry::piece`] that marks a path's last piece.
const LAST: u32 = 1 << 31;

/// One piece of a path: the box of its vertices grown by the path's radius (grid steps,
/// rounded outward), its time range, its world, and which piece of the path it is. The vertices
/// themselves stay in the world's [`IndexedObject`] (the store's only copy of them): a query
/// looks the object up for the few pieces whose box meets the frustum. 24 bytes, against 44
/// with an f32 box and 232 when each piece carried f64 copies of its vertices and times
/// (`mwb bench query`, docs/performance.md).
#[derive(Debug, Clone)]
struct Entry {
    bounds: GridBox,
    /// The piece's time range in steps of [`TIME_STEP_S`] ([`time_from`], [`time_to`]):
    /// windows that miss it skip the piece unseen. A path's last piece reaches to +∞ (the
    /// final pose is held after the end).
    t0: u16,
    t1: u16,
    world: u32,
    /// The piece's index in its path (its first segment is `index × PIECE_SEGMENTS`), and
    /// [`LAST`] when the piece ends the path: its last vertex is the final pose, held after
    /// the end. (Paths have fewer than 2³² vertices, so fewer than 2³¹ pieces.)
    piece: u32,
}

const _: () = assert!(
    PIECE_SEGMENTS >= 2,
    "piece indices must leave the LAST bit free"
);

/// The code of a piece's start time `t`: rounded down; 0 (read as −∞) below one step.
fn time_code_down(t: f64) -> u16 {
    let s = (t / TIME_STEP_S).floor();
    if s >= 1.0 {
        s.min(f64::from(u16::MAX - 1)) as u16
    } else {
        0
    }
}

/// The code of a piece's end time `t`: rounded up; [`u16::MAX`] (read as +∞) beyond reach.
fn time_code_up(t: f64) -> u16 {
    let s = (t / TIME_STEP_S).ceil();
    if s <= f64::from(u16::MAX - 1) {
        s.max(0.0) as u16
    } else {
        u16::MAX
    }
}

/// A piece's start time from its code (0: −∞).
fn time_from(s: u16) -> f64 {
    if s == 0 {
        f64::NEG_INFINITY
    } else {
        f64::from(s) * TIME_STEP_S
    }
}

/// A piece's end time from its code ([`u16::MAX`]: +∞).
fn time_to(s: u16) -> f64 {
    if s == u16::MAX {
        f64::INFINITY
    } else {
        f64::from(s) * TIME_STEP_S
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
        self.entry.piece & LAST != 0
    }

    /// The path's first segment in this piece.
    pub fn first_segment(&self) -> usize {
        (self.entry.piece & !LAST) as usize * PIECE_SEGMENTS
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
        let first = self.first_segment();
        // Pieces are cut every PIECE_SEGMENTS segments, so the path tells how many this holds.
        let count = PIECE_SEGMENTS.min(path.segment_count().saturating_sub(first));
        path.entry_in(first, count, self.is_last(), region, self.mask, window)
    }

    /// Whether the piece ends its path and the path's final pose is inside `region` (the
    /// query's frustum inflated by the path's radius).
    pub fn final_pose_inside(&self, path: &IndexedObject, region: &Frustum) -> bool {
        let (p, _) = path.vertex(path.len() - 1);
        self.is_last()
            && region
                .clip_segment_masked(p, p, 0.0, 1.0, self.mask)
                .is_some()
    }
}

/// Pieces a block is built from: the pending list is built into a block when the next path's
/// pieces would take it past this. 4096 pieces (~1 400 ten-object tumble worlds per object
/// index) build in well under a millisecond, and the worlds' paths a block's queries read
/// (~2 MB) stay in the caches.
pub const BLOCK: usize = 4096;

/// A share of a query's work: a subtree of a block (its root, or one near it), or a run of the
/// pending pieces.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Part {
    Subtree { block: u32, node: u32 },
    Pending { start: u32, end: u32 },
}

impl Part {
    /// The block this part belongs to ([`u32::MAX`] for the pending list): parts of different
    /// object indexes with the same block number hold the pieces of roughly the same worlds.
    pub fn block(&self) -> u32 {
        match self {
            Part::Subtree { block, .. } => *block,
            Part::Pending { .. } => u32::MAX,
        }
    }
}

/// Pieces built into a hierarchy of their own, on their own grid.
#[derive(Debug, Clone)]
struct Block {
    grid: Grid,
    /// In hierarchy order.
    entries: Box<[Entry]>,
    nodes: Box<[Node]>,
    /// Lowest and highest world with a piece here: a removal looks only at blocks whose range
    /// holds its world.
    worlds: (u32, u32),
}

impl Block {
    /// The hierarchy over `entries` (boxes on `grid`); `None` when there are none.
    fn build(grid: Grid, mut entries: Box<[Entry]>) -> Option<Block> {
        let first = entries.first()?;
        let mut worlds = (first.world, first.world);
        for e in entries.iter() {
            worlds = (worlds.0.min(e.world), worlds.1.max(e.world));
        }
        // A full binary tree whose leaves hold at least LEAF / 2 pieces.
        let mut nodes = Vec::with_capacity(4 * entries.len() / LEAF + 1);
        nodes.push(Node {
            bounds: first.bounds,
            first: 0,
            count: 0,
        });
        let n = entries.len();
        build(&mut entries, &mut nodes, 0, 0, n);
        Some(Block {
            grid,
            entries,
            nodes: nodes.into_boxed_slice(),
            worlds,
        })
    }

    fn heap_bytes(&self) -> usize {
        self.entries.len() * std::mem::size_of::<Entry>()
            + self.nodes.len() * std::mem::size_of::<Node>()
    }
}

/// Builds node `at` over `entries[lo..hi]`: median split along the longest axis of the
/// entries' centres.
fn build(entries: &mut [Entry], nodes: &mut Vec<Node>, at: usize, lo: usize, hi: usize) {
    let bounds = entries[lo + 1..hi]
        .iter()
        .fold(entries[lo].bounds, |b, e| b.union(&e.bounds));
    if hi - lo <= LEAF {
        nodes[at] = Node {
            bounds,
            first: lo as u32,
            count: (hi - lo) as u32,
        };
        return;
    }
    let (mut cmin, mut cmax) = ([i32::MAX; 3], [i32::MIN; 3]);
    for e in &entries[lo..hi] {
        for k in 0..3 {
            let c = e.bounds.centre2(k);
            cmin[k] = cmin[k].min(c);
            cmax[k] = cmax[k].max(c);
        }
    }
    let axis = (0..3).max_by_key(|&k| cmax[k] - cmin[k]).unwrap_or(0);
    let mid = lo + (hi - lo) / 2;
    entries[lo..hi].select_nth_unstable_by_key(mid - lo, |e| e.bounds.centre2(axis));
    let left = nodes.len();
    for _ in 0..2 {
        nodes.push(Node {
            bounds,
            first: 0,
            count: 0,
        });
    }
    nodes[at] = Node {
        bounds,
        first: left as u32,
        count: 0,
    };
    build(entries, nodes, left, lo, mid);
    build(entries, nodes, left + 1, mid, hi);
}

/// The hierarchy over the path pieces of one object index: built blocks and the pending list.
#[derive(Debug, Clone)]
pub struct PathBvh {
    /// Pieces a block is built from ([`BLOCK`]; smaller in tests).
    block: usize,
    blocks: Vec<Block>,
    /// Inserted since the last block was built.
    pending: Vec<Entry>,
    /// The grid of the pending pieces (`None` when there are none): the next block's.
    grid: Option<Grid>,
    /// Largest radius inserted (for the vertex box of the inflated frustum).
    max_radius: f64,
    /// Most pieces one path has added (what the next one is expected to add, for
    /// [`growth_bytes`](Self::growth_bytes)).
    most_pieces: usize,
}

impl Default for PathBvh {
    fn default() -> Self {
        PathBvh {
            block: BLOCK,
            blocks: Vec::new(),
            pending: Vec::new(),
            grid: None,
            max_radius: 0.0,
            most_pieces: 0,
        }
    }
}

impl PathBvh {
    /// A hierarchy whose blocks are built from `block` pieces (at least 1; tests use small
    /// blocks so that small stores hold many).
    pub(crate) fn with_block(block: usize) -> PathBvh {
        PathBvh {
            block: block.max(1),
            ..PathBvh::default()
        }
    }

    /// Adds `world`'s path with its never-miss radius (NaN: unknown, taken as +∞, so the path is
    /// never pruned), cut into pieces of [`PIECE_SEGMENTS`] segments. A one-vertex path is one
    /// degenerate segment, as [`IndexedObject::segment_count`] counts it. When the path's
    /// pieces would take the pending list past [`BLOCK`], the list is built into a block first
    /// (the only work an insertion does beyond its own pieces).
    pub fn insert(&mut self, world: u32, path: &IndexedObject) {
        let radius = if path.radius.is_nan() {
            f64::INFINITY
        } else {
            path.radius.max(0.0)
        };
        let segments = path.segment_count();
        let pieces = segments.div_ceil(PIECE_SEGMENTS);
        if !self.pending.is_empty() && self.pending.len() + pieces > self.block {
            self.seal();
        }
        self.max_radius = self.max_radius.max(radius);
        let mut grid = *self.grid.get_or_insert_with(|| Grid {
            origin: path.vertex(0).0.map(f64::round),
            exp: BOX_GRID_EXP,
        });
        let mut span = Vec::with_capacity(PIECE_SEGMENTS + 1);
        for first in (0..segments).step_by(PIECE_SEGMENTS) {
            let count = PIECE_SEGMENTS.min(segments - first);
            span.clear();
            span.extend((first..=first + count).map(|i| path.vertex(i).0));
            let Some(b) = Aabb::of_points(&span, radius) else {
                continue;
            };
            let bounds = match grid.encode(&b) {
                Some(bounds) => bounds,
                None => {
                    // Beyond the grid's reach: the coarsest grid (up to the limit) that holds it,
                    // every pending box rounded outward to it; else an infinite side.
                    let mut coarser = grid;
                    while coarser.exp < BOX_GRID_MAX_EXP && coarser.encode(&b).is_none() {
                        coarser.exp += 1;
                    }
                    if coarser.encode(&b).is_some() {
                        self.coarsen(coarser.exp);
                        grid = coarser;
                    }
                    grid.encode_clamped(&b)
                }
            };
            let last = first + count >= segments;
            self.pending.push(Entry {
                bounds,
                t0: time_code_down(path.vertex(first).1),
                t1: if last {
                    u16::MAX
                } else {
                    time_code_up(path.vertex(first + count).1)
                },
                world,
                piece: (first / PIECE_SEGMENTS) as u32 | if last { LAST } else { 0 },
            });
        }
        self.most_pieces = self.most_pieces.max(pieces.max(1));
    }

    /// Builds the pending pieces into a block of their own.
    fn seal(&mut self) {
        let Some(grid) = self.grid.take() else {
            return;
        };
        // A copy of exactly the pieces' size; the pending list keeps its room for the next.
        let entries: Box<[Entry]> = self.pending.drain(..).collect();
        self.blocks.extend(Block::build(grid, entries));
    }

    /// Bytes that [`heap_bytes`](Self::heap_bytes) may grow by, beyond the new pieces' own,
    /// when the next path is inserted: the pending list doubling its capacity, or a block being
    /// built (its nodes, and the block list doubling). A store admits a world only if this fits
    /// under its cap too, so that a vector's doubling never carries it past the cap.
    pub fn growth_bytes(&self) -> usize {
        let k = 2 * self.most_pieces.max(1);
        let entry = std::mem::size_of::<Entry>();
        let mut grow = 0;
        if self.pending.len() + k > self.pending.capacity() {
            grow += self.pending.capacity().max(k).max(4) * entry;
        }
        if self.pending.len() + k > self.block {
            // The pieces move from the pending list (which keeps its room) into the block, and
            // a block has fewer nodes than pieces.
            grow += self.pending.len() * (entry + std::mem::size_of::<Node>());
            if self.blocks.len() == self.blocks.capacity() {
                grow += self.blocks.capacity().max(4) * std::mem::size_of::<Block>();
            }
        }
        grow
    }

    /// Doubles the pending grid's step until its exponent is `exp`, every pending box rounded
    /// outward (built blocks keep their grids).
    fn coarsen(&mut self, exp: i32) {
        let Some(grid) = self.grid.as_mut() else {
            return;
        };
        while grid.exp < exp {
            grid.exp += 1;
            for e in &mut self.pending {
                e.bounds = e.bounds.coarsened();
            }
        }
    }

    /// Removes every piece of `world`: the blocks that held one are built again without them
    /// (a world is replaced rarely: when it is sampled again).
    pub fn remove(&mut self, world: u32) {
        let mut i = 0;
        while i < self.blocks.len() {
            let b = &self.blocks[i];
            let held = (b.worlds.0..=b.worlds.1).contains(&world)
                && b.entries.iter().any(|e| e.world == world);
            if !held {
                i += 1;
                continue;
            }
            let kept: Box<[Entry]> = b
                .entries
                .iter()
                .filter(|e| e.world != world)
                .cloned()
                .collect();
            match Block::build(b.grid, kept) {
                Some(rebuilt) => {
                    self.blocks[i] = rebuilt;
                    i += 1;
                }
                None => {
                    self.blocks.remove(i);
                }
            }
        }
        self.pending.retain(|e| e.world != world);
        if self.pending.is_empty() {
            self.grid = None;
        }
    }

    /// Pieces held.
    pub fn len(&self) -> usize {
        self.blocks.iter().map(|b| b.entries.len()).sum::<usize>() + self.pending.len()
    }

    pub fn is_empty(&self) -> bool {
        self.blocks.is_empty() && self.pending.is_empty()
    }

    pub fn heap_bytes(&self) -> usize {
        self.blocks.capacity() * std::mem::size_of::<Block>()
            + self.blocks.iter().map(Block::heap_bytes).sum::<usize>()
            + self.pending.capacity() * std::mem::size_of::<Entry>()
    }

    /// Largest radius of any piece inserted: a query's `region_box` must bound the frustum
    /// inflated by at least this.
    pub fn max_radius(&self) -> f64 {
        self.max_radius
    }

    /// The whole hierarchy as at least `at_least` shares where it is big enough (the blocks,
    /// split into subtrees near their tops while there are too few, then runs of up to 256
    /// pending pieces), for threads to take one at a time.
    pub fn parts(&self, at_least: usize) -> Vec<Part> {
        let mut level: Vec<(u32, u32)> = (0..self.blocks.len() as u32).map(|b| (b, 0)).collect();
        while level.len() < at_least {
            let mut next = Vec::with_capacity(2 * level.len());
            let mut split = false;
            for &(b, i) in &level {
                let n = &self.blocks[b as usize].nodes[i as usize];
                if n.count == 0 {
                    next.extend([(b, n.first), (b, n.first + 1)]);
                    split = true;
                } else {
                    next.push((b, i));
                }
            }
            level = next;
            if !split {
                break;
            }
        }
        let mut parts: Vec<Part> = level
            .into_iter()
            .map(|(block, node)| Part::Subtree { block, node })
            .collect();
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
    pub fn query<'s>(
        &'s self,
        part: Part,
        frustum: &Frustum,
        region_box: Option<&Aabb>,
        window: Option<TimeWindow>,
        skip: impl Fn(u32) -> bool,
        mut visit: impl FnMut(Piece<'s>),
    ) {
        let (grid, entries, nodes, root) = match part {
            Part::Subtree { block, node } => {
                let Some(b) = self.blocks.get(block as usize) else {
                    return;
                };
                if b.nodes.get(node as usize).is_none() {
                    return;
                }
                (b.grid, &b.entries[..], &b.nodes[..], Some(node as usize))
            }
            Part::Pending { start, end } => {
                let Some(grid) = self.grid else {
                    return;
                };
                let end = (end as usize).min(self.pending.len());
                let run = self.pending.get(start as usize..end).unwrap_or_default();
                (grid, run, &[][..], None)
            }
        };
        let on_grid = GridTest::new(grid, frustum.planes(), region_box);
        let test = |b: &GridBox, mask: u8| on_grid.classify(b, mask);
        let mut leaf = |entry: &'s Entry, mask: u8| {
            if window
                .is_some_and(|w| time_to(entry.t1) < w.start() || time_from(entry.t0) > w.end())
                || skip(entry.world)
            {
                return;
            }
            // Below a node inside every plane, every box is too: no test needed.
            if mask == 0 {
                visit(Piece { entry, mask });
            } else if let Some(mask) = test(&entry.bounds, mask) {
                visit(Piece { entry, mask });
            }
        };
        let Some(root) = root else {
            for e in entries {
                leaf(e, ALL_PLANES);
            }
            return;
        };
        let mut stack = vec![(root, ALL_PLANES)];
        while let Some((i, mask)) = stack.pop() {
            let node = &nodes[i];
            let mask = if mask == 0 {
                0
            } else if let Some(mask) = test(&node.bounds, mask) {
                mask
            } else {
                continue;
            };
            if node.count > 0 {
                let (a, n) = (node.first as usize, node.count as usize);
                for e in &entries[a..a + n] {
                    leaf(e, mask);
                }
            } else {
                stack.push((node.first as usize + 1, mask));
                stack.push((node.first as usize, mask));
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

    impl PathBvh {
        /// Every stored piece with the grid its box is on: the blocks', then the pending ones.
        fn stored(&self) -> Vec<(Grid, &Entry)> {
            let mut out: Vec<(Grid, &Entry)> = Vec::new();
            for b in &self.blocks {
                out.extend(b.entries.iter().map(|e| (b.grid, e)));
            }
            if let Some(grid) = self.grid {
                out.extend(self.pending.iter().map(|e| (grid, e)));
            }
            out
        }

        /// The grids in use: each block's, and the pending list's.
        fn grids(&self) -> Vec<Grid> {
            self.blocks
                .iter()
                .map(|b| b.grid)
                .chain(self.grid)
                .collect()
        }
    }

    /// Random-walk paths of 1 to 40 vertices on a 120 Hz frame grid, radii from 0 to 5 cm (one
    /// unknown, NaN), stored as the index stores them.
    fn paths(rng: &mut WorldRng, n: u32) -> Vec<IndexedObject> {
        spread_paths(rng, n, 10.0)
    }

    /// [`paths`] starting up to `spread` metres from the origin sideways.
    fn spread_paths(rng: &mut WorldRng, n: u32, spread: f64) -> Vec<IndexedObject> {
        (0..n)
            .map(|i| {
                let mut p = [
                    rng.uniform(-spread, spread),
                    rng.uniform(0.0, 3.0),
                    rng.uniform(-spread, spread),
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
                            let first = p.first_segment();
                            let count = PIECE_SEGMENTS.min(path.segment_count() - first);
                            for i in first..=first + count {
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
    /// test of the pieces' segments keep exactly the worlds a segment-by-segment test of the
    /// whole path against the inflated frustum keeps — whatever the block size, a removal, and
    /// however the work is split.
    #[test]
    fn pieces_keep_exactly_the_worlds_brute_force_keeps() {
        let mut rng = WorldRng::new(3, Stream::Scene);
        let paths = paths(&mut rng, 3000);
        for block in [BLOCK, 700] {
            keeps_exactly_what_brute_force_keeps(&mut rng, &paths, 10.0, block);
        }
    }

    /// The same over paths spread across 1.2 km, and two far beyond the grid's reach (50 km
    /// away): the grid's step doubles up to [`BOX_GRID_MAX_EXP`] as the paths come, and the
    /// far pieces get infinite sides — still exactly brute force's answer.
    #[test]
    fn a_grid_grown_or_out_of_reach_still_keeps_exactly_what_brute_force_keeps() {
        let mut rng = WorldRng::new(4, Stream::Scene);
        let mut paths = spread_paths(&mut rng, 1500, 1.0);
        paths.extend(spread_paths(&mut rng, 1500, 600.0));
        for w in [1700, 2900] {
            let p = paths[w].polyline();
            let far = p
                .points()
                .iter()
                .map(|v| [v[0] + 5e4, v[1], v[2] - 5e4])
                .collect();
            let far = Polyline::new(p.times().to_vec(), far).unwrap_or_else(|e| panic!("{e}"));
            paths[w] =
                IndexedObject::new(&far, DT, paths[w].radius).unwrap_or_else(|e| panic!("{e}"));
        }
        let mut bvh = PathBvh::with_block(1000);
        for (w, path) in paths.iter().enumerate() {
            bvh.insert(w as u32, path);
        }
        let grids = bvh.grids();
        // The first blocks hold only the paths near the origin: the finest grid; the later
        // ones are coarsened, as far as allowed where the far paths are.
        assert_eq!(grids[0].exp, BOX_GRID_EXP);
        assert!(grids.iter().any(|g| g.exp == BOX_GRID_MAX_EXP));
        assert!(grids.iter().all(|g| g.exp <= BOX_GRID_MAX_EXP));
        assert!(
            bvh.stored()
                .iter()
                .any(|(_, e)| e.bounds.lo.contains(&i16::MIN) || e.bounds.hi.contains(&i16::MAX)),
            "some pieces beyond reach"
        );
        assert_boxes_hold_their_pieces(&bvh, &paths);
        keeps_exactly_what_brute_force_keeps(&mut rng, &paths, 10.0, 1000);
    }

    /// [`GridTest::classify`] answers what decoding the box, testing it against the region box
    /// and classifying it against the planes answers: over every stored box of paths spread
    /// across a kilometre (grids of several steps, boxes with infinite sides), against
    /// oblique frustums (rotated boxes: every normal has all three components) near the paths
    /// and far out of the grids' reach, under four plane masks.
    #[test]
    fn boxes_are_tested_on_their_grid_as_decoded() {
        let mut rng = WorldRng::new(8, Stream::Scene);
        let mut paths = spread_paths(&mut rng, 600, 1.0);
        paths.extend(spread_paths(&mut rng, 600, 500.0));
        let mut bvh = PathBvh::with_block(300);
        for (w, path) in paths.iter().enumerate() {
            bvh.insert(w as u32, path);
        }
        let stored = bvh.stored();
        let (mut outside, mut spared, mut infinite) = (0usize, 0usize, 0usize);
        for q in 0..60 {
            // A random orthonormal frame (Gram–Schmidt of two random directions).
            let mut random_dir = || {
                let v = [0, 1, 2].map(|_| rng.uniform(-1.0, 1.0));
                let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-3);
                v.map(|x| x / n)
            };
            let e0 = random_dir();
            let v = random_dir();
            let along = e0[0] * v[0] + e0[1] * v[1] + e0[2] * v[2];
            let e1 = [0, 1, 2].map(|k| v[k] - along * e0[k]);
            let n1 = (e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2]).sqrt();
            let e1 = e1.map(|x| x / n1);
            let e2 = [
                e0[1] * e1[2] - e0[2] * e1[1],
                e0[2] * e1[0] - e0[0] * e1[2],
                e0[0] * e1[1] - e0[1] * e1[0],
            ];
            let (c, half) = random_box(&mut rng, if q % 10 == 9 { 1e6 } else { 3.0 });
            let mut planes = [Plane {
                normal: [0.0; 3],
                offset: 0.0,
            }; 6];
            for (i, u) in [e0, e1, e2].into_iter().enumerate() {
                let along = u[0] * c[0] + u[1] * c[1] + u[2] * c[2];
                planes[2 * i] = Plane {
                    normal: u,
                    offset: along + half[i],
                };
                planes[2 * i + 1] = Plane {
                    normal: u.map(|x| -x),
                    offset: -along + half[i],
                };
            }
            let frustum = Frustum::from_planes(planes).unwrap_or_else(|e| panic!("{e}"));
            let region = region_box(&frustum);
            for (grid, entry) in &stored {
                let on_grid = GridTest::new(*grid, frustum.planes(), region.as_ref());
                let b = &entry.bounds;
                infinite += usize::from(b.lo.contains(&i16::MIN) || b.hi.contains(&i16::MAX));
                for mask in [ALL_PLANES, 0b10_1101, 0b00_0110, 0] {
                    let decoded = grid.decode(b);
                    let want = if region.as_ref().is_some_and(|r| decoded.disjoint(r)) {
                        None
                    } else {
                        decoded.classify(frustum.planes(), mask)
                    };
                    assert_eq!(on_grid.classify(b, mask), want, "query {q}, mask {mask:#b}");
                    outside += usize::from(want.is_none());
                    spared += usize::from(want.is_some_and(|m| m != mask));
                }
            }
        }
        assert!(
            outside > 1000 && spared > 1000,
            "{outside} outside, {spared} spared"
        );
        assert!(infinite > 0, "boxes with infinite sides are tested");
    }

    /// Every stored piece's box, decoded, holds each of its vertices grown by the path's
    /// radius along every axis, and its time range holds the piece's vertex times (the last
    /// piece's to +∞); each path's pieces are all there, once, the last one marked.
    fn assert_boxes_hold_their_pieces(bvh: &PathBvh, paths: &[IndexedObject]) {
        let mut seen = vec![Vec::new(); paths.len()];
        for (grid, e) in bvh.stored() {
            let path = &paths[e.world as usize];
            let piece = Piece { entry: e, mask: 0 };
            let first = piece.first_segment();
            let segments = path.segment_count();
            let count = PIECE_SEGMENTS.min(segments - first);
            assert_eq!(piece.is_last(), first + count >= segments);
            seen[e.world as usize].push(first);
            let b = grid.decode(&e.bounds);
            let r = if path.radius.is_nan() {
                f64::INFINITY
            } else {
                path.radius
            };
            for i in first..=first + count {
                let (v, t) = path.vertex(i);
                for k in 0..3 {
                    assert!(
                        b.min[k] <= v[k] - r && v[k] + r <= b.max[k],
                        "{v:?} ± {r}: {b:?}"
                    );
                }
                assert!(time_from(e.t0) <= t && t <= time_to(e.t1), "{t} in {e:?}");
            }
            if piece.is_last() {
                assert_eq!(time_to(e.t1), f64::INFINITY);
            }
        }
        for (w, firsts) in seen.iter_mut().enumerate() {
            firsts.sort_unstable();
            let want: Vec<usize> = (0..paths[w].segment_count())
                .step_by(PIECE_SEGMENTS)
                .collect();
            assert_eq!(*firsts, want, "path {w}");
        }
    }

    /// Boxes survive block builds and coarsenings unchanged or grown, never shrunk below their
    /// pieces: checked after every 100 insertions of paths spreading ever wider.
    #[test]
    fn boxes_hold_their_pieces_through_blocks_and_coarsening() {
        let mut rng = WorldRng::new(6, Stream::Scene);
        let mut paths = Vec::new();
        let mut bvh = PathBvh::with_block(500);
        for round in 0..12 {
            let spread = 2f64.powi(round);
            for path in spread_paths(&mut rng, 100, spread) {
                bvh.insert(paths.len() as u32, &path);
                paths.push(path);
            }
            assert_boxes_hold_their_pieces(&bvh, &paths);
            // Each grid is the finest whose reach (±2¹⁵ steps) holds its pieces, up to the
            // limit: the pending pieces are from this round or earlier ones.
            assert!(bvh.grids().iter().all(|g| g.exp <= BOX_GRID_MAX_EXP));
            let grid = bvh.grid.unwrap_or_else(|| panic!("a grid"));
            if spread + 5.0 < 2f64.powi(15 + BOX_GRID_EXP - 1) {
                assert_eq!(grid.exp, BOX_GRID_EXP, "round {round}");
            }
        }
        assert!(bvh.blocks.len() >= 5, "{} blocks", bvh.blocks.len());
    }

    /// Ingest never rebuilds: a block, once built, stays where it is, unchanged, however many
    /// paths come after it; each holds at most a block's pieces (a path is never split across
    /// blocks); a removal rebuilds only the blocks that held the world.
    #[test]
    fn blocks_are_built_once_and_never_merged() {
        let mut rng = WorldRng::new(9, Stream::Scene);
        let paths = paths(&mut rng, 2000);
        let mut bvh = PathBvh::with_block(256);
        let mut built: Vec<(*const Entry, usize)> = Vec::new();
        for (w, path) in paths.iter().enumerate() {
            bvh.insert(w as u32, path);
            let now: Vec<(*const Entry, usize)> = bvh
                .blocks
                .iter()
                .map(|b| (b.entries.as_ptr(), b.entries.len()))
                .collect();
            assert!(now.len() <= built.len() + 1, "one block at most per path");
            assert_eq!(now[..built.len()], built[..], "built blocks untouched");
            built = now;
            assert!(bvh.pending.len() <= 256);
        }
        assert!(bvh.blocks.len() > 20, "{} blocks", bvh.blocks.len());
        for b in &bvh.blocks {
            assert!(b.entries.len() <= 256);
            let mut worlds: Vec<u32> = b.entries.iter().map(|e| e.world).collect();
            worlds.sort_unstable();
            worlds.dedup();
            // Whole paths: every piece of each world it holds.
            for w in worlds {
                let want = paths[w as usize].segment_count().div_ceil(PIECE_SEGMENTS);
                assert_eq!(b.entries.iter().filter(|e| e.world == w).count(), want);
            }
        }
        let before = bvh.len();
        let held = bvh
            .blocks
            .iter()
            .position(|b| b.entries.iter().any(|e| e.world == 1000))
            .unwrap_or_else(|| panic!("world 1000 is in a block"));
        bvh.remove(1000);
        assert_eq!(
            bvh.len(),
            before - paths[1000].segment_count().div_ceil(PIECE_SEGMENTS)
        );
        for (i, b) in bvh.blocks.iter().enumerate() {
            assert_eq!(i == held, b.entries.as_ptr() != built[i].0, "block {i}");
        }
        assert!(bvh.stored().iter().all(|(_, e)| e.world != 1000));
    }

    /// Time codes round outward: a start code never reads later than the time, an end code
    /// never earlier, and beyond reach they read as −∞ and +∞.
    #[test]
    fn time_codes_round_outward() {
        let mut rng = WorldRng::new(8, Stream::Scene);
        for _ in 0..10_000 {
            let t = rng.uniform(0.0, 1100.0);
            assert!(time_from(time_code_down(t)) <= t, "{t}");
            assert!(time_to(time_code_up(t)) >= t, "{t}");
        }
        assert_eq!(time_from(time_code_down(0.01)), f64::NEG_INFINITY);
        assert_eq!(time_to(time_code_up(2000.0)), f64::INFINITY);
        assert_eq!(time_from(time_code_down(2000.0)), 65534.0 * TIME_STEP_S);
    }

    /// The random boxes and windows of the brute-force comparison, around paths within
    /// `spread` metres of the origin.
    /// A random box's centre (within `spread` across, 0–3 m up) and half extents.
    fn random_box(rng: &mut WorldRng, spread: f64) -> ([f64; 3], [f64; 3]) {
        let c = [
            rng.uniform(-spread, spread),
            rng.uniform(0.0, 3.0),
            rng.uniform(-spread, spread),
        ];
        let h = [
            rng.uniform(0.01, 3.0),
            rng.uniform(0.01, 1.0),
            rng.uniform(0.01, 3.0),
        ];
        (c, h)
    }

    fn keeps_exactly_what_brute_force_keeps(
        rng: &mut WorldRng,
        paths: &[IndexedObject],
        spread: f64,
        block: usize,
    ) {
        let mut bvh = PathBvh::with_block(block);
        // A removal rebuilds the block that held the world; the last paths then wait in the
        // pending list.
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
            !bvh.pending.is_empty() && bvh.blocks.len() >= 2,
            "blocks and the pending list are tested"
        );
        let splits = [bvh.parts(1), bvh.parts(5), bvh.parts(64)];
        assert!(splits[2].len() >= 64);
        let (mut kept, mut windowed) = (0, 0);
        for q in 0..300 {
            let (c, h) = random_box(rng, spread);
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
                    touched(&bvh, parts, &frustum, window, paths),
                    truth,
                    "query {q}"
                );
            }
        }
        assert!(
            kept > 50 && windowed > 50,
            "kept {kept}, windowed {windowed}"
        );
    }

    /// Split any way, the parts hand over every piece exactly once (a region holding
    /// everything prunes nothing).
    #[test]
    fn parts_cover_every_piece_once() {
        let mut rng = WorldRng::new(5, Stream::Scene);
        let mut bvh = PathBvh::with_block(400);
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
