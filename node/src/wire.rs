//! The wire forms every producer of worlds shares: a job's codec preset, and a recorded segment
//! as a `MotionSegment`.

use mwb_proto::v1::{Encoding, LowResPath, MotionSegment, Quality};

/// The job's codec preset; unspecified (or unknown to this version) is standard.
pub fn codec_quality(q: Quality) -> mwb_codec::Quality {
    match q {
        Quality::Draft => mwb_codec::Quality::Draft,
        Quality::Final => mwb_codec::Quality::Final,
        Quality::Standard | Quality::Unspecified => mwb_codec::Quality::Standard,
    }
}

/// One recorded segment of a world, whoever computed it (forward sampler, reverse stepper).
#[derive(Debug, Clone, PartialEq)]
pub struct SegmentBody {
    /// 0-based segment number.
    pub seq: u32,
    /// First frame (playback order).
    pub first_frame: u32,
    pub frame_count: u32,
    pub body_count: u32,
    /// How `payload` is encoded.
    pub encoding: Encoding,
    pub payload: Vec<u8>,
    /// The few-Hz path of each body over this segment.
    pub lowres: Vec<mwb_codec::LowResPath>,
}

/// The wire form of segment `body` of world `(job, node, counter)`: the payload with its CRC32
/// and, beside it, the low-resolution paths.
pub fn segment_message(
    job_id: &str,
    node: &str,
    counter: u64,
    seed: u64,
    body: SegmentBody,
) -> MotionSegment {
    MotionSegment {
        job_id: job_id.to_owned(),
        node_id: node.to_owned(),
        world_counter: counter,
        seed,
        seq: body.seq,
        first_frame: body.first_frame,
        frame_count: body.frame_count,
        body_count: body.body_count,
        encoding: body.encoding as i32,
        crc32: crc32fast::hash(&body.payload),
        lowres: Some(lowres_message(&body.lowres, mwb_codec::DEFAULT_LOWRES_HZ)),
        payload: body.payload,
    }
}

/// A segment's low-resolution paths on the wire: the vertex frames once (they are the same for
/// every body of a segment), then every body's vertices.
fn lowres_message(paths: &[mwb_codec::LowResPath], hz: f64) -> LowResPath {
    LowResPath {
        hz,
        frames: paths.first().map(|p| p.frames.clone()).unwrap_or_default(),
        xyz: paths
            .iter()
            .flat_map(|p| p.positions.iter().flatten().copied())
            .collect(),
        // Rounded up, so the bound stays a bound in f32.
        max_deviation: paths
            .iter()
            .map(|p| {
                let d = p.max_deviation as f32;
                if f64::from(d) < p.max_deviation {
                    d.next_up()
                } else {
                    d
                }
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deviations_round_up_and_the_crc_covers_the_payload() {
        let path = mwb_codec::LowResPath {
            frames: vec![0, 4],
            positions: vec![[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]],
            max_deviation: 0.1,
        };
        let msg = segment_message(
            "j",
            "n",
            3,
            9,
            SegmentBody {
                seq: 1,
                first_frame: 10,
                frame_count: 5,
                body_count: 1,
                encoding: Encoding::SplineV1,
                payload: vec![1, 2, 3],
                lowres: vec![path],
            },
        );
        assert_eq!(msg.crc32, crc32fast::hash(&[1, 2, 3]));
        assert_eq!(msg.encoding, Encoding::SplineV1 as i32);
        let lowres = msg.lowres.unwrap_or_default();
        assert_eq!(lowres.frames, [0, 4]);
        assert_eq!(lowres.xyz, [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
        // 0.1 is not an f32: the f32 sent is the next one up, never below the true bound.
        assert!(f64::from(lowres.max_deviation[0]) >= 0.1);
        assert!(lowres.max_deviation[0] > 0.1f32.next_down());
    }

    #[test]
    fn unknown_quality_is_standard() {
        assert_eq!(
            codec_quality(Quality::Unspecified),
            mwb_codec::Quality::Standard
        );
        assert_eq!(codec_quality(Quality::Draft), mwb_codec::Quality::Draft);
        assert_eq!(codec_quality(Quality::Final), mwb_codec::Quality::Final);
    }
}
