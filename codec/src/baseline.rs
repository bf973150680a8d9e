//! Reference points for the codec's compression ratio: the raw size, and a simple "quantised
//! frames" encoding at the same error bounds that a benchmark can feed to a general-purpose
//! compressor (zstd) to see what the spline codec buys over quantisation + entropy coding.

use crate::Track;
use crate::error::CodecError;
use crate::rotation;

/// Raw storage of one object-frame: position and quaternion as 7 × `f32`.
pub const RAW_BYTES_PER_OBJECT_FRAME: usize = 7 * 4;

/// Raw size of the tracks as 7 × `f32` per object-frame.
pub fn raw_f32_size(tracks: &[Track]) -> usize {
    tracks.iter().map(Track::len).sum::<usize>() * RAW_BYTES_PER_OBJECT_FRAME
}

/// Every frame quantised independently to the same bounds, as a byte vector:
///
/// * positions per axis with step `2·e_max/√3` (Euclidean error ≤ e_max),
/// * quaternion components with step `θ_max/2.5` after choosing the sign closest to the previous
///   frame (angle error ≈ 2·|δq| ≤ θ_max),
/// * per object and channel (x, y, z, qx, qy, qz, qw), frame-to-frame deltas of the quantised
///   integers, zig-zag mapped and written as LEB128 varints — channel-planar, so a general-purpose
///   compressor sees long runs of similar small numbers.
///
/// Layout: `u32` object count, then per object `u32` frame count followed by its 7 channels.
/// The two steps are stored once at the start (2 × f64) after the object count.
pub fn quantised_frames_baseline(
    tracks: &[Track],
    e_max: f64,
    theta_max: f64,
) -> Result<Vec<u8>, CodecError> {
    let (pos_step, rot_step) = baseline_steps(e_max, theta_max)?;
    let mut out = Vec::new();
    out.extend_from_slice(&(tracks.len() as u32).to_le_bytes());
    out.extend_from_slice(&pos_step.to_le_bytes());
    out.extend_from_slice(&rot_step.to_le_bytes());
    for (object, t) in tracks.iter().enumerate() {
        if t.positions.len() != t.rotations.len() {
            return Err(CodecError::TrackLengthMismatch {
                object,
                positions: t.positions.len(),
                rotations: t.rotations.len(),
            });
        }
        out.extend_from_slice(&(t.len() as u32).to_le_bytes());
        let mut quats = Vec::with_capacity(t.len());
        let mut prev = rotation::IDENTITY;
        for (frame, q) in t.rotations.iter().enumerate() {
            let q = rotation::normalise(*q)
                .ok_or(CodecError::DegenerateQuaternion { object, frame })?;
            let d: f64 = (0..4).map(|i| q[i] * prev[i]).sum();
            let q = if d < 0.0 { q.map(|v| -v) } else { q };
            quats.push(q);
            prev = q;
        }
        let channel = |out: &mut Vec<u8>, values: &mut dyn Iterator<Item = f64>, step: f64| {
            let mut last = 0i64;
            for (frame, v) in values.enumerate() {
                let q = (v / step).round();
                if !(q.is_finite() && q.abs() < 9.0e15) {
                    return Err(CodecError::NonFinite {
                        object,
                        frame,
                        what: "baseline sample",
                    });
                }
                let q = q as i64;
                write_varint(out, crate::bits::zigzag(q - last));
                last = q;
            }
            Ok(())
        };
        for axis in 0..3 {
            channel(&mut out, &mut t.positions.iter().map(|p| p[axis]), pos_step)?;
        }
        for c in 0..4 {
            channel(&mut out, &mut quats.iter().map(|q| q[c]), rot_step)?;
        }
    }
    Ok(out)
}

fn baseline_steps(e_max: f64, theta_max: f64) -> Result<(f64, f64), CodecError> {
    if !(e_max.is_finite() && e_max > 0.0) {
        return Err(CodecError::InvalidParam {
            name: "e_max",
            value: e_max,
            expected: "finite and > 0",
        });
    }
    if !(theta_max.is_finite() && theta_max > 0.0) {
        return Err(CodecError::InvalidParam {
            name: "theta_max",
            value: theta_max,
            expected: "finite and > 0",
        });
    }
    Ok((2.0 * e_max / 3f64.sqrt(), theta_max / 2.5))
}

fn write_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read_varint(b: &[u8], at: &mut usize) -> u64 {
        let mut v = 0u64;
        let mut shift = 0;
        loop {
            let byte = b[*at];
            *at += 1;
            v |= u64::from(byte & 0x7f) << shift;
            if byte & 0x80 == 0 {
                return v;
            }
            shift += 7;
        }
    }

    /// Test-only decoder, to check that the baseline really meets the bounds it claims.
    fn decode(b: &[u8]) -> Vec<Track> {
        let n = u32::from_le_bytes(b[0..4].try_into().unwrap()) as usize;
        let ps = f64::from_le_bytes(b[4..12].try_into().unwrap());
        let rs = f64::from_le_bytes(b[12..20].try_into().unwrap());
        let mut at = 20;
        (0..n)
            .map(|_| {
                let frames = u32::from_le_bytes(b[at..at + 4].try_into().unwrap()) as usize;
                at += 4;
                let mut ch = vec![vec![0.0; frames]; 7];
                for (c, values) in ch.iter_mut().enumerate() {
                    let step = if c < 3 { ps } else { rs };
                    let mut last = 0i64;
                    for v in values.iter_mut() {
                        last += crate::bits::unzigzag(read_varint(b, &mut at));
                        *v = last as f64 * step;
                    }
                }
                Track {
                    positions: (0..frames)
                        .map(|f| [ch[0][f], ch[1][f], ch[2][f]])
                        .collect(),
                    rotations: (0..frames)
                        .map(|f| [ch[3][f], ch[4][f], ch[5][f], ch[6][f]])
                        .collect(),
                }
            })
            .collect()
    }

    #[test]
    fn raw_size_is_seven_floats_per_frame() {
        let t = Track {
            positions: vec![[0.0; 3]; 10],
            rotations: vec![[0.0, 0.0, 0.0, 1.0]; 10],
        };
        assert_eq!(raw_f32_size(&[t.clone(), t]), 2 * 10 * 28);
    }

    #[test]
    fn baseline_meets_the_bounds() {
        let (e_max, theta_max) = crate::Quality::Standard.bounds();
        let frames = 500;
        let t = Track {
            positions: (0..frames)
                .map(|i| {
                    let t = i as f64 / 120.0;
                    [1.0 + 0.37 * t, 2.0 + 3.1 * t - 4.9 * t * t, -0.123 * t]
                })
                .collect(),
            rotations: (0..frames)
                .map(|i| {
                    let q = rotation::exp([0.031 * i as f64, -0.017 * i as f64, 0.002 * i as f64]);
                    if i % 7 == 0 { q.map(|v| -v) } else { q }
                })
                .collect(),
        };
        let bytes = quantised_frames_baseline(std::slice::from_ref(&t), e_max, theta_max).unwrap();
        assert!(bytes.len() < raw_f32_size(std::slice::from_ref(&t)));
        let d = &decode(&bytes)[0];
        for f in 0..frames {
            let e: [f64; 3] = std::array::from_fn(|i| d.positions[f][i] - t.positions[f][i]);
            assert!(rotation::norm3(e) <= e_max);
            let q = rotation::normalise(d.rotations[f]).unwrap();
            assert!(rotation::angle_between(q, t.rotations[f]) <= theta_max);
        }
    }
}
