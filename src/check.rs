//! Verifying a fetched world end to end: every segment's CRC, contiguity, and that the payload
//! decodes to the announced number of frames.

use anyhow::{Result, bail};
use mwb_proto::v1::{Encoding, World};

/// What a verified world contains.
#[derive(Debug, Clone, PartialEq)]
pub struct WorldCheck {
    pub frames: u32,
    pub bodies: u32,
    pub bytes: u64,
    pub impacts: u64,
}

pub fn verify_world(w: &World) -> Result<WorldCheck> {
    let Some(done) = &w.done else {
        bail!("world {}: no summary", w.index);
    };
    if w.segments.len() != done.segment_count as usize {
        bail!(
            "world {}: {} segments, summary says {}",
            w.index,
            w.segments.len(),
            done.segment_count
        );
    }
    let mut frames = 0u32;
    let mut bytes = 0u64;
    let bodies = w.segments.first().map_or(0, |s| s.body_count);
    for (i, s) in w.segments.iter().enumerate() {
        if crc32fast::hash(&s.payload) != s.crc32 {
            bail!("world {}: segment {i}: CRC mismatch", w.index);
        }
        if s.seq as usize != i || s.first_frame != frames || s.seed != done.seed {
            bail!("world {}: segment {i} out of order", w.index);
        }
        if s.encoding != Encoding::QuantisedFramesV1 as i32 {
            bail!(
                "world {}: segment {i}: unknown encoding {}",
                w.index,
                s.encoding
            );
        }
        let poses = mwb_core::frames::decode(&s.payload, s.frame_count, s.body_count)?;
        if poses.iter().any(|p| {
            p.position.iter().any(|x| !x.is_finite()) || p.rotation.iter().any(|x| !x.is_finite())
        }) {
            bail!("world {}: segment {i}: non-finite pose", w.index);
        }
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
    Ok(WorldCheck {
        frames,
        bodies,
        bytes,
        impacts: done.impacts.iter().map(|&x| u64::from(x)).sum(),
    })
}
