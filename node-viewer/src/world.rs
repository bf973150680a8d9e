//! One world as the viewer holds it: per body the path the store indexed (the same polyline,
//! the same never-miss radius), and — once loaded — its decoded full-rate motion and scene
//! instance for playback.
//!
//! Worlds come from two places and are read the same way: a store's `q/paths` answer
//! ([`WorldData::from_paths`]), or a world simulated in this process and indexed with the
//! store's own `mwb_store::index_world` ([`crate::offline`]). Motion is always decoded from the
//! wire form of the segments with `mwb_export::decode_segments` (CRC, order, contiguity).

use std::sync::Arc;

use mwb_codec::Track;
use mwb_core::browse::{ObjectMetrics, PathTree, Polyline};
use mwb_core::scene::Scene;
use mwb_proto::v1::{IndexedPaths, World};

use crate::ViewerError;
use crate::math::{V3, lerp};

/// A body's centre-of-mass path as the store indexed it.
#[derive(Debug, Clone)]
pub struct BodyPath {
    pub tree: PathTree,
    /// Never-miss inflation: the codec's e_max plus the polyline's deviation, rounded up.
    pub radius: f64,
}

/// A world's decoded motion and the scene instance it moves (body shapes can differ between
/// the worlds of one scene).
#[derive(Debug, Clone)]
pub struct Motion {
    pub scene: Scene,
    pub frame_dt: f64,
    /// Full-rate motion, one track per body in scene order.
    pub tracks: Vec<Track>,
}

impl Motion {
    /// Decodes a world as the store serves it (a refined world stored as a difference with its
    /// parent chain: `mwb_export::decode_world`) for `scene`. Every body of the scene must have
    /// a track and every track every frame.
    pub fn decode(scene: Scene, world: &World) -> Result<Self, ViewerError> {
        let motion =
            mwb_export::decode_world(world).map_err(|e| ViewerError::Motion(e.to_string()))?;
        let frame_dt = motion.frame_dt;
        if motion.tracks.len() != scene.bodies.len() {
            return Err(ViewerError::BodyCount {
                scene: scene.bodies.len(),
                motion: motion.tracks.len(),
            });
        }
        Ok(Self {
            scene,
            frame_dt,
            tracks: motion.tracks,
        })
    }

    /// Frames of motion (the longest track).
    pub fn frames(&self) -> usize {
        self.tracks.iter().map(Track::len).max().unwrap_or(0)
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

/// A world the viewer can draw, test constraints against and (with its motion) play back.
#[derive(Debug, Clone)]
pub struct WorldData {
    /// The store's global index (offline: the world's number): the bit of the constraint
    /// bitsets.
    pub index: u32,
    pub job: String,
    pub seed: u64,
    pub frame_dt: f64,
    pub frames: u32,
    /// Per body, its indexed path.
    pub paths: Vec<BodyPath>,
    /// Per body, the ranking metrics of §4.4.3 (offline worlds; a live store ranks its own).
    pub metrics: Vec<ObjectMetrics>,
    /// Decoded motion: offline worlds have it from the start, live ones once fetched.
    pub motion: Option<Arc<Motion>>,
}

impl WorldData {
    /// A world from a store's `q/paths` answer. Every polyline is checked (lengths, finite,
    /// increasing times) and gets the same OBB tree the store built from it.
    pub fn from_paths(p: &IndexedPaths) -> Result<Self, ViewerError> {
        if !(p.frame_dt.is_finite() && p.frame_dt > 0.0) {
            return Err(ViewerError::FrameDt(p.frame_dt));
        }
        let mut paths = Vec::with_capacity(p.objects.len());
        for (b, o) in p.objects.iter().enumerate() {
            let bad = |what: String| ViewerError::Body { body: b, what };
            if o.xyz.len() != 3 * o.times.len() {
                return Err(bad(format!(
                    "{} coordinates for {} vertices",
                    o.xyz.len(),
                    o.times.len()
                )));
            }
            if !(o.radius.is_finite() && o.radius >= 0.0) {
                return Err(bad(format!("path radius {} is not a distance", o.radius)));
            }
            let points = o.xyz.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
            let line = Polyline::new(o.times.clone(), points).map_err(|e| bad(e.to_string()))?;
            paths.push(BodyPath {
                tree: PathTree::build(line),
                radius: o.radius,
            });
        }
        Ok(Self {
            index: p.world,
            job: p.job_id.clone(),
            seed: p.seed,
            frame_dt: p.frame_dt,
            frames: p.frames,
            paths,
            metrics: Vec::new(),
            motion: None,
        })
    }

    /// A world whose paths run through every frame of `motion` exactly (radius 0, no
    /// simplification): for tests and synthetic benchmarks, where no codec or store is involved.
    pub fn from_exact_motion(index: u32, seed: u64, motion: Motion) -> Result<Self, ViewerError> {
        if !(motion.frame_dt.is_finite() && motion.frame_dt > 0.0) {
            return Err(ViewerError::FrameDt(motion.frame_dt));
        }
        let mut paths = Vec::with_capacity(motion.tracks.len());
        for (b, t) in motion.tracks.iter().enumerate() {
            let line =
                Polyline::uniform(0.0, motion.frame_dt, t.positions.clone()).map_err(|e| {
                    ViewerError::Body {
                        body: b,
                        what: e.to_string(),
                    }
                })?;
            paths.push(BodyPath {
                tree: PathTree::build(line),
                radius: 0.0,
            });
        }
        Ok(Self {
            index,
            job: String::new(),
            seed,
            frame_dt: motion.frame_dt,
            frames: motion.frames() as u32,
            paths,
            metrics: Vec::new(),
            motion: Some(Arc::new(motion)),
        })
    }

    /// Simulated duration, seconds.
    pub fn duration(&self) -> f64 {
        match &self.motion {
            Some(m) => m.frames().saturating_sub(1) as f64 * m.frame_dt,
            None => f64::from(self.frames.saturating_sub(1)) * self.frame_dt,
        }
    }

    /// Body `b`'s pose at time `t`, when the motion is loaded.
    pub fn pose_at(&self, b: usize, t: f64) -> Option<(V3, [f64; 4])> {
        self.motion.as_ref()?.pose_at(b, t)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mwb_proto::v1::ObjectPath;

    fn paths(objects: Vec<ObjectPath>) -> IndexedPaths {
        IndexedPaths {
            world: 7,
            job_id: "j".into(),
            seed: 3,
            frames: 61,
            frame_dt: 1.0 / 60.0,
            rested: true,
            objects,
        }
    }

    fn line() -> ObjectPath {
        ObjectPath {
            times: vec![0.0, 0.5, 1.0],
            xyz: vec![0.0, 1.0, 0.0, 1.0, 1.0, 0.0, 2.0, 0.5, 0.0],
            radius: 0.011,
        }
    }

    #[test]
    fn a_store_answer_becomes_the_same_polyline_and_radius() {
        let w = WorldData::from_paths(&paths(vec![line(), line()])).expect("reads");
        assert_eq!((w.index, w.seed, w.job.as_str()), (7, 3, "j"));
        assert_eq!(w.paths.len(), 2);
        assert_eq!(w.paths[0].radius, 0.011);
        assert_eq!(w.paths[0].tree.path().times(), &[0.0, 0.5, 1.0]);
        assert_eq!(w.paths[0].tree.path().points()[2], [2.0, 0.5, 0.0]);
        assert!((w.duration() - 1.0).abs() < 1e-12);
        assert!(w.pose_at(0, 0.5).is_none(), "no motion until it is fetched");
    }

    #[test]
    fn garbage_from_a_store_is_refused_naming_the_body() {
        let cases: Vec<(IndexedPaths, &str)> = vec![
            (
                paths(vec![
                    line(),
                    ObjectPath {
                        xyz: vec![0.0; 8],
                        ..line()
                    },
                ]),
                "body 1: 8 coordinates for 3 vertices",
            ),
            (
                paths(vec![ObjectPath {
                    radius: f64::NAN,
                    ..line()
                }]),
                "body 0: path radius NaN",
            ),
            (
                paths(vec![ObjectPath {
                    times: vec![0.0, 1.0, 0.5],
                    ..line()
                }]),
                "body 0:",
            ),
            (
                paths(vec![ObjectPath {
                    xyz: vec![0.0, f64::INFINITY, 0.0, 1.0, 1.0, 0.0, 2.0, 0.5, 0.0],
                    ..line()
                }]),
                "body 0:",
            ),
            (
                IndexedPaths {
                    frame_dt: 0.0,
                    ..paths(vec![line()])
                },
                "frame_dt 0",
            ),
        ];
        for (p, want) in cases {
            let e = WorldData::from_paths(&p).expect_err(want).to_string();
            assert!(e.contains(want), "{e:?} should say {want:?}");
        }
    }
}
