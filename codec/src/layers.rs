//! Composing a world stored as a difference from its parent (refinement, Twigg and James,
//! SIGGRAPH 2007, §4.5).
//!
//! A refined world re-simulates only some bodies from its branch frame on; what it sends is
//! those bodies' tracks, segment by segment on the parent's segment grid. The whole world is the
//! parent's motion with those tracks laid over it: [`Layered::start`] takes the parent's decoded
//! tracks and fits them to the child's frame count (a body the child did not re-simulate holds
//! the parent's last pose after the parent ended: the simulator left it there at rest), and
//! [`Layered::overlay`] replaces one segment's frames of the bodies it carries.
//!
//! Pure: decoded tracks in, decoded tracks out. The store (for its index) and every client that
//! decodes a fetched world (export, viewer, checks) compose through it.

use crate::Track;

/// Why a segment cannot be laid over a world.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LayerError {
    #[error("the parent has no frames")]
    EmptyParent,
    #[error("carries body {body}, the world has {bodies}")]
    Body { body: u32, bodies: usize },
    #[error("lists body {body} twice")]
    Repeated { body: u32 },
    #[error("lists {listed} bodies and holds {tracks} tracks")]
    Tracks { listed: usize, tracks: usize },
    #[error("frames {first}..{end} run past the world's {frames} frames")]
    Frames { first: u64, end: u64, frames: usize },
    #[error("body {body}: a track of {got} frames, the segment has {want}")]
    TrackLength { body: u32, got: usize, want: usize },
}

/// A world being composed from its parent's motion and its own segments.
#[derive(Debug, Clone, PartialEq)]
pub struct Layered {
    tracks: Vec<Track>,
    frames: usize,
}

impl Layered {
    /// The parent's decoded `tracks` (one per body, the same length), fitted to `frames`: cut
    /// if the child is shorter, each body's last pose held if it is longer.
    pub fn start(mut tracks: Vec<Track>, frames: usize) -> Result<Self, LayerError> {
        for t in &mut tracks {
            let (Some(&p), Some(&r)) = (t.positions.last(), t.rotations.last()) else {
                return Err(LayerError::EmptyParent);
            };
            t.positions.resize(frames, p);
            t.rotations.resize(frames, r);
        }
        Ok(Self { tracks, frames })
    }

    /// Lays one segment over the world: `tracks[j]` replaces body `bodies[j]`'s frames from
    /// `first_frame` (every body in order when `bodies` is empty).
    pub fn overlay(
        &mut self,
        first_frame: u32,
        bodies: &[u32],
        tracks: Vec<Track>,
    ) -> Result<(), LayerError> {
        let n = self.tracks.len();
        let listed: Vec<u32> = if bodies.is_empty() {
            (0..n as u32).collect()
        } else {
            bodies.to_vec()
        };
        if listed.len() != tracks.len() {
            return Err(LayerError::Tracks {
                listed: listed.len(),
                tracks: tracks.len(),
            });
        }
        let mut seen = vec![false; n];
        for &b in &listed {
            let slot = seen
                .get_mut(b as usize)
                .ok_or(LayerError::Body { body: b, bodies: n })?;
            if std::mem::replace(slot, true) {
                return Err(LayerError::Repeated { body: b });
            }
        }
        let want = tracks.first().map_or(0, Track::len);
        let first = first_frame as usize;
        if first + want > self.frames {
            return Err(LayerError::Frames {
                first: u64::from(first_frame),
                end: (first + want) as u64,
                frames: self.frames,
            });
        }
        for (&b, t) in listed.iter().zip(tracks) {
            if t.len() != want || t.rotations.len() != want {
                return Err(LayerError::TrackLength {
                    body: b,
                    got: t.len().min(t.rotations.len()),
                    want,
                });
            }
            let dst = &mut self.tracks[b as usize];
            dst.positions[first..first + want].copy_from_slice(&t.positions);
            dst.rotations[first..first + want].copy_from_slice(&t.rotations);
        }
        Ok(())
    }

    /// The composed tracks, one per body, `frames` long.
    pub fn finish(self) -> Vec<Track> {
        self.tracks
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn track(xs: &[f64]) -> Track {
        Track {
            positions: xs.iter().map(|&x| [x, 0.0, 0.0]).collect(),
            rotations: vec![[0.0, 0.0, 0.0, 1.0]; xs.len()],
        }
    }

    fn xs(t: &Track) -> Vec<f64> {
        t.positions.iter().map(|p| p[0]).collect()
    }

    #[test]
    fn a_segment_replaces_only_its_bodies_and_frames() {
        let parent = vec![
            track(&[0.0, 1.0, 2.0, 3.0]),
            track(&[10.0, 11.0, 12.0, 13.0]),
        ];
        let mut w = Layered::start(parent, 6).unwrap();
        w.overlay(2, &[1], vec![track(&[20.0, 21.0])]).unwrap();
        let out = w.finish();
        // Body 0 is the parent's, its last pose held past the parent's end.
        assert_eq!(xs(&out[0]), [0.0, 1.0, 2.0, 3.0, 3.0, 3.0]);
        assert_eq!(xs(&out[1]), [10.0, 11.0, 20.0, 21.0, 13.0, 13.0]);
    }

    #[test]
    fn a_shorter_child_cuts_the_parent_and_an_empty_list_means_every_body() {
        let parent = vec![track(&[0.0, 1.0, 2.0]), track(&[5.0, 6.0, 7.0])];
        let mut w = Layered::start(parent, 2).unwrap();
        w.overlay(1, &[], vec![track(&[9.0]), track(&[8.0])])
            .unwrap();
        let out = w.finish();
        assert_eq!(xs(&out[0]), [0.0, 9.0]);
        assert_eq!(xs(&out[1]), [5.0, 8.0]);
    }

    #[test]
    fn bad_segments_are_named() {
        let parent = vec![track(&[0.0, 1.0]), track(&[0.0, 1.0])];
        let mut w = Layered::start(parent, 2).unwrap();
        let one = || vec![track(&[1.0])];
        assert_eq!(
            w.overlay(0, &[2], one()),
            Err(LayerError::Body { body: 2, bodies: 2 })
        );
        assert_eq!(
            w.overlay(0, &[0, 0], vec![track(&[1.0]), track(&[1.0])]),
            Err(LayerError::Repeated { body: 0 })
        );
        assert_eq!(
            w.overlay(0, &[0, 1], one()),
            Err(LayerError::Tracks {
                listed: 2,
                tracks: 1
            })
        );
        assert_eq!(
            w.overlay(1, &[0], vec![track(&[1.0, 2.0])]),
            Err(LayerError::Frames {
                first: 1,
                end: 3,
                frames: 2
            })
        );
        assert_eq!(
            w.overlay(0, &[0, 1], vec![track(&[1.0]), track(&[1.0, 2.0])]),
            Err(LayerError::TrackLength {
                body: 1,
                got: 2,
                want: 1
            })
        );
        assert_eq!(
            Layered::start(vec![Track::default()], 3),
            Err(LayerError::EmptyParent)
        );
    }
}
