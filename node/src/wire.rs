//! The wire forms every producer of worlds shares: a job's codec preset, and a recorded segment
//! as a `MotionSegment`.

use mwb_proto::v1::{Encoding, LowResPath, MotionSegment, Quality, WorldDone};

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
    /// The scene indices of the bodies the payload holds, in order; empty: every body.
    pub bodies: Vec<u32>,
    /// How `payload` is encoded.
    pub encoding: Encoding,
    pub payload: Vec<u8>,
}

/// The wire form of segment `body` of world `(job, node, counter)`: the payload with its CRC32.
/// No low-resolution path goes beside it any more: viewers draw the store's error-bounded index
/// paths (`q/paths`), and the 4 Hz path was about half of a stored tumble world's segment bytes.
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
        bodies: body.bodies,
        encoding: body.encoding as i32,
        crc32: crc32fast::hash(&body.payload),
        lowres: None,
        payload: body.payload,
    }
}

/// A world's digest: a CRC-32 over everything in its segments and summary that its scene text
/// and seed determine — each segment's numbering, encoding, payload and low-resolution path,
/// and the summary's counts, rest times, impacts, perturbations, steps, plausibility numbers
/// and scene hash — and over nothing that names where or when it was computed (job, node,
/// counter, CPU time, provenance, the segments' CRCs, which follow from their payloads) or that
/// the scene hash already decides (the simulation plan). A stored world and its regeneration
/// from `(scene, seed)` (`mwb world`) have equal digests.
pub fn world_digest(segments: &[MotionSegment], done: &WorldDone) -> u32 {
    let mut h = crc32fast::Hasher::new();
    for s in segments {
        // Every field, by destructuring: a new one does not compile until it is decided here.
        let MotionSegment {
            job_id: _,
            node_id: _,
            world_counter: _,
            seed,
            seq,
            first_frame,
            frame_count,
            body_count,
            encoding,
            payload,
            crc32: _,
            lowres,
            bodies,
        } = s;
        h.update(&seed.to_le_bytes());
        for x in [seq, first_frame, frame_count, body_count] {
            h.update(&x.to_le_bytes());
        }
        // Nothing for a segment with every body, so sampled worlds keep their digests.
        bodies.iter().for_each(|b| h.update(&b.to_le_bytes()));
        h.update(&encoding.to_le_bytes());
        h.update(&(payload.len() as u64).to_le_bytes());
        h.update(payload);
        if let Some(LowResPath {
            hz,
            frames,
            xyz,
            max_deviation,
        }) = lowres
        {
            h.update(&hz.to_bits().to_le_bytes());
            frames.iter().for_each(|f| h.update(&f.to_le_bytes()));
            xyz.iter()
                .for_each(|x| h.update(&x.to_bits().to_le_bytes()));
            max_deviation
                .iter()
                .for_each(|x| h.update(&x.to_bits().to_le_bytes()));
        }
    }
    let WorldDone {
        job_id: _,
        node_id: _,
        world_counter: _,
        seed,
        frame_count,
        segment_count,
        frame_dt,
        rested,
        impacts,
        perturbations,
        sim_steps,
        cpu_seconds: _,
        provenance: _,
        scene_hash,
        rest_time_s,
        body_rested,
        energy_growth,
        angular_speed_growth,
        lineage,
        active_from,
        first_segment,
        plausible,
        plausibility_excess,
        sim: _,
        // Derived from the segments (and built by the sampler or the store alike).
        index: _,
    } = done;
    // Nothing for a sampled world (no lineage, no active_from), so their digests stay.
    if let Some(l) = lineage {
        h.update(l.root_job.as_bytes());
        h.update(&l.root_seed.to_le_bytes());
        for step in &l.steps {
            h.update(&step.frame.to_le_bytes());
            h.update(&step.seed.to_le_bytes());
            step.objects.iter().for_each(|o| h.update(&o.to_le_bytes()));
            // Nothing for a refinement (0), so refined worlds keep their digests.
            if step.scene_revision != 0 {
                h.update(&step.scene_revision.to_le_bytes());
            }
        }
    }
    active_from.iter().for_each(|x| h.update(&x.to_le_bytes()));
    // Nothing for a world sent whole (0), so their digests stay.
    if *first_segment > 0 {
        h.update(&first_segment.to_le_bytes());
    }
    for x in [seed, sim_steps, scene_hash] {
        h.update(&x.to_le_bytes());
    }
    for x in [frame_count, segment_count, perturbations] {
        h.update(&x.to_le_bytes());
    }
    h.update(&frame_dt.to_bits().to_le_bytes());
    h.update(&[u8::from(*rested)]);
    impacts.iter().for_each(|x| h.update(&x.to_le_bytes()));
    rest_time_s
        .iter()
        .for_each(|x| h.update(&x.to_bits().to_le_bytes()));
    body_rested.iter().for_each(|x| h.update(&[u8::from(*x)]));
    // Absent (forward worlds) is not 0.
    for x in [energy_growth, angular_speed_growth] {
        match x {
            Some(v) => {
                h.update(&[1]);
                h.update(&v.to_bits().to_le_bytes());
            }
            None => h.update(&[0]),
        }
    }
    // Absent in forward worlds: nothing, so their digests stay.
    if let Some(p) = plausible {
        h.update(&[2, u8::from(*p)]);
    }
    if let Some(x) = plausibility_excess {
        h.update(&x.to_bits().to_le_bytes());
    }
    h.finalize()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_crc_covers_the_payload_and_no_low_res_path_is_sent() {
        let msg = segment_message(
            "j",
            "n",
            3,
            9,
            SegmentBody {
                bodies: Vec::new(),
                seq: 1,
                first_frame: 10,
                frame_count: 5,
                body_count: 1,
                encoding: Encoding::SplineV1,
                payload: vec![1, 2, 3],
            },
        );
        assert_eq!(msg.crc32, crc32fast::hash(&[1, 2, 3]));
        assert_eq!(msg.encoding, Encoding::SplineV1 as i32);
        assert_eq!(msg.lowres, None);
    }

    #[test]
    fn the_digest_ignores_where_a_world_was_computed_and_nothing_else() {
        let seg = segment_message(
            "j",
            "n",
            3,
            9,
            SegmentBody {
                bodies: Vec::new(),
                seq: 0,
                first_frame: 0,
                frame_count: 5,
                body_count: 1,
                encoding: Encoding::SplineV1,
                payload: vec![1, 2, 3],
            },
        );
        let done = WorldDone {
            job_id: "j".into(),
            node_id: "n".into(),
            seed: 9,
            frame_count: 5,
            segment_count: 1,
            impacts: vec![2],
            ..Default::default()
        };
        let d = world_digest(std::slice::from_ref(&seg), &done);
        let elsewhere = MotionSegment {
            job_id: "other".into(),
            node_id: "m".into(),
            world_counter: 7,
            ..seg.clone()
        };
        let later = WorldDone {
            job_id: "other".into(),
            node_id: "m".into(),
            world_counter: 7,
            cpu_seconds: 1.5,
            provenance: "another build".into(),
            ..done.clone()
        };
        assert_eq!(world_digest(&[elsewhere], &later), d);
        let mut flipped = seg.clone();
        flipped.payload[1] ^= 1;
        assert_ne!(world_digest(&[flipped], &done), d);
        let measured = WorldDone {
            energy_growth: Some(0.0),
            ..done.clone()
        };
        assert_ne!(world_digest(std::slice::from_ref(&seg), &measured), d);
        let other_scene = WorldDone {
            scene_hash: 1,
            ..done
        };
        assert_ne!(world_digest(&[seg], &other_scene), d);
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
