//! One world as the viewer holds it: its scene instance, its decoded full-rate motion, and per
//! body the path index the store would build from that motion (same tolerance, same radius
//! rule), so that a constraint evaluated here answers what the store answers.

use mwb_codec::{Track, WorldReader};
use mwb_core::browse::{PathTree, Polyline};
use mwb_core::scene::Scene;
use mwb_sampler::{PayloadEncoding, Segment};

use crate::ViewerError;
use crate::math::{V3, lerp};

/// Largest distance between a drawn / indexed path and the decoded motion, metres. The store's
/// default (`mwb_store::index::DEFAULT_PATH_TOLERANCE_M`): paths on screen are within the
/// store's index tolerance of the true motion.
pub const PATH_TOLERANCE_M: f64 = 0.01;
/// Path radii round up to this step, metres (the store's `PATH_RADIUS_STEP_M`).
pub const PATH_RADIUS_STEP_M: f64 = 0.0005;

/// A body's centre-of-mass path as indexed for browsing.
#[derive(Debug, Clone)]
pub struct BodyPath {
    pub tree: PathTree,
    /// Never-miss inflation: the codec's e_max plus the polyline's deviation, rounded up.
    pub radius: f64,
}

/// A world the viewer can draw, play back and test constraints against.
#[derive(Debug, Clone)]
pub struct WorldData {
    /// Index in the session (bit of the constraint bitsets).
    pub index: u32,
    pub seed: u64,
    pub frame_dt: f64,
    /// The instantiated scene (shapes and statics can differ between worlds).
    pub scene: Scene,
    /// Decoded full-rate motion, one track per body in scene order.
    pub tracks: Vec<Track>,
    /// Per body, its indexed path.
    pub paths: Vec<BodyPath>,
}

fn round_radius(r: f64) -> f64 {
    let q = (r / PATH_RADIUS_STEP_M).ceil() * PATH_RADIUS_STEP_M;
    if q >= r { q } else { q + PATH_RADIUS_STEP_M }
}

/// Decodes a world's segments (in order) into one full-rate track per body and the largest
/// error bound of their payloads.
pub fn decode_segments(segments: &[Segment]) -> Result<(Vec<Track>, f64), ViewerError> {
    let first = segments.first().ok_or(ViewerError::NoSegments)?;
    let bodies = first.body_count as usize;
    let mut full = vec![Track::default(); bodies];
    let mut e_max = 0f64;
    for s in segments {
        let bad = |what: String| ViewerError::Segment { seq: s.seq, what };
        if s.body_count as usize != bodies {
            return Err(bad("body count differs from segment 0".into()));
        }
        let (tracks, e) = match s.encoding {
            PayloadEncoding::Spline => {
                let reader = WorldReader::new(&s.payload).map_err(|e| bad(e.to_string()))?;
                let tracks = reader.decode_all().map_err(|e| bad(e.to_string()))?;
                (tracks, reader.e_max())
            }
            PayloadEncoding::QuantisedFrames => {
                let poses = mwb_core::frames::decode(&s.payload, s.frame_count, s.body_count)
                    .map_err(|e| bad(e.to_string()))?;
                let mut tracks = vec![Track::default(); bodies];
                for (i, p) in poses.iter().enumerate() {
                    tracks[i % bodies].positions.push(p.position);
                    tracks[i % bodies].rotations.push(p.rotation);
                }
                (tracks, 0.5 * mwb_core::frames::POS_QUANTUM_M * 3f64.sqrt())
            }
        };
        if tracks.len() != bodies {
            return Err(bad(format!("payload holds {} bodies", tracks.len())));
        }
        e_max = e_max.max(e);
        for (b, t) in tracks.into_iter().enumerate() {
            if t.positions.len() != s.frame_count as usize || t.rotations.len() != t.positions.len()
            {
                return Err(bad("decoded track length differs from frame count".into()));
            }
            full[b].positions.extend(t.positions);
            full[b].rotations.extend(t.rotations);
        }
    }
    Ok((full, e_max))
}

impl WorldData {
    /// Indexes decoded motion: per body an error-bounded polyline (≤ [`PATH_TOLERANCE_M`] from
    /// the decoded path) in an OBB path tree, with radius e_max + deviation.
    pub fn new(
        index: u32,
        seed: u64,
        scene: Scene,
        frame_dt: f64,
        tracks: Vec<Track>,
        e_max: f64,
    ) -> Result<Self, ViewerError> {
        if !(frame_dt.is_finite() && frame_dt > 0.0) {
            return Err(ViewerError::FrameDt(frame_dt));
        }
        if tracks.len() != scene.bodies.len() {
            return Err(ViewerError::BodyCount {
                scene: scene.bodies.len(),
                motion: tracks.len(),
            });
        }
        let mut paths = Vec::with_capacity(tracks.len());
        for (b, t) in tracks.iter().enumerate() {
            let (line, dev) = Polyline::simplify(0.0, frame_dt, &t.positions, PATH_TOLERANCE_M)
                .map_err(|e| ViewerError::Body {
                    body: b,
                    what: e.to_string(),
                })?;
            paths.push(BodyPath {
                tree: PathTree::build(line),
                radius: round_radius(e_max + dev),
            });
        }
        Ok(Self {
            index,
            seed,
            frame_dt,
            scene,
            tracks,
            paths,
        })
    }

    /// Frames of motion (the longest track).
    pub fn frames(&self) -> usize {
        self.tracks.iter().map(Track::len).max().unwrap_or(0)
    }

    /// Simulated duration, seconds.
    pub fn duration(&self) -> f64 {
        self.frames().saturating_sub(1) as f64 * self.frame_dt
    }

    /// Body `b`'s pose at time `t` (clamped to the motion), interpolated between decoded
    /// frames (positions linearly, rotations by normalised lerp along the shorter arc).
    pub fn pose_at(&self, b: usize, t: f64) -> Option<(V3, [f64; 4])> {
        let track = self.tracks.get(b)?;
        let n = track.len();
        if n == 0 {
            return None;
        }
        let f = (t / self.frame_dt).clamp(0.0, (n - 1) as f64);
        let i = (f.floor() as usize).min(n - 1);
        let j = (i + 1).min(n - 1);
        let s = f - i as f64;
        let p = lerp(track.positions[i], track.positions[j], s);
        let (qa, mut qb) = (track.rotations[i], track.rotations[j]);
        if qa.iter().zip(&qb).map(|(a, b)| a * b).sum::<f64>() < 0.0 {
            qb = qb.map(|c| -c);
        }
        let mut q = [0.0; 4];
        for k in 0..4 {
            q[k] = qa[k] + (qb[k] - qa[k]) * s;
        }
        let l = q.iter().map(|c| c * c).sum::<f64>().sqrt();
        let q = if l > 1e-12 {
            q.map(|c| c / l)
        } else {
            [0.0, 0.0, 0.0, 1.0]
        };
        Some((p, q))
    }
}
