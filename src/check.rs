//! Verifying a fetched world end to end: every segment's CRC, contiguity, and that the payload
//! decodes to the announced number of frames and bodies, all finite. Payloads are motion-codec
//! streams (`SPLINE_V1`) or, in recordings made before the codec, interim quantised frames.

use anyhow::{Context, Result, bail};
use mwb_codec::WorldReader;
use mwb_proto::v1::{Encoding, MotionSegment, World};

/// What a verified world contains.
#[derive(Debug, Clone, PartialEq)]
pub struct WorldCheck {
    pub frames: u32,
    pub bodies: u32,
    /// Payload bytes (compressed motion) the world holds itself (a refined world stored as a
    /// difference: only its own).
    pub bytes: u64,
    /// The same motion as 7 × f32 per body-frame, for comparison.
    pub raw_f32_bytes: u64,
    pub impacts: u64,
}

/// Verifies a fetched world. A refined world stored as a difference from its parent (§4.5)
/// carries its own segments from `first_segment` on and its parent chain
/// ([`World::parent`]): its segments are checked the same way, the parent chain verified in
/// turn, and the composed motion decoded end to end. `bytes` counts what the world itself holds.
pub fn verify_world(w: &World) -> Result<WorldCheck> {
    let Some(done) = &w.done else {
        bail!("world {}: no summary", w.index);
    };
    let own = done.segment_count.checked_sub(done.first_segment);
    if own != Some(w.segments.len() as u32) {
        bail!(
            "world {}: {} segments from segment {}, summary says {} in all",
            w.index,
            w.segments.len(),
            done.first_segment,
            done.segment_count
        );
    }
    let layered = mwb_export::is_layered(done, &w.segments);
    let mut frames = w.segments.first().map_or(0, |s| s.first_frame);
    if !layered && frames != 0 {
        bail!("world {}: segment 0 starts at frame {frames}", w.index);
    }
    let mut bytes = 0u64;
    for (i, s) in w.segments.iter().enumerate() {
        let seq = done.first_segment as usize + i;
        if crc32fast::hash(&s.payload) != s.crc32 {
            bail!("world {}: segment {seq}: CRC mismatch", w.index);
        }
        if s.seq as usize != seq || s.first_frame != frames || s.seed != done.seed {
            bail!("world {}: segment {seq} out of order", w.index);
        }
        verify_payload(s).with_context(|| format!("world {}: segment {seq}", w.index))?;
        frames += s.frame_count;
        bytes += s.payload.len() as u64;
    }
    if frames != done.frame_count {
        bail!(
            "world {}: {frames} frames, summary says {}",
            w.index,
            done.frame_count
        );
    }
    let bodies = if layered {
        let parent = w.parent.as_deref().with_context(|| {
            format!(
                "world {}: stored as a difference from its parent, which did not come with it",
                w.index
            )
        })?;
        verify_world(parent).with_context(|| format!("world {}: its parent", w.index))?;
        let motion = mwb_export::decode_world(w)
            .with_context(|| format!("world {}: composing it over its parent", w.index))?;
        motion.tracks.len() as u32
    } else {
        w.segments.first().map_or(0, |s| s.body_count)
    };
    Ok(WorldCheck {
        frames,
        bodies,
        bytes,
        raw_f32_bytes: u64::from(frames)
            * u64::from(bodies)
            * mwb_codec::RAW_BYTES_PER_OBJECT_FRAME as u64,
        impacts: done.impacts.iter().map(|&x| u64::from(x)).sum(),
    })
}

/// Decodes one segment's payload and checks it against the segment's frame and body counts.
fn verify_payload(s: &MotionSegment) -> Result<()> {
    let finite = |p: &[f64]| p.iter().all(|x| x.is_finite());
    match Encoding::try_from(s.encoding) {
        Ok(Encoding::SplineV1) => {
            let reader = WorldReader::new(&s.payload)?;
            if reader.object_count() != s.body_count as usize
                || reader.frame_count() != s.frame_count as usize
            {
                bail!(
                    "payload holds {} bodies × {} frames, segment says {} × {}",
                    reader.object_count(),
                    reader.frame_count(),
                    s.body_count,
                    s.frame_count
                );
            }
            for (body, track) in reader.decode_all()?.iter().enumerate() {
                if track.len() != s.frame_count as usize {
                    bail!("body {body}: {} frames", track.len());
                }
                if !track.positions.iter().all(|p| finite(p))
                    || !track.rotations.iter().all(|q| finite(q))
                {
                    bail!("body {body}: non-finite pose");
                }
            }
            if let Some(l) = &s.lowres {
                let expected = l.frames.len() * s.body_count as usize * 3;
                if l.xyz.len() != expected || l.max_deviation.len() != s.body_count as usize {
                    bail!("low-res path does not match {} bodies", s.body_count);
                }
                if l.frames.last().is_some_and(|&f| f + 1 != s.frame_count) {
                    bail!("low-res path does not end at the last frame");
                }
            }
        }
        Ok(Encoding::QuantisedFramesV1) => {
            let poses = mwb_core::frames::decode(&s.payload, s.frame_count, s.body_count)?;
            if poses
                .iter()
                .any(|p| !finite(&p.position) || !finite(&p.rotation))
            {
                bail!("non-finite pose");
            }
        }
        Ok(Encoding::Unspecified) | Err(_) => bail!("unknown encoding {}", s.encoding),
    }
    Ok(())
}
