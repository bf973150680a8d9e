//! Ingest-time indexing of a stored world for browsing (§4.4.2–4.4.3): per object, an OBB path
//! tree over the low-resolution polyline with its never-miss inflation radius, and the ranking
//! metrics computed once from the full-rate decoded motion. Pure: no bus, no clock.

use crate::assembly::StoredWorld;
use mwb_codec::WorldReader;
use mwb_core::browse::api::{RefineStep, Refined};
use mwb_core::browse::{ObjectMetrics, PathTree, Polyline, RestThresholds, Track, WorldMetrics};
use mwb_proto::v1::{Encoding, IndexedPaths, Job, MotionSegment, ObjectPath};
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

/// One object of an indexed world.
#[derive(Debug, Clone)]
pub struct IndexedObject {
    pub tree: PathTree,
    /// Inflation for frustum tests, metres: the codec's error bound plus the largest distance
    /// between the full-rate decoded path and the indexed polyline, so that a world whose true
    /// path enters a frustum is never missed (§4.4.2 tests the low-res path conservatively);
    /// rounded up to [`PATH_RADIUS_STEP_M`].
    pub radius: f64,
}

/// A world as the browsing layer sees it.
#[derive(Debug, Clone)]
pub struct IndexedWorld {
    /// Global world index (see [`crate::ShardSpec`]).
    pub world: u32,
    pub job_id: String,
    pub seed: u64,
    pub frames: u32,
    pub frame_dt: f64,
    pub rested: bool,
    /// Body names in object-index order, shared by every world of the job; empty if unknown.
    pub bodies: Arc<[String]>,
    pub objects: Vec<IndexedObject>,
    /// Per object, the §4.4.3 ranking metrics (a slice, as rankings combine them).
    pub metrics: Vec<ObjectMetrics>,
    /// Per-world measurements from the world's summary (plausibility of backward worlds).
    pub world_metrics: WorldMetrics,
    /// A refined world's lineage (§4.5); `None` for sampled worlds.
    pub refined: Option<Box<Refined>>,
}

impl IndexedWorld {
    /// Heap bytes held by the index of this world (trees, polylines, metrics).
    pub fn heap_bytes(&self) -> usize {
        self.job_id.capacity()
            + self.objects.capacity() * std::mem::size_of::<IndexedObject>()
            + self.metrics.capacity() * std::mem::size_of::<ObjectMetrics>()
            + self
                .objects
                .iter()
                .map(|o| o.tree.heap_bytes())
                .sum::<usize>()
    }
}

impl IndexedWorld {
    /// The world's indexed paths as they travel on `q/paths` (for drawing): every object's
    /// polyline and radius exactly as the index holds them, so that a client testing a frustum
    /// against them gets the store's answer.
    pub fn paths_message(&self) -> IndexedPaths {
        IndexedPaths {
            world: self.world,
            job_id: self.job_id.clone(),
            seed: self.seed,
            frames: self.frames,
            frame_dt: self.frame_dt,
            rested: self.rested,
            objects: self
                .objects
                .iter()
                .map(|o| {
                    let path = o.tree.path();
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
    #[error("frame_dt {0} is not a positive number")]
    FrameDt(f64),
    #[error("segment {seq}: {what}")]
    Segment { seq: u32, what: String },
    #[error("object {object}: {what}")]
    Object { object: usize, what: String },
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

/// Indexes a complete (assembled, CRC-verified) world under global index `world`, with its
/// job's scene facts (`scene`: rest thresholds, body names; a bare [`RestThresholds`] converts).
///
/// Every segment is decoded once (full rate). From the decoded centre-of-mass positions each
/// object gets an error-bounded polyline ([`Polyline::simplify`], deviation ≤ `tolerance`) and
/// an OBB tree over it; its never-miss radius is the codec's e_max plus the measured deviation.
/// (The 4 Hz low-res path that travels with the segments is meant for instant display: a
/// bouncing box strays decimetres from it, which would widen every query box as much.)
/// Metrics come from the same full-rate track; impact counts from the world summary; rest
/// thresholds from the job's scene.
pub fn index_world(
    stored: &StoredWorld,
    world: u32,
    scene: impl Into<JobScene>,
    tolerance: f64,
) -> Result<IndexedWorld, IndexError> {
    let JobScene {
        rest,
        bodies: names,
    } = scene.into();
    let done = &stored.done;
    let first = stored.segments.first().ok_or(IndexError::Empty)?;
    let dt = done.frame_dt;
    if !(dt.is_finite() && dt > 0.0) {
        return Err(IndexError::FrameDt(dt));
    }
    let bodies = first.body_count as usize;
    let mut full: Vec<mwb_codec::Track> = vec![mwb_codec::Track::default(); bodies];
    let mut e_max = 0f64;
    for s in &stored.segments {
        let seg_err = |what: &str| IndexError::Segment {
            seq: s.seq,
            what: what.to_owned(),
        };
        if s.body_count as usize != bodies {
            return Err(seg_err("body count differs from segment 0"));
        }
        let decoded = decode_segment(s)?;
        if !(decoded.e_max.is_finite() && decoded.e_max >= 0.0) {
            return Err(seg_err("the payload's error bound is not a distance"));
        }
        e_max = e_max.max(decoded.e_max);
        for (b, track) in decoded.tracks.iter().enumerate() {
            if track.len() != s.frame_count as usize || track.rotations.len() != track.len() {
                return Err(seg_err("decoded track length differs from frame count"));
            }
            full[b].positions.extend_from_slice(&track.positions);
            full[b].rotations.extend_from_slice(&track.rotations);
        }
    }
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
        objects.push(IndexedObject {
            tree: PathTree::build(polyline),
            radius: round_radius(e_max + deviation),
        });
        all_metrics.push(metrics);
    }
    Ok(IndexedWorld {
        world,
        job_id: stored.job_id.clone(),
        seed: done.seed,
        frames: done.frame_count,
        frame_dt: dt,
        rested: done.rested,
        // Names only when they fit the world (a scene edited under the same job id would not).
        bodies: if names.len() == objects.len() {
            names
        } else {
            Arc::from(Vec::new())
        },
        objects,
        metrics: all_metrics,
        // Reverse nodes measure a backward world's plausibility (§5.3.1); forward worlds leave
        // the fields absent. A NaN would sort unpredictably: it counts as not measured.
        world_metrics: WorldMetrics {
            energy_growth: done.energy_growth.filter(|v| !v.is_nan()),
            angular_speed_growth: done.angular_speed_growth.filter(|v| !v.is_nan()),
        },
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
                    })
                    .collect(),
                active_from: done
                    .active_from
                    .iter()
                    .map(|&f| u32::try_from(f).ok())
                    .collect(),
            })
        }),
    })
}
