//! Reference points for the codec's compression ratio: the raw size, and a simple "quantised
//! frames" encoding at the same error bounds that a benchmark can feed to a general-purpose
//! compressor (zstd) to see what the spline codec buys over quantisation + entropy coding.

use crate::Track;
use crate::error::CodecError;
use crate::rotation::{self, Quat, Vec3};

/// Raw storage of one object-frame: position and quaternion as 7 × `f32`.
pub const RAW_BYTES_PER_OBJECT_FRAME: usize = 7 * 4;

/// Raw size of the tracks as 7 × `f32` per object-frame.
pub fn raw_f32_size(tracks: &[Track]) -> usize {
    tracks.iter().map(Track::len).sum::<usize>() * RAW_BYTES_PER_OBJECT_FRAME
}

/// How a quantised-frames baseline stores orientations.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BaselineRotation {
    /// The four quaternion components, as raw poses store them (7 numbers per frame).
    Quaternion,
    /// The rotation vector (log map, 3 numbers per frame), kept continuous across frames.
    RotationVector,
}

/// Every frame quantised independently to the same bounds, as a byte vector — what a user who
/// does not have the codec would store and hand to a general-purpose compressor:
///
/// * positions per axis with step `2·e_max/√3`: the Euclidean error is ≤ e_max;
/// * [`BaselineRotation::Quaternion`]: the components with step `sin(θ_max/2)`, after choosing the
///   sign closest to the previous frame. The error vector δ of the four components then has
///   |δ| ≤ step, the normalised quaternion is within `asin(|δ|)` of the input as a direction in
///   4-D, and the rotation angle is twice that: ≤ θ_max. (Until 2026-11-22 the step was
///   `θ_max/2.5`, 80 % of the bound — a weaker baseline, 5–6 % larger after zstd.)
/// * [`BaselineRotation::RotationVector`]: the rotation vector `log q`, unwrapped to the
///   equivalent vector (length changed by a multiple of 2π) nearest the previous frame's, with
///   step `2·θ_max/√3`. The exponential map is 1-Lipschitz (its differential has singular values
///   1 and `sin(φ/2)/(φ/2)`), so an error vector of length ≤ θ_max is a rotation error ≤ θ_max.
///
/// Both steps are shrunk by 10⁻⁹ (relative) against floating-point rounding. Per object and
/// channel (x, y, z, then the rotation's), frame-to-frame deltas of the quantised integers,
/// zig-zag mapped and written as LEB128 varints — channel-planar, so a general-purpose compressor
/// sees long runs of similar small numbers.
///
/// Layout: `u32` object count, then the two steps (2 × f64), then per object `u32` frame count
/// followed by its channels.
pub fn quantised_frames_baseline(
    tracks: &[Track],
    e_max: f64,
    theta_max: f64,
) -> Result<Vec<u8>, CodecError> {
    quantised_baseline(tracks, e_max, theta_max, BaselineRotation::Quaternion)
}

/// [`quantised_frames_baseline`] with a choice of rotation channels.
pub fn quantised_baseline(
    tracks: &[Track],
    e_max: f64,
    theta_max: f64,
    rotation: BaselineRotation,
) -> Result<Vec<u8>, CodecError> {
    let (pos_step, rot_step) = baseline_steps(e_max, theta_max, rotation)?;
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
        match rotation {
            BaselineRotation::Quaternion => {
                for c in 0..4 {
                    channel(&mut out, &mut quats.iter().map(|q| q[c]), rot_step)?;
                }
            }
            BaselineRotation::RotationVector => {
                let vectors = continuous_rotation_vectors(&quats);
                for c in 0..3 {
                    channel(&mut out, &mut vectors.iter().map(|r| r[c]), rot_step)?;
                }
            }
        }
    }
    Ok(out)
}

/// The rotation vectors of unit quaternions, each the equivalent one (length changed by a
/// multiple of 2π, [`rotation::unwrap_near`]) nearest the previous frame's, so a spinning body's
/// vector grows instead of jumping at angle π.
fn continuous_rotation_vectors(quats: &[Quat]) -> Vec<Vec3> {
    let mut out: Vec<Vec3> = Vec::with_capacity(quats.len());
    for &q in quats {
        let r = rotation::log(q);
        out.push(match out.last() {
            Some(&prev) => rotation::unwrap_near(r, prev),
            None => r,
        });
    }
    out
}

fn baseline_steps(
    e_max: f64,
    theta_max: f64,
    rotation: BaselineRotation,
) -> Result<(f64, f64), CodecError> {
    if !(e_max.is_finite() && e_max > 0.0) {
        return Err(CodecError::InvalidParam {
            name: "e_max",
            value: e_max,
            expected: "finite and > 0",
        });
    }
    if !(theta_max.is_finite() && theta_max > 0.0 && theta_max < std::f64::consts::PI) {
        return Err(CodecError::InvalidParam {
            name: "theta_max",
            value: theta_max,
            expected: "in (0, π)",
        });
    }
    let shrink = 1.0 - 1e-9;
    let rot = match rotation {
        BaselineRotation::Quaternion => (theta_max / 2.0).sin(),
        BaselineRotation::RotationVector => 2.0 * theta_max / 3f64.sqrt(),
    };
    Ok((2.0 * e_max / 3f64.sqrt() * shrink, rot * shrink))
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
    fn decode(b: &[u8], rotation: BaselineRotation) -> Vec<Track> {
        let n = u32::from_le_bytes(b[0..4].try_into().unwrap()) as usize;
        let ps = f64::from_le_bytes(b[4..12].try_into().unwrap());
        let rs = f64::from_le_bytes(b[12..20].try_into().unwrap());
        let rot_channels = match rotation {
            BaselineRotation::Quaternion => 4,
            BaselineRotation::RotationVector => 3,
        };
        let mut at = 20;
        (0..n)
            .map(|_| {
                let frames = u32::from_le_bytes(b[at..at + 4].try_into().unwrap()) as usize;
                at += 4;
                let mut ch = vec![vec![0.0; frames]; 3 + rot_channels];
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
                        .map(|f| match rotation {
                            BaselineRotation::Quaternion => {
                                [ch[3][f], ch[4][f], ch[5][f], ch[6][f]]
                            }
                            BaselineRotation::RotationVector => {
                                rotation::exp([ch[3][f], ch[4][f], ch[5][f]])
                            }
                        })
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

    /// The largest position and rotation errors of a baseline over `t`.
    fn errors(t: &Track, e_max: f64, theta_max: f64, rotation: BaselineRotation) -> (f64, f64) {
        let bytes =
            quantised_baseline(std::slice::from_ref(t), e_max, theta_max, rotation).unwrap();
        assert!(bytes.len() < raw_f32_size(std::slice::from_ref(t)));
        let d = &decode(&bytes, rotation)[0];
        let (mut e, mut a) = (0.0f64, 0.0f64);
        for f in 0..t.len() {
            let x: [f64; 3] = std::array::from_fn(|i| d.positions[f][i] - t.positions[f][i]);
            e = e.max(rotation::norm3(x));
            let q = rotation::normalise(d.rotations[f]).unwrap();
            a = a.max(rotation::angle_between(q, t.rotations[f]));
        }
        (e, a)
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
        for rotation in [
            BaselineRotation::Quaternion,
            BaselineRotation::RotationVector,
        ] {
            let (e, a) = errors(&t, e_max, theta_max, rotation);
            assert!(e <= e_max && a <= theta_max, "{rotation:?}: {e} {a}");
        }
    }

    proptest::proptest! {
        /// Random positions and orientations (frame to frame independent, or spins through many
        /// turns) stay within the bound.
        #[test]
        fn baselines_keep_the_bound(
            seed in 0u64..1_000_000,
            spin in 0.0f64..3.0,
            log_bound in -4.0f64..-1.0,
        ) {
            let bound = 10f64.powf(log_bound);
            let mut x = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
            let mut next = move || {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                (x >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
            };
            let axis = [next(), next(), next()];
            let frames = 400;
            let t = Track {
                positions: (0..frames).map(|_| [next(), next(), next()]).collect(),
                rotations: (0..frames)
                    .map(|i| {
                        if spin < 1.0 {
                            rotation::normalise([next(), next(), next(), next()]).unwrap()
                        } else {
                            rotation::exp(axis.map(|a| a * spin * i as f64))
                        }
                    })
                    .collect(),
            };
            for rotation in [BaselineRotation::Quaternion, BaselineRotation::RotationVector] {
                let (e, a) = errors(&t, bound, bound, rotation);
                proptest::prop_assert!(e <= bound, "{:?}: position {} > {}", rotation, e, bound);
                proptest::prop_assert!(a <= bound, "{:?}: rotation {} > {}", rotation, a, bound);
            }
        }
    }

    /// The steps are the coarsest that keep the bound, not a margin below it (a weaker baseline
    /// would flatter the codec): values placed just below the middle between two lattice points
    /// in three coordinates err by nearly the whole bound, and not more.
    #[test]
    fn baselines_use_the_whole_bound() {
        let (e_max, theta_max) = (1e-3, 1e-3);
        for rotation in [
            BaselineRotation::Quaternion,
            BaselineRotation::RotationVector,
        ] {
            let (ps, rs) = baseline_steps(e_max, theta_max, rotation).unwrap();
            let mid = |k: f64, step: f64| (k + 0.5 - 1e-10) * step;
            let position = [mid(3.0, ps), mid(-8.0, ps), mid(120.0, ps)];
            let q = match rotation {
                BaselineRotation::Quaternion => {
                    let v = [mid(5.0, rs), mid(-2.0, rs), mid(11.0, rs)];
                    let w = (1.0 - rotation::dot3(v, v)).sqrt();
                    [v[0], v[1], v[2], w]
                }
                BaselineRotation::RotationVector => {
                    rotation::exp([mid(5.0, rs), mid(-2.0, rs), mid(11.0, rs)])
                }
            };
            let t = Track {
                positions: vec![position; 2],
                rotations: vec![q; 2],
            };
            let (e, a) = errors(&t, e_max, theta_max, rotation);
            assert!(e <= e_max && a <= theta_max, "{rotation:?}: {e} {a}");
            assert!(e > 0.999 * e_max, "{rotation:?}: position {e}");
            // Quaternions: three of four components off by half a step is √3/2 of the bound.
            let used = match rotation {
                BaselineRotation::Quaternion => 0.86,
                BaselineRotation::RotationVector => 0.99,
            };
            assert!(a > used * theta_max, "{rotation:?}: rotation {a}");
        }
    }
}
