//! The interim motion payload: quantised frames (`ENCODING_QUANTISED_FRAMES_V1`).
//!
//! Until the error-bounded spline codec of §4.3 replaces it, a segment's payload is every frame
//! of every body, quantised and delta-coded: position to [`POS_QUANTUM_M`], quaternion
//! components to 1/32767; each value is the zig-zag varint of its difference from the same
//! body's previous frame in the segment (the first frame of a segment is relative to zero, so a
//! segment decodes on its own). The quaternion sign is chosen per frame to stay on the previous
//! frame's hemisphere, so deltas stay small through the double cover.

use thiserror::Error;

/// Position quantum, metres (maximum error per axis is half of it).
pub const POS_QUANTUM_M: f64 = 1e-4;
/// Quaternion component scale.
const ROT_SCALE: f64 = 32767.0;
/// Values per body per frame: x, y, z, qx, qy, qz, qw.
const VALUES: usize = 7;

/// One body's pose in one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub position: [f64; 3],
    /// Unit quaternion `[x, y, z, w]`.
    pub rotation: [f64; 4],
}

#[derive(Debug, Error, PartialEq, Eq)]
pub enum FrameError {
    #[error("frame payload: {frames} frames × {bodies} bodies cannot fit in {len} bytes")]
    TooShort {
        frames: u32,
        bodies: u32,
        len: usize,
    },
    #[error("frame payload: truncated varint at byte {at}")]
    Truncated { at: usize },
    #[error("frame payload: varint overflow at byte {at}")]
    Overflow { at: usize },
    #[error("frame payload: {extra} trailing bytes")]
    Trailing { extra: usize },
    #[error("frame payload: pose count {poses} is not a multiple of body count {bodies}")]
    Shape { poses: usize, bodies: usize },
}

fn put_varint(out: &mut Vec<u8>, v: i64) {
    let mut z = ((v << 1) ^ (v >> 63)) as u64;
    while z >= 0x80 {
        out.push((z as u8) | 0x80);
        z >>= 7;
    }
    out.push(z as u8);
}

fn get_varint(buf: &[u8], at: &mut usize) -> Result<i64, FrameError> {
    let start = *at;
    let mut z: u64 = 0;
    for shift in (0..70).step_by(7) {
        let Some(&b) = buf.get(*at) else {
            return Err(FrameError::Truncated { at: start });
        };
        *at += 1;
        if shift == 63 && b > 1 {
            return Err(FrameError::Overflow { at: start });
        }
        z |= u64::from(b & 0x7f) << shift;
        if b & 0x80 == 0 {
            return Ok(((z >> 1) as i64) ^ -((z & 1) as i64));
        }
    }
    Err(FrameError::Overflow { at: start })
}

fn quantise(pose: &Pose, prev_q: &[i64; VALUES]) -> [i64; VALUES] {
    let p = pose.position;
    let mut q = pose.rotation;
    // Stay on the previous quaternion's hemisphere (q and −q are the same rotation).
    let prev = [prev_q[3], prev_q[4], prev_q[5], prev_q[6]];
    let dot: f64 = (0..4).map(|i| q[i] * prev[i] as f64).sum();
    let flip = if prev == [0; 4] {
        q[3] < 0.0
    } else {
        dot < 0.0
    };
    if flip {
        q = [-q[0], -q[1], -q[2], -q[3]];
    }
    let qp = |x: f64| (x / POS_QUANTUM_M).round() as i64;
    let qr = |x: f64| (x.clamp(-1.0, 1.0) * ROT_SCALE).round() as i64;
    [
        qp(p[0]),
        qp(p[1]),
        qp(p[2]),
        qr(q[0]),
        qr(q[1]),
        qr(q[2]),
        qr(q[3]),
    ]
}

/// Encodes `poses` (frame-major: frame 0 body 0, frame 0 body 1, …).
pub fn encode(poses: &[Pose], body_count: usize) -> Result<Vec<u8>, FrameError> {
    if body_count == 0 || !poses.len().is_multiple_of(body_count) {
        return Err(FrameError::Shape {
            poses: poses.len(),
            bodies: body_count,
        });
    }
    let mut out = Vec::with_capacity(poses.len() * VALUES * 2);
    let mut prev = vec![[0i64; VALUES]; body_count];
    for (i, pose) in poses.iter().enumerate() {
        let b = i % body_count;
        let cur = quantise(pose, &prev[b]);
        for k in 0..VALUES {
            put_varint(&mut out, cur[k].wrapping_sub(prev[b][k]));
        }
        prev[b] = cur;
    }
    Ok(out)
}

/// Decodes a payload of `frames` × `bodies` poses. Never panics and never allocates more than
/// the payload can describe (every value takes at least one byte).
pub fn decode(payload: &[u8], frames: u32, bodies: u32) -> Result<Vec<Pose>, FrameError> {
    let n = u64::from(frames) * u64::from(bodies);
    if n.saturating_mul(VALUES as u64) > payload.len() as u64 || (bodies == 0 && frames > 0) {
        return Err(FrameError::TooShort {
            frames,
            bodies,
            len: payload.len(),
        });
    }
    let n = n as usize;
    let bodies = bodies as usize;
    let mut out = Vec::with_capacity(n);
    let mut prev = vec![[0i64; VALUES]; bodies.max(1)];
    let mut at = 0;
    for i in 0..n {
        let b = i % bodies;
        let mut cur = [0i64; VALUES];
        for k in 0..VALUES {
            cur[k] = prev[b][k].wrapping_add(get_varint(payload, &mut at)?);
        }
        prev[b] = cur;
        let mut q = [
            cur[3] as f64 / ROT_SCALE,
            cur[4] as f64 / ROT_SCALE,
            cur[5] as f64 / ROT_SCALE,
            cur[6] as f64 / ROT_SCALE,
        ];
        let len = q.iter().map(|x| x * x).sum::<f64>().sqrt();
        if len > 0.0 && len.is_finite() {
            q = q.map(|x| x / len);
        } else {
            q = [0.0, 0.0, 0.0, 1.0];
        }
        out.push(Pose {
            position: [
                cur[0] as f64 * POS_QUANTUM_M,
                cur[1] as f64 * POS_QUANTUM_M,
                cur[2] as f64 * POS_QUANTUM_M,
            ],
            rotation: q,
        });
    }
    if at != payload.len() {
        return Err(FrameError::Trailing {
            extra: payload.len() - at,
        });
    }
    Ok(out)
}

/// `v` rotated by the unit quaternion `q = [x, y, z, w]` (`v + 2w(u×v) + 2u×(u×v)`, u the
/// vector part).
pub fn rotate_vector(q: [f64; 4], v: [f64; 3]) -> [f64; 3] {
    let [x, y, z, w] = q;
    let u = [x, y, z];
    let cross = |a: [f64; 3], b: [f64; 3]| {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    };
    let t = cross(u, v).map(|c| 2.0 * c);
    let c = cross(u, t);
    [0, 1, 2].map(|k| v[k] + w * t[k] + c[k])
}

/// Angle (radians) of the rotation taking quaternion `a` to `b` (q ≡ −q; inputs need not be
/// exactly unit). Computed as 2·atan2(‖v‖, |w|) of `conj(a)·b`, which stays accurate for the
/// small angles error bounds are about (an `acos` of the dot product loses half the digits).
pub fn rotation_angle_between(a: [f64; 4], b: [f64; 4]) -> f64 {
    let unit = |q: [f64; 4]| {
        let n = q.iter().map(|x| x * x).sum::<f64>().sqrt();
        q.map(|x| x / n)
    };
    let ([ax, ay, az, aw], [bx, by, bz, bw]) = (unit(a), unit(b));
    let w = aw * bw + ax * bx + ay * by + az * bz;
    let v = [
        aw * bx - bw * ax - (ay * bz - az * by),
        aw * by - bw * ay - (az * bx - ax * bz),
        aw * bz - bw * az - (ax * by - ay * bx),
    ];
    2.0 * v.iter().map(|x| x * x).sum::<f64>().sqrt().atan2(w.abs())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn a_quarter_turn_about_z_takes_x_to_y() {
        let h = std::f64::consts::FRAC_PI_4;
        let q = [0.0, 0.0, h.sin(), h.cos()];
        let r = rotate_vector(q, [1.0, 0.0, 0.0]);
        assert!(
            (r[0]).abs() < 1e-15 && (r[1] - 1.0).abs() < 1e-15 && r[2].abs() < 1e-15,
            "{r:?}"
        );
        // The identity leaves a vector alone; a rotation keeps its length and the angle.
        assert_eq!(
            rotate_vector([0.0, 0.0, 0.0, 1.0], [1.0, 2.0, 3.0]),
            [1.0, 2.0, 3.0]
        );
        let q = unit([0.3, -0.2, 0.5, 0.8]);
        let v = rotate_vector(q, [1.0, 2.0, 3.0]);
        let len = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        assert!((len - 14f64.sqrt()).abs() < 1e-12);
    }

    fn unit(q: [f64; 4]) -> [f64; 4] {
        let l = q.iter().map(|x| x * x).sum::<f64>().sqrt();
        q.map(|x| x / l)
    }

    proptest! {
        #[test]
        fn roundtrip_within_quantum(
            raw in prop::collection::vec(
                (prop::array::uniform3(-100.0f64..100.0), prop::array::uniform4(-1.0f64..1.0)), 1..60),
            bodies in 1usize..4,
        ) {
            let frames = raw.len() / bodies;
            prop_assume!(frames > 0);
            let poses: Vec<Pose> = raw[..frames * bodies].iter()
                .filter(|(_, q)| q.iter().map(|x| x * x).sum::<f64>() > 0.01)
                .map(|(p, q)| Pose { position: *p, rotation: unit(*q) })
                .collect();
            let frames = poses.len() / bodies;
            let poses = &poses[..frames * bodies];
            let bytes = encode(poses, bodies).unwrap_or_else(|e| panic!("{e}"));
            let back = decode(&bytes, frames as u32, bodies as u32).unwrap_or_else(|e| panic!("{e}"));
            prop_assert_eq!(back.len(), poses.len());
            for (a, b) in poses.iter().zip(&back) {
                for k in 0..3 {
                    prop_assert!((a.position[k] - b.position[k]).abs() <= POS_QUANTUM_M * 0.5 + 1e-9);
                }
                prop_assert!(rotation_angle_between(a.rotation, b.rotation) < 2e-4);
            }
        }

        #[test]
        fn arbitrary_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..200),
                                       frames in 0u32..1000, bodies in 0u32..1000) {
            let _ = decode(&bytes, frames, bodies);
        }
    }

    #[test]
    fn huge_counts_are_refused_before_allocating() {
        assert!(matches!(
            decode(&[0; 10], u32::MAX, u32::MAX),
            Err(FrameError::TooShort { .. })
        ));
    }

    #[test]
    fn resting_bodies_cost_seven_bytes_per_frame() {
        let pose = Pose {
            position: [1.0, 0.5, -2.0],
            rotation: unit([0.1, 0.2, 0.3, 0.9]),
        };
        let poses = vec![pose; 100];
        let bytes = encode(&poses, 1).unwrap_or_else(|e| panic!("{e}"));
        // first frame absolute, then 99 frames of seven zero deltas
        assert!(bytes.len() <= 7 * 99 + 7 * 3);
    }
}
