//! A world's motion decoded from its segments: per body (scene order), every frame's position
//! and unit quaternion `[x, y, z, w]`, frame `k` at time `k · frame_dt` (frame 0 is the initial
//! state).
//!
//! Every segment decodes alone (each is its own codec stream, or its own quantised frames), so
//! a world is the concatenation of its segments in `seq` order, checked to be contiguous.

use mwb_codec::{Layered, Track, WorldReader};
use mwb_core::scene::Scene;
use mwb_proto::v1::{Encoding, MotionSegment, World, WorldDone};

/// Every body's track over the whole world.
#[derive(Debug, Clone, PartialEq)]
pub struct Motion {
    /// Seconds between frames (the scene's `dt`; `WorldDone.frame_dt`).
    pub frame_dt: f64,
    /// One per scene body, all the same length.
    pub tracks: Vec<Track>,
}

impl Motion {
    /// Number of frames (of the first track; [`crate::ExportWorld::check`] checks the others).
    pub fn frame_count(&self) -> usize {
        self.tracks.first().map_or(0, Track::len)
    }

    /// `frames` frames of every body standing still where the scene puts it (for examples and
    /// tests of the writers).
    pub fn at_rest(scene: &Scene, frames: usize, frame_dt: f64) -> Self {
        Self {
            frame_dt,
            tracks: scene
                .bodies
                .iter()
                .map(|b| Track {
                    positions: vec![b.position; frames],
                    rotations: vec![b.rotation; frames],
                })
                .collect(),
        }
    }

    /// Each body's quaternions with the sign of each chosen so that consecutive keys are in the
    /// same hemisphere (`q_k · q_{k−1} ≥ 0`), renormalised. `q` and `−q` are the same rotation,
    /// but an importer that interpolates the components (Blender's quaternion curves do)
    /// would swing a body the long way round between two keys of opposite sign.
    pub fn continuous_rotations(&self) -> Vec<Vec<[f64; 4]>> {
        self.tracks
            .iter()
            .map(|t| sign_continuous(&t.rotations))
            .collect()
    }
}

/// See [`Motion::continuous_rotations`].
pub fn sign_continuous(rotations: &[[f64; 4]]) -> Vec<[f64; 4]> {
    let mut out: Vec<[f64; 4]> = Vec::with_capacity(rotations.len());
    for q in rotations {
        let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
        let mut q = if n > 0.0 {
            [q[0] / n, q[1] / n, q[2] / n, q[3] / n]
        } else {
            mwb_core::scene::IDENTITY
        };
        if let Some(p) = out.last() {
            let dot = p[0] * q[0] + p[1] * q[1] + p[2] * q[2] + p[3] * q[3];
            if dot < 0.0 {
                q = [-q[0], -q[1], -q[2], -q[3]];
            }
        }
        out.push(q);
    }
    out
}

/// What a segment's payload is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PayloadKind {
    /// `ENCODING_SPLINE_V1`: an `mwb-codec` stream.
    Spline,
    /// `ENCODING_QUANTISED_FRAMES_V1`: `mwb_core::frames`.
    QuantisedFrames,
}

/// One segment of a world, borrowed from wherever it came from (a store's `World`, a
/// recording, a local simulation).
#[derive(Debug, Clone, Copy)]
pub struct SegmentPayload<'a> {
    pub seq: u32,
    pub first_frame: u32,
    pub frame_count: u32,
    pub body_count: u32,
    /// The bodies the payload holds, in order (empty: every body). See [`decode_world`].
    pub bodies: &'a [u32],
    pub kind: PayloadKind,
    pub payload: &'a [u8],
}

impl<'a> SegmentPayload<'a> {
    /// A bus segment (`mwb.v1.MotionSegment`). The CRC is checked here too, so that a
    /// corrupted segment is named rather than decoded into wrong motion.
    pub fn from_proto(s: &'a MotionSegment) -> Result<Self, MotionError> {
        let kind = match Encoding::try_from(s.encoding) {
            Ok(Encoding::SplineV1) => PayloadKind::Spline,
            Ok(Encoding::QuantisedFramesV1) => PayloadKind::QuantisedFrames,
            Ok(Encoding::Unspecified) | Err(_) => {
                return Err(MotionError::Encoding {
                    seq: s.seq,
                    encoding: s.encoding,
                });
            }
        };
        let crc = crc32fast::hash(&s.payload);
        if crc != s.crc32 {
            return Err(MotionError::Crc {
                seq: s.seq,
                saved: s.crc32,
                computed: crc,
            });
        }
        Ok(Self {
            seq: s.seq,
            first_frame: s.first_frame,
            frame_count: s.frame_count,
            body_count: s.body_count,
            bodies: &s.bodies,
            kind,
            payload: &s.payload,
        })
    }
}

/// Why segments did not make a motion.
#[derive(Debug, thiserror::Error)]
pub enum MotionError {
    #[error("no segments")]
    Empty,
    #[error("segment {seq}: unknown encoding {encoding}")]
    Encoding { seq: u32, encoding: i32 },
    #[error("segment {seq}: CRC mismatch (saved {saved:08x}, computed {computed:08x})")]
    Crc { seq: u32, saved: u32, computed: u32 },
    #[error("segment {seq} is at position {position} (segments must come in order 0, 1, …)")]
    Order { seq: u32, position: usize },
    #[error("segment {seq}: starts at frame {first_frame}, the segments before end at {expected}")]
    Gap {
        seq: u32,
        first_frame: u32,
        expected: u64,
    },
    #[error("segment {seq}: {got} bodies, segment 0 has {expected}")]
    Bodies { seq: u32, got: u32, expected: u32 },
    #[error(
        "segment {seq}: payload holds {bodies} bodies × {frames} frames, the segment says {want_bodies} × {want_frames}"
    )]
    Shape {
        seq: u32,
        bodies: usize,
        frames: usize,
        want_bodies: u32,
        want_frames: u32,
    },
    #[error("segment {seq}: {source}")]
    Codec {
        seq: u32,
        #[source]
        source: mwb_codec::CodecError,
    },
    #[error("segment {seq}: {source}")]
    Frames {
        seq: u32,
        #[source]
        source: mwb_core::frames::FrameError,
    },
    #[error("segment {seq}: body {body}: a non-finite pose")]
    NotFinite { seq: u32, body: usize },
    #[error("the segments hold {got} frames, the world's summary says {expected}")]
    FrameCount { got: u64, expected: u64 },
    #[error("world {world}: no summary")]
    NoSummary { world: u32 },
    #[error(
        "world {world} is stored as a difference from its parent (refined), which did not come with it"
    )]
    NoParent { world: u32 },
    #[error("parent world {world}: {source}")]
    Parent {
        world: u32,
        #[source]
        source: Box<MotionError>,
    },
    #[error("segment {seq}: {source}")]
    Layer {
        seq: u32,
        #[source]
        source: mwb_codec::LayerError,
    },
}

/// Decodes a world's segments (in `seq` order, contiguous) into one [`Motion`]. With
/// `expected_frames` (the summary's `frame_count`) the total is checked against it.
pub fn decode_segments(
    segments: &[SegmentPayload<'_>],
    frame_dt: f64,
    expected_frames: Option<u64>,
) -> Result<Motion, MotionError> {
    let first = segments.first().ok_or(MotionError::Empty)?;
    let bodies = first.body_count;
    let mut tracks: Vec<Track> = (0..bodies)
        .map(|_| Track {
            positions: Vec::new(),
            rotations: Vec::new(),
        })
        .collect();
    let mut next_frame = 0u64;
    for (position, s) in segments.iter().enumerate() {
        let seq = s.seq;
        if seq as usize != position {
            return Err(MotionError::Order { seq, position });
        }
        if u64::from(s.first_frame) != next_frame {
            return Err(MotionError::Gap {
                seq,
                first_frame: s.first_frame,
                expected: next_frame,
            });
        }
        if s.body_count != bodies {
            return Err(MotionError::Bodies {
                seq,
                got: s.body_count,
                expected: bodies,
            });
        }
        for (t, d) in tracks.iter_mut().zip(decode_payload(s)?) {
            t.positions.extend(d.positions);
            t.rotations.extend(d.rotations);
        }
        next_frame += u64::from(s.frame_count);
    }
    check_frames(next_frame, expected_frames)?;
    Ok(Motion { frame_dt, tracks })
}

fn check_frames(got: u64, expected: Option<u64>) -> Result<(), MotionError> {
    match expected {
        Some(expected) if expected != got => Err(MotionError::FrameCount { got, expected }),
        _ => Ok(()),
    }
}

/// One segment's payload decoded: a track per body it carries, each `frame_count` long and
/// finite.
pub fn decode_payload(s: &SegmentPayload<'_>) -> Result<Vec<Track>, MotionError> {
    let seq = s.seq;
    let bodies = s.body_count as usize;
    let shape_err = |b: usize, f: usize| MotionError::Shape {
        seq,
        bodies: b,
        frames: f,
        want_bodies: s.body_count,
        want_frames: s.frame_count,
    };
    let tracks = match s.kind {
        PayloadKind::Spline => {
            let reader =
                WorldReader::new(s.payload).map_err(|source| MotionError::Codec { seq, source })?;
            if reader.object_count() != bodies || reader.frame_count() != s.frame_count as usize {
                return Err(shape_err(reader.object_count(), reader.frame_count()));
            }
            reader
                .decode_all()
                .map_err(|source| MotionError::Codec { seq, source })?
        }
        PayloadKind::QuantisedFrames => {
            let poses = mwb_core::frames::decode(s.payload, s.frame_count, s.body_count)
                .map_err(|source| MotionError::Frames { seq, source })?;
            if poses.len() != s.frame_count as usize * bodies {
                return Err(shape_err(bodies, poses.len() / bodies.max(1)));
            }
            let mut tracks = vec![Track::default(); bodies];
            // Frame-major: frame 0 body 0, frame 0 body 1, …
            for (i, p) in poses.iter().enumerate() {
                let t = &mut tracks[i % bodies];
                t.positions.push(p.position);
                t.rotations.push(p.rotation);
            }
            tracks
        }
    };
    for (body, d) in tracks.iter().enumerate() {
        if d.len() != s.frame_count as usize || d.rotations.len() != d.len() {
            return Err(shape_err(bodies, d.len()));
        }
        if !all_finite(d) {
            return Err(MotionError::NotFinite { seq, body });
        }
    }
    Ok(tracks)
}

/// Whether a fetched world was stored as a difference from its parent (§4.5): it starts past
/// segment 0 or some segment carries only some bodies.
pub fn is_layered(done: &WorldDone, segments: &[MotionSegment]) -> bool {
    done.first_segment > 0 || segments.iter().any(|s| !s.bodies.is_empty())
}

/// Decodes a world as a store serves it (`q/world/<i>`): its own segments, and for a refined
/// world stored as a difference its parent chain ([`World::parent`]), composed with
/// [`mwb_codec::Layered`]: each body's motion is its own where one of its segments carries it,
/// its parent's elsewhere. The frame count is checked against the summary.
pub fn decode_world(w: &World) -> Result<Motion, MotionError> {
    let done = w
        .done
        .as_ref()
        .ok_or(MotionError::NoSummary { world: w.index })?;
    let payloads = w
        .segments
        .iter()
        .map(SegmentPayload::from_proto)
        .collect::<Result<Vec<_>, _>>()?;
    let frames = u64::from(done.frame_count);
    if !is_layered(done, &w.segments) {
        return decode_segments(&payloads, done.frame_dt, Some(frames));
    }
    let parent = w
        .parent
        .as_deref()
        .ok_or(MotionError::NoParent { world: w.index })?;
    let base = decode_world(parent).map_err(|source| MotionError::Parent {
        world: parent.index,
        source: Box::new(source),
    })?;
    let mut layered =
        Layered::start(base.tracks, frames as usize).map_err(|source| MotionError::Layer {
            seq: done.first_segment,
            source,
        })?;
    let mut next_frame: Option<u64> = None;
    for (i, s) in payloads.iter().enumerate() {
        let seq = s.seq;
        let position = done.first_segment as usize + i;
        if seq as usize != position {
            return Err(MotionError::Order { seq, position });
        }
        if let Some(expected) = next_frame
            && u64::from(s.first_frame) != expected
        {
            return Err(MotionError::Gap {
                seq,
                first_frame: s.first_frame,
                expected,
            });
        }
        let tracks = decode_payload(s)?;
        layered
            .overlay(s.first_frame, s.bodies, tracks)
            .map_err(|source| MotionError::Layer { seq, source })?;
        next_frame = Some(u64::from(s.first_frame) + u64::from(s.frame_count));
    }
    check_frames(next_frame.unwrap_or(0), Some(frames))?;
    Ok(Motion {
        frame_dt: done.frame_dt,
        tracks: layered.finish(),
    })
}

fn all_finite(t: &Track) -> bool {
    t.positions.iter().flatten().all(|x| x.is_finite())
        && t.rotations.iter().flatten().all(|x| x.is_finite())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sign_continuity_flips_only_what_crosses_the_hemisphere() {
        let s = std::f64::consts::FRAC_1_SQRT_2;
        let q = [
            [0.0, 0.0, 0.0, 1.0],
            [0.0, s, 0.0, s],
            [0.0, -s, 0.0, -s], // the same rotation as the key before it
            [0.0, -1.0, 0.0, 0.0],
        ];
        let c = sign_continuous(&q);
        assert_eq!(c[1], q[1]);
        assert_eq!(c[2], q[1]);
        assert_eq!(c[3], [0.0, 1.0, 0.0, 0.0]);
        for w in c.windows(2) {
            let dot: f64 = (0..4).map(|i| w[0][i] * w[1][i]).sum();
            assert!(dot >= 0.0);
        }
    }

    #[test]
    fn out_of_order_and_gapped_segments_are_named() {
        let a = SegmentPayload {
            seq: 1,
            first_frame: 0,
            frame_count: 1,
            body_count: 1,
            bodies: &[],
            kind: PayloadKind::QuantisedFrames,
            payload: &[],
        };
        let e = decode_segments(&[a], 1.0 / 120.0, None).unwrap_err();
        assert!(
            matches!(
                e,
                MotionError::Order {
                    seq: 1,
                    position: 0
                }
            ),
            "{e}"
        );
        let b = SegmentPayload {
            seq: 0,
            first_frame: 5,
            ..a
        };
        let e = decode_segments(&[b], 1.0 / 120.0, None).unwrap_err();
        assert!(matches!(e, MotionError::Gap { seq: 0, .. }), "{e}");
        assert!(matches!(
            decode_segments(&[], 1.0, None),
            Err(MotionError::Empty)
        ));
    }
}
