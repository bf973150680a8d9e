//! A world's browsing index (§4.4.2–4.4.3): per object, the low-resolution polyline stored
//! compactly (grid-rounded vertices, the rounding folded into the never-miss inflation
//! radius), and the ranking metrics computed once from the full-rate decoded motion. Pure: no
//! bus, no clock.
//!
//! A store holds these; a sampler builds them too ([`index_motion`] on the segments it sends,
//! the function a store would run) and sends them beside the world's summary
//! ([`IndexedWorld::to_wire`]), so that a store only checks and inserts them
//! ([`IndexedWorld::from_wire`]): decoding and simplifying were most of a store's work a world.

use mwb_codec::WorldReader;
use mwb_core::browse::api::{RefineStep, Refined};
use mwb_core::browse::{
    ALL_PLANES, Frustum, ObjectMetrics, PackedMetrics, Polyline, RestThresholds, TimeWindow, Track,
    WorldMetrics, rest_entry, segment_entry,
};
use mwb_proto::v1::{
    Encoding, IndexedPaths, Job, MotionSegment, ObjectIndex, ObjectPath, WorldDone, WorldIndex,
};
use std::sync::Arc;

/// What indexing needs from a job's scene: its rest thresholds (for the time-to-rest metric)
/// and its body names in object-index order (so that browsing can name objects). Read once per
/// job.
#[derive(Debug, Clone, PartialEq)]
pub struct JobScene {
    pub rest: RestThresholds,
    /// Empty when the scene could not be read here.
    pub bodies: Arc<[String]>,
}

impl Default for JobScene {
    /// The scene defaults' thresholds and no names.
    fn default() -> Self {
        Self {
            rest: RestThresholds::from(&mwb_core::scene::Settings::default()),
            bodies: Arc::from(Vec::new()),
        }
    }
}

impl JobScene {
    /// From the job's scene text; the defaults if it does not parse here.
    pub fn of(job: &Job) -> Self {
        job.scene
            .as_ref()
            .and_then(|s| mwb_core::scene::SceneTemplate::parse(&s.toml, &s.name).ok())
            .map_or_else(Self::default, |t| Self {
                rest: RestThresholds::from(t.settings()),
                bodies: t.body_names().map(str::to_owned).collect(),
            })
    }
}

impl From<RestThresholds> for JobScene {
    /// Thresholds without names (benchmarks, tests).
    fn from(rest: RestThresholds) -> Self {
        Self {
            rest,
            ..Self::default()
        }
    }
}

/// Grid of stored path vertices, metres (2⁻¹⁰ m ≈ 0.98 mm): a vertex is stored as whole steps
/// of this grid from its path's lower corner, so the rounding moves it by at most √3/2 of a
/// step, 0.85 mm. That error is measured and added to the never-miss radius
/// ([`IndexedObject::new`]); the exact deviation of the rounded path that [`index_world`]
/// measures absorbs most of it (the radius already holds the 10 mm simplification tolerance).
/// A finer grid costs 3 bits a coordinate for every halving of the error (2⁻¹³ m: 9 bits a
/// vertex more, ~21 bytes a tumbling object's path, for 0.7 mm less radius).
pub const PATH_GRID_M: f64 = 1.0 / 1024.0;

/// Bytes of a stored path's header, before its packed vertices: the grid origin (3 × f32), the
/// frame interval (f64), the first vertex's frame (u32), the vertex count (u32), the grid
/// step's exponent (i8) and the bit widths of x, y, z and frame offset (4 × u8).
const HEADER: usize = 12 + 8 + 4 + 4 + 1 + 4;

/// Widest field of a packed vertex, bits (a coordinate in grid steps, or a frame offset).
const MAX_FIELD_BITS: u32 = 32;

/// Why a polyline could not be stored as an object's path.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PathError {
    #[error("frame interval {0} is not a positive number")]
    FrameDt(f64),
    #[error("vertex {vertex}: time {time} s is not a whole number of {frame_dt} s frames")]
    OffFrame {
        vertex: usize,
        time: f64,
        frame_dt: f64,
    },
    #[error("vertex {vertex}: a coordinate is not finite or too far from the path's origin")]
    TooFar { vertex: usize },
}

/// One object of an indexed world: its indexed polyline, stored compactly, and its never-miss
/// radius. This is the only copy of the path's vertices in the store: the per-object
/// hierarchies ([`crate::spatial`]) hold boxes that refer to it.
///
/// Layout (measured with `mwb bench query`, docs/performance.md): one allocation per path, a
/// [`HEADER`] of 33 bytes and then the vertices bit-packed at fixed widths chosen per path —
/// each coordinate as whole steps of a power-of-two grid ([`PATH_GRID_M`]) above the path's
/// lower corner, in as many bits as the path's extent along that axis needs, and the frame as
/// an offset from the first vertex's. A 3 s tumbling path (~2 m × 1 m × 2 m, 360 frames) packs
/// a vertex into ~42 bits, against 10 bytes as i16 steps of a 0.12 mm grid and a u32 frame and
/// 32 as an f64 point and time. Fixed widths keep vertex `i` one multiplication away, so a
/// hierarchy piece reads its few segments without decoding the path from its start.
#[derive(Debug, Clone, PartialEq)]
pub struct IndexedObject {
    /// Header and packed vertices ([`HEADER`]; [`Layout`] reads them).
    data: Box<[u8]>,
    /// Inflation for frustum tests, metres: the codec's error bound plus the largest distance
    /// between the full-rate decoded path and the indexed polyline plus the grid rounding of
    /// its vertices, so that a world whose true path enters a frustum is never missed (§4.4.2
    /// tests the low-res path conservatively); rounded up to [`PATH_RADIUS_STEP_M`]. NaN:
    /// unknown (never pruned).
    pub radius: f64,
}

/// A stored path's header, read once per test so that the vertex loop only unpacks bits.
#[derive(Debug, Clone, Copy)]
struct Layout {
    origin: [f64; 3],
    step: f64,
    frame_dt: f64,
    first_frame: u32,
    len: usize,
    /// Bit widths of x, y, z and the frame offset, and their sum (bits a vertex).
    widths: [u32; 4],
    stride: usize,
}

/// `2^exp` for the exponents a path grid can have (normal f64 numbers).
fn pow2(exp: i32) -> f64 {
    f64::from_bits(((exp + 1023) as u64) << 52)
}

/// Bits needed to write `v` (0 for 0).
fn bit_width(v: u32) -> u32 {
    u32::BITS - v.leading_zeros()
}

/// The 64 bits of `packed` from byte `bit / 8` on (zeros past the end), shifted so that bit
/// `bit` comes first: at least 57 bits from `bit` on, least significant first.
#[inline]
fn read_word(packed: &[u8], bit: usize) -> u64 {
    let byte = bit / 8;
    let word = match packed.get(byte..byte + 8) {
        Some(w) => u64::from_le_bytes([w[0], w[1], w[2], w[3], w[4], w[5], w[6], w[7]]),
        None => {
            let mut buf = [0u8; 8];
            let tail = packed.get(byte..).unwrap_or_default();
            buf[..tail.len()].copy_from_slice(tail);
            u64::from_le_bytes(buf)
        }
    };
    word >> (bit % 8)
}

/// The low `width` (≤ 32) bits of `word`.
#[inline]
fn low_bits(word: u64, width: u32) -> u32 {
    (word & ((1u64 << width) - 1)) as u32
}

/// Appends bit fields to a byte vector, least significant bit first.
struct BitWriter {
    bytes: Vec<u8>,
    /// Bits not yet written out (the low `pending` bits of `acc`).
    acc: u64,
    pending: u32,
}

impl BitWriter {
    /// Appends the low `width` (≤ 32) bits of `value`.
    fn push(&mut self, value: u32, width: u32) {
        if width == 0 {
            return;
        }
        self.acc |= u64::from(value & (u32::MAX >> (32 - width))) << self.pending;
        self.pending += width;
        while self.pending >= 8 {
            self.bytes.push(self.acc as u8);
            self.acc >>= 8;
            self.pending -= 8;
        }
    }

    fn finish(mut self) -> Vec<u8> {
        if self.pending > 0 {
            self.bytes.push(self.acc as u8);
        }
        self.bytes
    }
}

impl Layout {
    fn of(data: &[u8]) -> Layout {
        let f32_at = |i: usize| {
            f64::from(f32::from_le_bytes([
                data[i],
                data[i + 1],
                data[i + 2],
                data[i + 3],
            ]))
        };
        let u32_at =
            |i: usize| u32::from_le_bytes([data[i], data[i + 1], data[i + 2], data[i + 3]]);
        let mut dt = [0u8; 8];
        dt.copy_from_slice(&data[12..20]);
        let widths = [
            u32::from(data[29]),
            u32::from(data[30]),
            u32::from(data[31]),
            u32::from(data[32]),
        ];
        Layout {
            origin: [f32_at(0), f32_at(4), f32_at(8)],
            frame_dt: f64::from_le_bytes(dt),
            first_frame: u32_at(20),
            len: u32_at(24) as usize,
            step: pow2(i32::from(data[28] as i8)),
            widths,
            stride: widths.iter().sum::<u32>() as usize,
        }
    }

    /// Vertex `i` (clamped to the last) of the packed vertices `packed`: position and time.
    /// A vertex of up to 57 bits (every tumbling path's) is read as one word.
    #[inline]
    fn vertex(&self, packed: &[u8], i: usize) -> ([f64; 3], f64) {
        let fields = self.fields(packed, i);
        (
            [0, 1, 2].map(|k| decode_coordinate(self.origin[k], self.step, fields[k])),
            f64::from(self.first_frame + fields[3]) * self.frame_dt,
        )
    }

    /// Vertex `i`'s (clamped to the last) packed fields: x, y, z steps and frame offset.
    #[inline]
    fn fields(&self, packed: &[u8], i: usize) -> [u32; 4] {
        let bit = i.min(self.len - 1) * self.stride;
        let mut fields = [0u32; 4];
        if self.stride <= 57 {
            let mut word = read_word(packed, bit);
            for (f, &w) in fields.iter_mut().zip(&self.widths) {
                *f = low_bits(word, w);
                word >>= w;
            }
        } else {
            let mut at = bit;
            for (f, &w) in fields.iter_mut().zip(&self.widths) {
                *f = low_bits(read_word(packed, at), w);
                at += w as usize;
            }
        }
        fields
    }
}

impl IndexedObject {
    /// Stores `path` (its times whole multiples of `frame_dt`, from 0) with never-miss radius
    /// `radius` for the path as given: the vertices are rounded to the grid, and the largest
    /// distance a vertex moved is added to the radius before it is rounded up to
    /// [`PATH_RADIUS_STEP_M`]. Between vertices the stored path is within that distance of the
    /// given one too (both are linear in time between the same vertex times), so whatever the
    /// radius bounded still lies within the new radius of the stored path.
    pub fn new(path: &Polyline, frame_dt: f64, radius: f64) -> Result<Self, PathError> {
        if !(frame_dt.is_finite() && frame_dt > 0.0) {
            return Err(PathError::FrameDt(frame_dt));
        }
        let points = path.points();
        let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        for p in points {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        // The lower corner, rounded down to f32, so that every step count is ≥ 0 (up to the
        // rounding to the nearest step).
        let origin = lo.map(|v| {
            let o = v as f32;
            if f64::from(o) > v { o.next_down() } else { o }
        });
        // The finest power-of-two step at or above PATH_GRID_M at which every vertex is within
        // MAX_FIELD_BITS of the origin (a step above 2⁶⁴ m would fail the range check below:
        // coordinates that large are refused).
        let reach = (0..3)
            .map(|k| hi[k] - f64::from(origin[k]))
            .fold(0.0f64, f64::max);
        let mut step_exp = PATH_GRID_M.log2() as i32;
        while reach / pow2(step_exp) > f64::from(u32::MAX - 1) && step_exp < 64 {
            step_exp += 1;
        }
        let step = pow2(step_exp);
        let mut steps = Vec::with_capacity(points.len());
        let mut frames = Vec::with_capacity(points.len());
        let mut moved = 0.0f64;
        for (vertex, (p, &t)) in points.iter().zip(path.times()).enumerate() {
            let mut s = [0u32; 3];
            let mut d2 = 0.0;
            for k in 0..3 {
                let v = ((p[k] - f64::from(origin[k])) / step).round();
                // (NaN is refused too: it fails the range test.)
                if !(0.0..=f64::from(u32::MAX)).contains(&v) {
                    return Err(PathError::TooFar { vertex });
                }
                s[k] = v as u32;
                let d = decode_coordinate(f64::from(origin[k]), step, s[k]) - p[k];
                d2 += d * d;
            }
            moved = moved.max(d2.sqrt());
            let f = (t / frame_dt).round();
            if !(0.0..=f64::from(u32::MAX)).contains(&f) || f * frame_dt != t {
                return Err(PathError::OffFrame {
                    vertex,
                    time: t,
                    frame_dt,
                });
            }
            steps.push(s);
            frames.push(f as u32);
        }
        // Times increase strictly (a polyline's invariant), so every offset is ≥ 0.
        let first_frame = frames.first().copied().unwrap_or(0);
        let mut widths = [0u32; 4];
        for (s, &f) in steps.iter().zip(&frames) {
            for k in 0..3 {
                widths[k] = widths[k].max(bit_width(s[k]));
            }
            widths[3] = widths[3].max(bit_width(f - first_frame));
        }
        let stride: u32 = widths.iter().sum();
        let mut header = Vec::with_capacity(HEADER + (steps.len() * stride as usize).div_ceil(8));
        header.extend(origin.iter().flat_map(|o| o.to_le_bytes()));
        header.extend(frame_dt.to_le_bytes());
        header.extend(first_frame.to_le_bytes());
        let len = u32::try_from(steps.len()).map_err(|_| PathError::TooFar {
            vertex: u32::MAX as usize,
        })?;
        header.extend(len.to_le_bytes());
        header.push(step_exp as i8 as u8);
        header.extend(widths.map(|w| w as u8));
        let mut bits = BitWriter {
            bytes: header,
            acc: 0,
            pending: 0,
        };
        for (s, &f) in steps.iter().zip(&frames) {
            for k in 0..3 {
                bits.push(s[k], widths[k]);
            }
            bits.push(f - first_frame, widths[3]);
        }
        debug_assert!(widths.iter().all(|&w| w <= MAX_FIELD_BITS));
        Ok(Self {
            data: bits.finish().into_boxed_slice(),
            radius: round_radius(radius + moved),
        })
    }

    fn layout(&self) -> Layout {
        Layout::of(&self.data)
    }

    /// A path as another node stored it ([`IndexedWorld::to_wire`]): `data` in this
    /// version's layout, checked so that every read of it stays in bounds and means a path —
    /// the header's frame interval is `frame_dt`, the grid step one [`new`](Self::new) can
    /// choose, every field at most 32 bits, the vertex count what the bytes hold, the origin
    /// finite, the vertex frames strictly increasing and below `frames`, and `radius` a
    /// distance.
    pub fn from_parts(
        data: Vec<u8>,
        radius: f64,
        frame_dt: f64,
        frames: u32,
    ) -> Result<Self, &'static str> {
        if !(radius.is_finite() && radius >= 0.0) {
            return Err("the radius is not a distance");
        }
        if data.len() < HEADER {
            return Err("shorter than a path's header");
        }
        let layout = Layout::of(&data);
        let exp = i32::from(data[28] as i8);
        if !(PATH_GRID_M.log2() as i32..=64).contains(&exp) {
            return Err("grid step out of range");
        }
        if layout.frame_dt.to_bits() != frame_dt.to_bits() {
            return Err("frame interval differs from the summary's");
        }
        if layout.widths.iter().any(|&w| w > MAX_FIELD_BITS) {
            return Err("a field wider than 32 bits");
        }
        if !layout.origin.iter().all(|o| o.is_finite()) {
            return Err("origin not finite");
        }
        if layout.len == 0 || data.len() - HEADER != (layout.len * layout.stride).div_ceil(8) {
            return Err("vertex count differs from the bytes");
        }
        let path = Self {
            data: data.into_boxed_slice(),
            radius,
        };
        let mut last: Option<u64> = None;
        for i in 0..layout.len {
            let frame =
                u64::from(layout.first_frame) + u64::from(layout.fields(path.packed(), i)[3]);
            if frame >= u64::from(frames) || last.is_some_and(|l| frame <= l) {
                return Err("vertex frames not increasing within the world");
            }
            last = Some(frame);
        }
        Ok(path)
    }

    /// The first byte of the stored path: a caller about to test many paths reads it for each
    /// first, so that their cache misses overlap instead of coming one after another.
    #[inline]
    pub fn header_byte(&self) -> u8 {
        self.data.first().copied().unwrap_or(0)
    }

    /// The first byte of vertex `i`'s packed bits (clamped to the last vertex), for the same
    /// purpose as [`header_byte`](Self::header_byte): the vertices of a piece past the first
    /// lie in another cache line than the header.
    #[inline]
    pub fn vertex_byte(&self, i: usize) -> u8 {
        let layout = self.layout();
        let bit = i.min(layout.len.saturating_sub(1)) * layout.stride;
        self.packed().get(bit / 8).copied().unwrap_or(0)
    }

    /// The packed vertices (after the header).
    fn packed(&self) -> &[u8] {
        &self.data[HEADER..]
    }

    /// The grid step of this path, metres.
    pub fn grid_step(&self) -> f64 {
        self.layout().step
    }

    /// The same path moved by `d` rounded to whole grid steps, the vertices untouched and the
    /// radius unchanged (a move by whole steps adds no rounding): `None` when the moved origin
    /// is not exact in f32 (far from the scene's origin, ~16 km at the finest grid).
    pub fn translated(&self, d: [f64; 3]) -> Option<Self> {
        let layout = self.layout();
        let mut data = self.data.clone();
        for k in 0..3 {
            let moved = layout.origin[k] + (d[k] / layout.step).round() * layout.step;
            let o = moved as f32;
            if f64::from(o) != moved {
                return None;
            }
            data[4 * k..4 * k + 4].copy_from_slice(&o.to_le_bytes());
        }
        Some(Self {
            data,
            radius: self.radius,
        })
    }

    /// Vertices (at least 1).
    pub fn len(&self) -> usize {
        self.layout().len
    }

    /// Always false: a path has at least one vertex.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Segments, as [`Polyline::segment_count`] counts them (one vertex: one degenerate).
    pub fn segment_count(&self) -> usize {
        self.len().saturating_sub(1).max(1)
    }

    /// Vertex `i` (clamped to the last) decoded: its position and time. Every reader — the
    /// hierarchies, the world-by-world test, `q/paths` — decodes with this one function, so
    /// all see the same f64 path.
    #[inline]
    pub fn vertex(&self, i: usize) -> ([f64; 3], f64) {
        self.layout().vertex(self.packed(), i)
    }

    /// The stored path as a polyline (allocates; for drawing, benchmarks and tests).
    pub fn polyline(&self) -> Polyline {
        let layout = self.layout();
        let (points, times) = (0..layout.len)
            .map(|i| layout.vertex(self.packed(), i))
            .unzip();
        // Times strictly increase and points are finite: they were checked when stored.
        Polyline::new(times, points).unwrap_or_else(|e| unreachable!("stored path: {e}"))
    }

    /// Exact test of segments `first..first + count`: the earliest time in `window` at which
    /// one is inside the planes of `region` in `mask` ([`segment_entry`], as brute force runs
    /// it), then, if `rest`, the final pose held after the end ([`rest_entry`]).
    pub fn entry_in(
        &self,
        first: usize,
        count: usize,
        rest: bool,
        region: &Frustum,
        mask: u8,
        window: Option<TimeWindow>,
    ) -> Option<f64> {
        let layout = self.layout();
        let packed = self.packed();
        let mut a = layout.vertex(packed, first);
        (first..first + count)
            .find_map(|i| {
                let b = layout.vertex(packed, i + 1);
                let hit = segment_entry(a.0, b.0, a.1, b.1, region, mask, window);
                a = b;
                hit
            })
            .or_else(|| {
                let (p, t) = layout.vertex(packed, layout.len - 1);
                rest.then(|| rest_entry(p, t, region, mask, window))
                    .flatten()
            })
    }

    /// The earliest time in `window` at which the stored path (its final pose held after the
    /// end) is inside `region`: [`Polyline::first_entry`] of [`polyline`](Self::polyline).
    pub fn first_entry(&self, region: &Frustum, window: Option<TimeWindow>) -> Option<f64> {
        self.entry_in(0, self.segment_count(), true, region, ALL_PLANES, window)
    }

    /// Whether the final pose is inside `region` (on the boundary counts).
    pub fn final_pose_inside(&self, region: &Frustum) -> bool {
        let (p, _) = self.vertex(self.len() - 1);
        region
            .clip_segment_masked(p, p, 0.0, 1.0, ALL_PLANES)
            .is_some()
    }

    /// Never-miss test: does the path come within `frustum` inflated by the radius during
    /// `window`?
    pub fn intersects(&self, frustum: &Frustum, window: Option<TimeWindow>) -> bool {
        self.first_entry(&frustum.inflated(self.radius), window)
            .is_some()
    }

    /// Heap bytes held (header and packed vertices).
    pub fn heap_bytes(&self) -> usize {
        self.data.len()
    }
}

/// `origin + steps × step`: one rounding (the product is exact, `step` a power of two and
/// `steps` below 2³²).
#[inline]
fn decode_coordinate(origin: f64, step: f64, steps: u32) -> f64 {
    origin + f64::from(steps) * step
}

/// A world as the browsing layer sees it.
///
/// One is held for every world a store keeps, so it is kept small (112 bytes beside its paths
/// and metrics): the job id is shared by the job's worlds (the shard interns it), the object
/// and metric lists are boxed slices, and the measurements only backward worlds have are
/// boxed apart.
#[derive(Debug, Clone)]
pub struct IndexedWorld {
    /// Global world index (see [`crate::ShardSpec`]).
    pub world: u32,
    pub job_id: Arc<str>,
    pub seed: u64,
    pub frames: u32,
    pub frame_dt: f64,
    pub rested: bool,
    /// Body names in object-index order, shared by every world of the job; empty if unknown.
    pub bodies: Arc<[String]>,
    pub objects: Box<[IndexedObject]>,
    /// Per object, the §4.4.3 ranking metrics (a slice, as rankings combine them), in f32
    /// ([`PackedMetrics`]: 36 bytes an object instead of 64).
    pub metrics: Box<[PackedMetrics]>,
    /// Per-world measurements from the world's summary (plausibility of backward worlds);
    /// `None` when the world has none of them (every forward world). Read through
    /// [`world_metrics`](Self::world_metrics).
    pub measured: Option<Box<WorldMetrics>>,
    /// A refined world's lineage (§4.5); `None` for sampled worlds.
    pub refined: Option<Box<Refined>>,
}

impl IndexedWorld {
    /// The per-world measurements (every field absent where the world has none).
    pub fn world_metrics(&self) -> &WorldMetrics {
        const NONE: &WorldMetrics = &WorldMetrics {
            energy_growth: None,
            angular_speed_growth: None,
            plausible: None,
            plausibility_excess: None,
        };
        self.measured.as_deref().unwrap_or(NONE)
    }

    /// Sets the per-world measurements, boxed only when one of them is present.
    pub fn set_world_metrics(&mut self, m: WorldMetrics) {
        self.measured = (m != WorldMetrics::default()).then(|| Box::new(m));
    }

    /// Heap bytes held by the index of this world beyond its own struct (paths, metrics,
    /// measurements, lineage), by capacity. The job id and body names are shared by the job's
    /// worlds and not counted here.
    pub fn heap_bytes(&self) -> usize {
        std::mem::size_of_val::<[IndexedObject]>(&self.objects)
            + std::mem::size_of_val::<[PackedMetrics]>(&self.metrics)
            + self
                .objects
                .iter()
                .map(IndexedObject::heap_bytes)
                .sum::<usize>()
            + self
                .measured
                .as_ref()
                .map_or(0, |_| std::mem::size_of::<WorldMetrics>())
            + self.refined.as_ref().map_or(0, |r| {
                std::mem::size_of::<Refined>()
                    + r.root_job.capacity()
                    + r.steps.capacity() * std::mem::size_of::<RefineStep>()
                    + r.steps
                        .iter()
                        .map(|s| s.objects.capacity() * std::mem::size_of::<u32>())
                        .sum::<usize>()
                    + r.active_from.capacity() * std::mem::size_of::<Option<u32>>()
            })
    }
}

impl IndexedWorld {
    /// The world's indexed paths as they travel on `q/paths` (for drawing): every object's
    /// polyline and radius exactly as the index holds them, so that a client testing a frustum
    /// against them gets the store's answer.
    pub fn paths_message(&self) -> IndexedPaths {
        IndexedPaths {
            world: self.world,
            job_id: self.job_id.to_string(),
            seed: self.seed,
            frames: self.frames,
            frame_dt: self.frame_dt,
            rested: self.rested,
            objects: self
                .objects
                .iter()
                .map(|o| {
                    let path = o.polyline();
                    ObjectPath {
                        times: path.times().to_vec(),
                        xyz: path.points().iter().flatten().copied().collect(),
                        radius: o.radius,
                    }
                })
                .collect(),
        }
    }
}

/// Why a world could not be indexed. Names the segment and what was wrong.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum IndexError {
    #[error("world has no summary")]
    NoSummary,
    #[error("world has no segments")]
    Empty,
    #[error("a refined world stored as a difference, without its parent")]
    NoParent,
    #[error("parent world {world}: {what}")]
    Parent { world: u32, what: String },
    #[error("frame_dt {0} is not a positive number")]
    FrameDt(f64),
    #[error("segment {seq}: {what}")]
    Segment { seq: u32, what: String },
    #[error("object {object}: {what}")]
    Object { object: usize, what: String },
    /// The store's own encoding of the world did not decode (a bug).
    #[error("{0}")]
    Stored(String),
}

/// Per-segment decoded motion and the payload's own error bound.
struct Decoded {
    tracks: Vec<mwb_codec::Track>,
    e_max: f64,
}

/// Largest position error of the interim quantised-frames payload: half a quantum per axis.
fn frames_e_max() -> f64 {
    0.5 * mwb_core::frames::POS_QUANTUM_M * 3f64.sqrt()
}

fn decode_segment(s: &MotionSegment) -> Result<Decoded, IndexError> {
    let err = |what: String| IndexError::Segment { seq: s.seq, what };
    match Encoding::try_from(s.encoding) {
        Ok(Encoding::SplineV1) => {
            let reader = WorldReader::new(&s.payload).map_err(|e| err(e.to_string()))?;
            if reader.object_count() != s.body_count as usize
                || reader.frame_count() != s.frame_count as usize
            {
                return Err(err(format!(
                    "payload holds {} bodies × {} frames, segment says {} × {}",
                    reader.object_count(),
                    reader.frame_count(),
                    s.body_count,
                    s.frame_count
                )));
            }
            let tracks = reader.decode_all().map_err(|e| err(e.to_string()))?;
            Ok(Decoded {
                tracks,
                e_max: reader.e_max(),
            })
        }
        Ok(Encoding::QuantisedFramesV1) => {
            let poses = mwb_core::frames::decode(&s.payload, s.frame_count, s.body_count)
                .map_err(|e| err(e.to_string()))?;
            let bodies = s.body_count as usize;
            let mut tracks = vec![mwb_codec::Track::default(); bodies];
            for (i, p) in poses.iter().enumerate() {
                let t = &mut tracks[i % bodies];
                t.positions.push(p.position);
                t.rotations.push(p.rotation);
            }
            Ok(Decoded {
                tracks,
                e_max: frames_e_max(),
            })
        }
        Ok(Encoding::Unspecified) | Err(_) => Err(err(format!("unknown encoding {}", s.encoding))),
    }
}

/// Default largest distance between an object's indexed polyline and its full-rate decoded
/// path, metres. Every box a user draws is widened by this plus the codec's e_max, so it is
/// the price of a smaller index in query precision.
pub const DEFAULT_PATH_TOLERANCE_M: f64 = 0.01;

/// Path radii are rounded up to a multiple of this, metres. A query inflates its frustum once
/// per distinct radius (with the inflated region's vertices, for the separating-axis test);
/// rounding leaves a handful of radii per query instead of one per path, and only widens the
/// never-miss margin, by at most half a millimetre.
pub const PATH_RADIUS_STEP_M: f64 = 0.0005;

/// `r` rounded up to [`PATH_RADIUS_STEP_M`] (never down: the margin must not shrink).
fn round_radius(r: f64) -> f64 {
    let q = (r / PATH_RADIUS_STEP_M).ceil() * PATH_RADIUS_STEP_M;
    // Division and product may each round down by an ulp.
    if q >= r { q } else { q + PATH_RADIUS_STEP_M }
}

/// The error bound a segment's payload states, checked to be a distance.
pub fn checked_e_max(seq: u32, e_max: f64) -> Result<f64, IndexError> {
    if e_max.is_finite() && e_max >= 0.0 {
        Ok(e_max)
    } else {
        Err(IndexError::Segment {
            seq,
            what: "the payload's error bound is not a distance".into(),
        })
    }
}

/// One segment's decoded motion (one track per body it carries) and its payload's error bound.
pub fn decode_segment_tracks(
    s: &MotionSegment,
) -> Result<(Vec<mwb_codec::Track>, f64), IndexError> {
    let d = decode_segment(s)?;
    Ok((d.tracks, checked_e_max(s.seq, d.e_max)?))
}

/// Every body's full-rate decoded motion of a whole world's `segments` (in order, every body
/// in each), and the largest error bound of their payloads.
pub fn decode_tracks(
    segments: &[MotionSegment],
) -> Result<(Vec<mwb_codec::Track>, f64), IndexError> {
    let first = segments.first().ok_or(IndexError::Empty)?;
    let bodies = first.body_count as usize;
    let mut full: Vec<mwb_codec::Track> = vec![mwb_codec::Track::default(); bodies];
    let mut e_max = 0f64;
    for s in segments {
        let seg_err = |what: &str| IndexError::Segment {
            seq: s.seq,
            what: what.to_owned(),
        };
        if s.body_count as usize != bodies {
            return Err(seg_err("body count differs from segment 0"));
        }
        let (tracks, bound) = decode_segment_tracks(s)?;
        e_max = e_max.max(bound);
        for (b, track) in tracks.iter().enumerate() {
            if track.len() != s.frame_count as usize || track.rotations.len() != track.len() {
                return Err(seg_err("decoded track length differs from frame count"));
            }
            full[b].positions.extend_from_slice(&track.positions);
            full[b].rotations.extend_from_slice(&track.rotations);
        }
    }
    Ok((full, e_max))
}

/// Indexes a whole world (not a refined difference) from its summary and segments: the store's
/// [`index_tracks`] of [`decode_tracks`]. A sampler runs this on what it sends, so that its
/// store only inserts the result ([`IndexedWorld::to_wire`]).
pub fn index_motion(
    done: &WorldDone,
    segments: &[MotionSegment],
    world: u32,
    job_id: Arc<str>,
    scene: impl Into<JobScene>,
    tolerance: f64,
) -> Result<IndexedWorld, IndexError> {
    let (full, e_max) = decode_tracks(segments)?;
    index_tracks(done, &full, e_max, world, job_id, scene, tolerance)
}

/// Indexes a world from its full-rate decoded motion `full` (one track per body) whose payloads
/// guarantee `e_max`, under global index `world`, with its job's scene facts (`scene`: rest
/// thresholds, body names; a bare [`RestThresholds`] converts).
///
/// From the decoded centre-of-mass positions each object gets an error-bounded polyline
/// ([`Polyline::simplify`], deviation ≤ `tolerance`), stored grid-rounded
/// ([`IndexedObject::new`]); its never-miss radius is the codec's e_max plus the measured
/// deviation plus the measured rounding.
/// (A 4 Hz low-res path — old recordings carry one beside each segment — would not do: a
/// bouncing box strays decimetres from it, which would widen every query box as much.)
/// Metrics come from the same full-rate track; impact counts from the world summary; rest
/// thresholds from the job's scene.
pub fn index_tracks(
    done: &WorldDone,
    full: &[mwb_codec::Track],
    e_max: f64,
    world: u32,
    job_id: Arc<str>,
    scene: impl Into<JobScene>,
    tolerance: f64,
) -> Result<IndexedWorld, IndexError> {
    let JobScene {
        rest,
        bodies: names,
    } = scene.into();
    let dt = done.frame_dt;
    if !(dt.is_finite() && dt > 0.0) {
        return Err(IndexError::FrameDt(dt));
    }
    let bodies = full.len();
    let mut objects = Vec::with_capacity(bodies);
    let mut all_metrics = Vec::with_capacity(bodies);
    for (b, track) in full.iter().enumerate() {
        let obj_err = |what: String| IndexError::Object { object: b, what };
        let (polyline, deviation) = Polyline::simplify(0.0, dt, &track.positions, tolerance)
            .map_err(|e| obj_err(e.to_string()))?;
        let mut metrics = ObjectMetrics::compute(
            &Track {
                frame_dt: dt,
                positions: &track.positions,
                rotations: &track.rotations,
            },
            done.impacts.get(b).copied().unwrap_or(0),
            rest,
            None,
        )
        .map_err(|e| obj_err(e.to_string()))?;
        // Rest from the simulator's own velocities when the sampler reported it: decoded
        // motion carries the codec's error, and a millimetre step between two segments reads
        // as 0.1 m/s — above any rest threshold.
        if let (Some(&t), Some(&rested)) = (done.rest_time_s.get(b), done.body_rested.get(b))
            && t.is_finite()
            && t >= 0.0
        {
            metrics.time_to_rest_s = t;
            metrics.came_to_rest = rested;
        }
        let mut object = IndexedObject::new(&polyline, dt, e_max + deviation)
            .map_err(|e| obj_err(e.to_string()))?;
        // The bound above adds the grid rounding to the simplification's deviation; the rounded
        // path's own deviation from the full-rate path, measured exactly (same-time distances
        // at every frame, as `simplify` measures), is mostly smaller: on `mwb bench query` the
        // p50 radius is 11.5 mm with the 1 mm grid, as it was with the 0.12 mm one (11.0 before
        // any rounding).
        let full = Polyline::uniform(0.0, dt, track.positions.clone())
            .map_err(|e| obj_err(e.to_string()))?;
        let exact = round_radius(e_max + object.polyline().max_deviation_from(&full));
        object.radius = object.radius.min(exact);
        objects.push(object);
        all_metrics.push(PackedMetrics::pack(&metrics));
    }
    Ok(IndexedWorld::of_summary(
        done,
        world,
        job_id,
        names,
        objects.into_boxed_slice(),
        all_metrics.into_boxed_slice(),
    ))
}

impl IndexedWorld {
    /// The world `done` describes, with its objects' paths and metrics: everything else comes
    /// from the summary, whoever built the objects (this store or the sampler).
    fn of_summary(
        done: &WorldDone,
        world: u32,
        job_id: Arc<str>,
        names: Arc<[String]>,
        objects: Box<[IndexedObject]>,
        metrics: Box<[PackedMetrics]>,
    ) -> IndexedWorld {
        let mut indexed = IndexedWorld {
            world,
            job_id,
            seed: done.seed,
            frames: done.frame_count,
            frame_dt: done.frame_dt,
            rested: done.rested,
            // Names only when they fit the world (a scene edited under the same job id would
            // not).
            bodies: if names.len() == objects.len() {
                names
            } else {
                Arc::from(Vec::new())
            },
            objects,
            metrics,
            measured: None,
            refined: done.lineage.as_ref().map(|l| {
                Box::new(Refined {
                    root_job: l.root_job.clone(),
                    root_seed: l.root_seed,
                    steps: l
                        .steps
                        .iter()
                        .map(|s| RefineStep {
                            frame: s.frame,
                            objects: s.objects.clone(),
                            seed: s.seed,
                            scene_revision: s.scene_revision,
                        })
                        .collect(),
                    active_from: done
                        .active_from
                        .iter()
                        .map(|&f| u32::try_from(f).ok())
                        .collect(),
                })
            }),
        };
        // Reverse nodes measure a backward world's plausibility (§5.3.1); forward worlds leave
        // the fields absent. A NaN would sort unpredictably: it counts as not measured.
        indexed.set_world_metrics(WorldMetrics {
            energy_growth: done.energy_growth.filter(|v| !v.is_nan()),
            angular_speed_growth: done.angular_speed_growth.filter(|v| !v.is_nan()),
            plausible: done.plausible,
            plausibility_excess: done.plausibility_excess.filter(|v| !v.is_nan()),
        });
        indexed
    }

    /// Whether `other` has the same paths, radii and metrics (what a sent index carries).
    pub fn same_objects(&self, other: &IndexedWorld) -> bool {
        self.objects == other.objects && self.metrics == other.metrics
    }

    /// This world's paths and metrics as a sampler sends them beside its summary
    /// (`WorldDone.index`), built with path tolerance `tolerance`.
    pub fn to_wire(&self, tolerance: f64) -> WorldIndex {
        WorldIndex {
            layout: PATH_LAYOUT,
            path_tolerance_m: tolerance,
            objects: self
                .objects
                .iter()
                .zip(self.metrics.iter())
                .map(|(o, m)| {
                    let m = m.unpack();
                    ObjectIndex {
                        path: o.data.to_vec(),
                        radius: o.radius,
                        angular_travel_rad: m.angular_travel_rad as f32,
                        time_to_rest_s: m.time_to_rest_s as f32,
                        orientation_error_rad: m.orientation_error_rad as f32,
                        impacts: m.impacts,
                        final_rotation: m.final_rotation.map(|v| v as f32).to_vec(),
                        came_to_rest: m.came_to_rest,
                    }
                })
                .collect(),
        }
    }

    /// The world `done` describes with the paths and metrics its sampler sent (`index`),
    /// checked: the same layout and path tolerance as this store's (`tolerance`), one object per
    /// body, every path well formed at the summary's frame interval and within its frames, every
    /// radius and metric a finite number. Equal to [`index_motion`] of the same world when the
    /// sampler ran it (a store checks that on a sample of worlds).
    pub fn from_wire(
        done: &WorldDone,
        index: WorldIndex,
        world: u32,
        job_id: Arc<str>,
        scene: impl Into<JobScene>,
        tolerance: f64,
    ) -> Result<IndexedWorld, WireIndexError> {
        use WireIndexError as E;
        if index.layout != PATH_LAYOUT {
            return Err(E::Layout(index.layout));
        }
        if index.path_tolerance_m != tolerance {
            return Err(E::Tolerance {
                sent: index.path_tolerance_m,
                ours: tolerance,
            });
        }
        let dt = done.frame_dt;
        if !(dt.is_finite() && dt > 0.0) {
            return Err(E::FrameDt(dt));
        }
        if index.objects.len() != done.impacts.len() {
            return Err(E::Objects {
                sent: index.objects.len(),
                bodies: done.impacts.len(),
            });
        }
        let mut objects = Vec::with_capacity(index.objects.len());
        let mut metrics = Vec::with_capacity(index.objects.len());
        for (object, o) in index.objects.into_iter().enumerate() {
            let field = |field: &'static str| E::Field { object, field };
            let finite = |v: f32, name: &'static str| {
                if v.is_finite() && v >= 0.0 {
                    Ok(f64::from(v))
                } else {
                    Err(field(name))
                }
            };
            let rotation: [f32; 4] = o
                .final_rotation
                .as_slice()
                .try_into()
                .map_err(|_| field("final_rotation"))?;
            if !rotation.iter().all(|v| v.is_finite()) {
                return Err(field("final_rotation"));
            }
            metrics.push(PackedMetrics::pack(&ObjectMetrics {
                angular_travel_rad: finite(o.angular_travel_rad, "angular_travel_rad")?,
                time_to_rest_s: finite(o.time_to_rest_s, "time_to_rest_s")?,
                came_to_rest: o.came_to_rest,
                impacts: o.impacts,
                orientation_error_rad: finite(o.orientation_error_rad, "orientation_error_rad")?,
                final_rotation: rotation.map(f64::from),
            }));
            let path = IndexedObject::from_parts(o.path, o.radius, dt, done.frame_count)
                .map_err(|what| E::Path { object, what })?;
            objects.push(path);
        }
        let JobScene { bodies: names, .. } = scene.into();
        Ok(IndexedWorld::of_summary(
            done,
            world,
            job_id,
            names,
            objects.into_boxed_slice(),
            metrics.into_boxed_slice(),
        ))
    }
}

/// The layout of a sent path (`ObjectIndex.path`): [`IndexedObject`]'s header and bit-packed
/// vertices as this version stores them. A store refuses another layout's paths (and indexes
/// such worlds itself).
pub const PATH_LAYOUT: u32 = 1;

/// Why a sent index (`WorldDone.index`) was not taken: the store indexes the world itself.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum WireIndexError {
    #[error("index.layout {0}: this store reads layout {PATH_LAYOUT}")]
    Layout(u32),
    #[error("index.path_tolerance_m {sent}: this store indexes at {ours}")]
    Tolerance { sent: f64, ours: f64 },
    #[error("frame_dt {0} is not a positive number")]
    FrameDt(f64),
    #[error("index.objects: {sent} paths for {bodies} bodies")]
    Objects { sent: usize, bodies: usize },
    #[error("index.objects[{object}].{field}: not a valid value")]
    Field { object: usize, field: &'static str },
    #[error("index.objects[{object}].path: {what}")]
    Path { object: usize, what: &'static str },
}

#[cfg(test)]
mod tests {
    use super::*;
    use mwb_core::rng::{Stream, WorldRng};
    use mwb_proto::v1::Message;

    /// Random walks on a 120 Hz frame grid, from a few centimetres to ~100 m across (so that
    /// some need a coarser grid than [`PATH_GRID_M`]), far from the origin too.
    fn walk(rng: &mut WorldRng, i: u32) -> Polyline {
        let dt = 1.0 / 120.0;
        let reach = [0.05, 2.0, 12.0, 100.0][i as usize % 4];
        let mut p = [
            rng.uniform(-500.0, 500.0),
            rng.uniform(-5.0, 5.0),
            rng.uniform(-500.0, 500.0),
        ];
        let (mut times, mut points) = (Vec::new(), Vec::new());
        let mut frame = rng.uniform(0.0, 50.0) as u32;
        for _ in 0..1 + i % 30 {
            times.push(f64::from(frame) * dt);
            points.push(p);
            frame += 1 + rng.uniform(0.0, 60.0) as u32;
            for v in &mut p {
                *v += rng.uniform(-reach, reach) / 4.0;
            }
        }
        Polyline::new(times, points).unwrap_or_else(|e| panic!("{e}"))
    }

    /// Every decoded vertex is at its own time and within the stated bound of the given one:
    /// √3/2 of the grid step, which is [`PATH_GRID_M`] unless a coordinate spans more than
    /// 2³² steps (~4 000 km; a tenth of these walks is blown up to that scale), and at most the
    /// radius's growth. So at every time the stored path is within `radius − given radius` of
    /// the given one (both linear between the same vertex times).
    #[test]
    fn decoded_vertices_are_within_the_bound_the_radius_carries() {
        let mut rng = WorldRng::new(41, Stream::Scene);
        let dt = 1.0 / 120.0;
        let mut coarse = 0;
        for i in 0..400 {
            let mut path = walk(&mut rng, i);
            if i % 10 == 9 {
                let points = path.points().iter().map(|p| p.map(|v| v * 1e5)).collect();
                path =
                    Polyline::new(path.times().to_vec(), points).unwrap_or_else(|e| panic!("{e}"));
            }
            let given = rng.uniform(0.0, 0.02);
            let obj = IndexedObject::new(&path, dt, given).unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(obj.len(), path.len());
            let span = (0..3)
                .map(|k| {
                    let (lo, hi) = path
                        .points()
                        .iter()
                        .fold((f64::MAX, f64::MIN), |(l, h), p| (l.min(p[k]), h.max(p[k])));
                    hi - lo
                })
                .fold(0.0, f64::max);
            let step = obj.grid_step();
            coarse += usize::from(step > PATH_GRID_M);
            if span < 4.0e6 {
                assert_eq!(step, PATH_GRID_M, "path {i} spans {span} m");
            }
            let stored = obj.polyline();
            for (v, (p, t)) in path.points().iter().zip(path.times()).enumerate() {
                let (q, tq) = obj.vertex(v);
                assert_eq!(tq, *t, "path {i} vertex {v}: times are exact");
                let d = (0..3).map(|k| (q[k] - p[k]).powi(2)).sum::<f64>().sqrt();
                // (Far from the origin the f64 sum rounds too: a hair of the coordinate.)
                let scale = p.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                assert!(
                    d <= 0.5 * 3f64.sqrt() * step * (1.0 + 1e-9) + 4.0 * f64::EPSILON * scale,
                    "{i}/{v}: {d}"
                );
                assert!(
                    d <= obj.radius - given,
                    "{i}/{v}: {d} > {}",
                    obj.radius - given
                );
            }
            assert!(stored.max_deviation_from(&path) <= obj.radius - given);
            if step == PATH_GRID_M {
                assert!(obj.radius - given <= 0.5 * 3f64.sqrt() * step + PATH_RADIUS_STEP_M);
            }
            // One allocation: the header and the vertices at the widths the extent needs.
            let bits = |extent: f64| (extent / step).round().max(1.0).log2().floor() + 1.0;
            let per_vertex: f64 = (0..3)
                .map(|k| {
                    let (lo, hi) = path
                        .points()
                        .iter()
                        .fold((f64::MAX, f64::MIN), |(l, h), p| (l.min(p[k]), h.max(p[k])));
                    // (A bit of slack: the f32 origin may sit a little below the lowest vertex.)
                    bits(hi - lo + step) + 1.0
                })
                .sum::<f64>()
                + bits(path.end().1 / dt - path.times()[0] / dt);
            assert!(
                obj.heap_bytes() as f64
                    <= HEADER as f64 + (per_vertex * path.len() as f64 / 8.0).ceil() + 1.0,
                "path {i}: {} bytes for {} vertices of {per_vertex} bits",
                obj.heap_bytes(),
                path.len()
            );
        }
        assert!(coarse > 5, "{coarse} paths needed a coarser grid");
    }

    /// Coordinates beyond 2³² steps of the coarsest grid (or not finite) are refused, naming
    /// the vertex; nothing is silently clamped.
    #[test]
    fn coordinates_out_of_reach_are_refused() {
        let path = Polyline::new(vec![0.0, 0.01], vec![[0.0; 3], [1e30, 0.0, 0.0]])
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(matches!(
            IndexedObject::new(&path, 0.01, 0.0),
            Err(PathError::TooFar { .. })
        ));
    }

    /// A box that touches the given path is never missed by the stored one (its radius covers
    /// the rounding), with or without a time window; tiny boxes placed on the path itself, so
    /// that only the radius saves them.
    #[test]
    fn a_box_touching_the_given_path_is_never_missed() {
        let mut rng = WorldRng::new(42, Stream::Scene);
        let dt = 1.0 / 120.0;
        let mut checks = 0;
        for i in 0..300 {
            let path = walk(&mut rng, i);
            let obj = IndexedObject::new(&path, dt, 0.0).unwrap_or_else(|e| panic!("{e}"));
            let (t0, t1) = (path.times()[0], path.end().1);
            for _ in 0..20 {
                let t = rng.uniform(t0, t1 + 0.5);
                let c = path.position_at(t);
                let h = rng.uniform(1e-6, 1e-3);
                let frustum = Frustum::aabb(c.map(|v| v - h), c.map(|v| v + h))
                    .unwrap_or_else(|e| panic!("{e}"));
                let window = (rng.next_f64() < 0.5)
                    .then(|| TimeWindow::new(t - 0.01, t + 0.01).ok())
                    .flatten();
                assert!(path.first_entry(&frustum, window).is_some());
                assert!(
                    obj.intersects(&frustum, window),
                    "path {i}: box of {h} m at {c:?}, t {t}, {window:?}"
                );
                checks += 1;
            }
        }
        assert_eq!(checks, 6000);
    }

    /// Times off the frame grid and non-positive frame intervals are refused, naming the
    /// vertex; nothing is silently moved in time.
    #[test]
    fn off_grid_times_are_refused() {
        let path = Polyline::new(vec![0.0, 0.013], vec![[0.0; 3], [1.0; 3]])
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(matches!(
            IndexedObject::new(&path, 0.01, 0.0),
            Err(PathError::OffFrame { vertex: 1, .. })
        ));
        assert_eq!(
            IndexedObject::new(&path, 0.0, 0.0),
            Err(PathError::FrameDt(0.0))
        );
    }

    /// A move by whole grid steps keeps the vertices and the radius: every decoded vertex moves
    /// by the rounded offset (up to the f64 sum's last bit), no farther.
    #[test]
    fn a_translated_path_moves_by_whole_steps() {
        let mut rng = WorldRng::new(43, Stream::Scene);
        for i in 0..100 {
            let obj = IndexedObject::new(&walk(&mut rng, 4 * i + 1), 1.0 / 120.0, 0.01)
                .unwrap_or_else(|e| panic!("{e}"));
            let d = [rng.uniform(-20.0, 20.0), 0.0, rng.uniform(-20.0, 20.0)];
            let Some(moved) = obj.translated(d) else {
                continue;
            };
            assert_eq!(moved.radius, obj.radius);
            let step = obj.grid_step();
            for v in 0..obj.len() {
                let ((a, ta), (b, tb)) = (obj.vertex(v), moved.vertex(v));
                assert_eq!(ta, tb);
                for k in 0..3 {
                    let want = a[k] + (d[k] / step).round() * step;
                    assert!(
                        (b[k] - want).abs() <= 1e-12 * (1.0 + want.abs()),
                        "{i}/{v}/{k}"
                    );
                }
            }
        }
    }

    /// Three bodies on a 120 Hz grid: one tumbling along a parabola, one sliding, one still.
    fn synthetic_world() -> (WorldDone, Vec<mwb_codec::Track>) {
        let dt = 1.0 / 120.0;
        let frames = 240;
        let tracks = (0..3)
            .map(|b| {
                let mut t = mwb_codec::Track::default();
                for f in 0..frames {
                    let s = f64::from(f) * dt;
                    let (p, angle) = match b {
                        0 => ([s, 2.0 + 3.0 * s - 4.9 * s * s, -1.0], 3.0 * s),
                        1 => ([1.0 + 0.5 * s, 0.1, 2.0], 0.0),
                        _ => ([-3.0, 0.5, 0.0], 0.0),
                    };
                    t.positions.push(p);
                    t.rotations
                        .push([0.0, (angle / 2.0).sin(), 0.0, (angle / 2.0).cos()]);
                }
                t
            })
            .collect();
        let done = WorldDone {
            seed: 9,
            frame_count: frames,
            frame_dt: dt,
            rested: true,
            impacts: vec![2, 0, 1],
            rest_time_s: vec![1.5, 0.25, 0.0],
            body_rested: vec![true, true, true],
            ..Default::default()
        };
        (done, tracks)
    }

    /// What a sampler sends comes back as the world it indexed: same paths, radii and metrics
    /// (to the bit), the world-level fields from the summary.
    #[test]
    fn the_wire_form_gives_back_the_same_world() {
        let (done, tracks) = synthetic_world();
        let tol = DEFAULT_PATH_TOLERANCE_M;
        let scene = JobScene::default();
        let w = index_tracks(&done, &tracks, 0.001, 4, Arc::from("j"), scene.clone(), tol)
            .unwrap_or_else(|e| panic!("{e}"));
        let wire = w.to_wire(tol);
        assert_eq!(wire.objects.len(), 3);
        let back = IndexedWorld::from_wire(&done, wire.clone(), 4, Arc::from("j"), scene, tol)
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(back.same_objects(&w));
        assert_eq!(
            (back.world, back.seed, back.frames, back.rested),
            (w.world, w.seed, w.frames, w.rested)
        );
        // Through its bytes too.
        let bytes = wire.encode_to_vec();
        let decoded = WorldIndex::decode(bytes.as_slice()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(decoded, wire);
        // A path whose vertices run past the world's frames is refused.
        let short = WorldDone {
            frame_count: 100,
            ..done.clone()
        };
        let err =
            IndexedWorld::from_wire(&short, wire, 4, Arc::from("j"), JobScene::default(), tol)
                .err();
        assert!(
            matches!(err, Some(WireIndexError::Path { object: 0, .. })),
            "{err:?}"
        );
    }

    proptest::proptest! {
        /// Any bytes in a sent path are refused or give a path every reader can read: no
        /// panic, every vertex finite, times strictly increasing within the world.
        #[test]
        fn any_sent_path_bytes_are_refused_or_read(
            flips in proptest::collection::vec((0usize..400, 0u8..=255), 0..6),
            cut in 0usize..400,
            len_patch in proptest::option::of(0u32..2000),
        ) {
            let (done, tracks) = synthetic_world();
            let tol = DEFAULT_PATH_TOLERANCE_M;
            let w = index_tracks(&done, &tracks, 0.001, 0, Arc::from("j"), JobScene::default(), tol)
                .unwrap_or_else(|e| panic!("{e}"));
            let mut data = w.objects[0].data.to_vec();
            for (at, v) in flips {
                if let Some(b) = data.get_mut(at) {
                    *b ^= v;
                }
            }
            if let Some(n) = len_patch {
                data[24..28].copy_from_slice(&n.to_le_bytes());
            }
            data.truncate(cut.max(1).min(data.len()));
            if let Ok(path) = IndexedObject::from_parts(data, 0.01, done.frame_dt, done.frame_count) {
                let poly = path.polyline();
                let mut last = -1.0;
                for (p, &t) in poly.points().iter().zip(poly.times()) {
                    proptest::prop_assert!(p.iter().all(|v| v.is_finite()));
                    proptest::prop_assert!(t > last && t < f64::from(done.frame_count) * done.frame_dt);
                    last = t;
                }
                let region = Frustum::aabb([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0])
                    .unwrap_or_else(|e| panic!("{e}"));
                let _ = path.first_entry(&region, None);
            }
        }
    }
}
