//! The low-resolution path that travels beside each compressed world (§4.3–4.4): a
//! few-Hz polyline of positions, uncompressed, for instant display and for the query index (the
//! store's OBB tree is built over it), while full decompression happens on demand.

use crate::rotation::Vec3;

/// A polyline through every `stride`-th decoded position (plus the last one), with the largest
/// distance between the full-rate decoded path and the polyline.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LowResPath {
    /// Frame index of each vertex (strictly increasing; first 0, last the final frame).
    pub frames: Vec<u32>,
    /// Vertex positions (decoded positions, rounded to `f32`).
    pub positions: Vec<[f32; 3]>,
    /// For every frame `f`, the decoded full-rate position lies within `max_deviation` of the
    /// polyline point at the same time (linear interpolation between the two vertices around
    /// `f`), and hence within `max_deviation` of the polyline as a set. Against the *input*
    /// motion the distance is at most `max_deviation + e_max`. Includes the `f32` rounding.
    pub max_deviation: f64,
}

impl LowResPath {
    /// Frames between vertices for a given vertex rate (at least 1).
    pub fn stride(frame_dt: f64, hz: f64) -> usize {
        let s = (1.0 / (hz * frame_dt)).round();
        if s.is_finite() && s >= 1.0 {
            s.min(u32::MAX as f64) as usize
        } else {
            1
        }
    }

    /// Builds the path from full-rate positions and measures its deviation.
    pub fn from_positions(positions: &[Vec3], frame_dt: f64, hz: f64) -> Self {
        let n = positions.len();
        if n == 0 {
            return Self::default();
        }
        let stride = Self::stride(frame_dt, hz);
        let mut frames: Vec<u32> = (0..n).step_by(stride).map(|f| f as u32).collect();
        if frames.last().copied() != Some((n - 1) as u32) {
            frames.push((n - 1) as u32);
        }
        let vertices: Vec<[f32; 3]> = frames
            .iter()
            .map(|&f| positions[f as usize].map(|v| v as f32))
            .collect();
        let mut path = Self {
            frames,
            positions: vertices,
            max_deviation: 0.0,
        };
        // Every frame against the polyline point [`LowResPath::position_at`] gives for it,
        // computed span by span instead of searching each frame's span (the same arithmetic,
        // so the same numbers): the frames of a span from its first vertex up to the next, the
        // last span including its end.
        let deviation = |f: usize, p: Vec3| {
            let d: Vec3 = std::array::from_fn(|i| p[i] - positions[f][i]);
            crate::rotation::norm3(d)
        };
        let m = path.frames.len();
        let mut max = 0.0f64;
        if m == 1 {
            let a = path.positions[0].map(f64::from);
            max = (0..n).map(|f| deviation(f, a)).fold(max, f64::max);
        }
        for j in 0..m.saturating_sub(1) {
            let (fa, fb) = (path.frames[j] as usize, path.frames[j + 1] as usize);
            let a = path.positions[j].map(f64::from);
            let b = path.positions[j + 1].map(f64::from);
            let end = if j + 2 == m { fb + 1 } else { fb };
            let span = fb as f64 - fa as f64;
            for f in fa..end {
                let u = (f as f64 - fa as f64) / span;
                let p: Vec3 = std::array::from_fn(|i| a[i] + (b[i] - a[i]) * u);
                max = max.max(deviation(f, p));
            }
        }
        path.max_deviation = max;
        path
    }

    /// The polyline point at (fractional) frame `f`, or `None` outside the path.
    pub fn position_at(&self, f: f64) -> Option<Vec3> {
        let last = *self.frames.last()?;
        if !(0.0..=f64::from(last)).contains(&f) {
            return None;
        }
        // The segment [frames[j], frames[j+1]] containing f.
        let j = self
            .frames
            .partition_point(|&v| f64::from(v) <= f)
            .saturating_sub(1)
            .min(self.frames.len().saturating_sub(2));
        let a = self.positions[j].map(f64::from);
        if self.frames.len() == 1 {
            return Some(a);
        }
        let b = self.positions[j + 1].map(f64::from);
        let (fa, fb) = (f64::from(self.frames[j]), f64::from(self.frames[j + 1]));
        let u = (f - fa) / (fb - fa);
        Some(std::array::from_fn(|i| a[i] + (b[i] - a[i]) * u))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_straight_line_has_only_rounding_deviation() {
        let x: Vec<Vec3> = (0..101).map(|i| [i as f64 * 0.01, 0.0, 0.0]).collect();
        let path = LowResPath::from_positions(&x, 1.0 / 120.0, 4.0);
        assert_eq!(path.frames, vec![0, 30, 60, 90, 100]);
        assert!(path.max_deviation < 1e-6, "{}", path.max_deviation);
    }

    #[test]
    fn deviation_of_a_parabola_matches_the_chord_error() {
        // y = t², sampled every 30 frames: the chord error of a parabola over a span h is h²/4.
        let dt = 1.0 / 120.0;
        let x: Vec<Vec3> = (0..=120)
            .map(|i| [0.0, (i as f64 * dt).powi(2), 0.0])
            .collect();
        let path = LowResPath::from_positions(&x, dt, 4.0);
        let h: f64 = 0.25;
        assert!(
            (path.max_deviation - h * h / 4.0).abs() < 1e-6,
            "{}",
            path.max_deviation
        );
    }

    /// The span-by-span deviation is the one [`LowResPath::position_at`] gives frame by frame.
    #[test]
    fn the_deviation_is_measured_against_position_at() {
        for n in [1usize, 2, 3, 29, 30, 31, 61, 100, 121] {
            let x: Vec<Vec3> = (0..n)
                .map(|i| {
                    let t = i as f64 * 0.013;
                    [t.sin() * 3.1, 1.0 + t * t, (7.0 * t).cos() * 1e-3]
                })
                .collect();
            let path = LowResPath::from_positions(&x, 1.0 / 120.0, 4.0);
            let want = (0..n)
                .map(|f| {
                    let p = path.position_at(f as f64).unwrap();
                    crate::rotation::norm3(std::array::from_fn(|i| p[i] - x[f][i]))
                })
                .fold(0.0, f64::max);
            assert_eq!(path.max_deviation.to_bits(), want.to_bits(), "{n}");
        }
    }

    #[test]
    fn tiny_paths() {
        assert_eq!(
            LowResPath::from_positions(&[], 0.01, 4.0),
            LowResPath::default()
        );
        let one = LowResPath::from_positions(&[[1.0, 2.0, 3.0]], 0.01, 4.0);
        assert_eq!(one.frames, vec![0]);
        assert_eq!(one.max_deviation, 0.0);
        assert_eq!(one.position_at(0.0), Some([1.0, 2.0, 3.0]));
        assert_eq!(LowResPath::stride(0.01, 1e9), 1);
    }
}
