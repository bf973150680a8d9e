//! The viewer's camera: a DCC-style orbit camera (target, yaw, pitch, distance) that always
//! hands out a [`mwb_core::browse::Camera`], so what is drawn and what is queried come from one
//! projection.
//!
//! Conventions are `mwb_core::browse`'s (glTF): the camera looks down its local −z with +y up;
//! the world is y-up (scenes put gravity along −y). Yaw turns about world +y, pitch lifts the
//! eye above the target (positive pitch looks down).

use mwb_core::browse::{self, Intrinsics, Viewport};
use serde::{Deserialize, Serialize};

use crate::math::{V3, add, dot, len, normalize, scale, sub};

/// Pitch is kept just short of the poles, where yaw would be undefined.
pub const MAX_PITCH_RAD: f64 = 1.55;
/// Closest the eye may come to the target, metres.
pub const MIN_DISTANCE_M: f64 = 0.05;

/// An orbit camera. Every field is plain data: the state changes it only through messages.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct OrbitCamera {
    /// The point orbited about and looked at.
    pub target: V3,
    /// Radians about world +y; 0 puts the eye on the +z side of the target.
    pub yaw: f64,
    /// Radians above the target's horizontal plane, |pitch| ≤ [`MAX_PITCH_RAD`].
    pub pitch: f64,
    /// Eye to target, metres, ≥ [`MIN_DISTANCE_M`].
    pub distance: f64,
    /// Full vertical field of view, radians.
    pub fov_y_rad: f64,
    pub near: f64,
    pub far: f64,
}

impl Default for OrbitCamera {
    fn default() -> Self {
        Self {
            target: [0.0, 0.5, 0.0],
            yaw: 0.6,
            pitch: 0.45,
            distance: 8.0,
            fov_y_rad: 45f64.to_radians(),
            near: 0.05,
            far: browse::DEFAULT_FAR_M,
        }
    }
}

/// Quaternion `[x, y, z, w]` of a rotation by `angle` about a unit `axis`.
fn axis_angle(axis: V3, angle: f64) -> [f64; 4] {
    let (s, c) = (0.5 * angle).sin_cos();
    [axis[0] * s, axis[1] * s, axis[2] * s, c]
}

fn quat_mul(a: [f64; 4], b: [f64; 4]) -> [f64; 4] {
    [
        a[3] * b[0] + a[0] * b[3] + a[1] * b[2] - a[2] * b[1],
        a[3] * b[1] - a[0] * b[2] + a[1] * b[3] + a[2] * b[0],
        a[3] * b[2] + a[0] * b[1] - a[1] * b[0] + a[2] * b[3],
        a[3] * b[3] - a[0] * b[0] - a[1] * b[1] - a[2] * b[2],
    ]
}

impl OrbitCamera {
    /// Unit vector from the target to the eye.
    pub fn back(&self) -> V3 {
        let (sp, cp) = self.pitch.sin_cos();
        let (sy, cy) = self.yaw.sin_cos();
        [cp * sy, sp, cp * cy]
    }

    /// The eye position, world space.
    pub fn eye(&self) -> V3 {
        add(self.target, scale(self.back(), self.distance))
    }

    /// Camera-to-world rotation `[x, y, z, w]`: yaw about world +y after pitch about camera +x.
    pub fn rotation(&self) -> [f64; 4] {
        quat_mul(
            axis_angle([0.0, 1.0, 0.0], self.yaw),
            axis_angle([1.0, 0.0, 0.0], -self.pitch),
        )
    }

    /// The browsing camera for a view of `viewport` pixels: the one the view draws with and the
    /// one every constraint drawn in that view is built from.
    pub fn browse_camera(&self, viewport: Viewport) -> browse::Camera {
        browse::Camera {
            position: self.eye(),
            rotation: self.rotation(),
            intrinsics: Intrinsics::VerticalFov {
                fov_y_rad: self.fov_y_rad,
            },
            viewport,
            near: self.near,
            far: self.far,
        }
    }

    /// Turns about the target (yaw, pitch in radians).
    pub fn orbit(&mut self, d_yaw: f64, d_pitch: f64) {
        self.yaw = (self.yaw + d_yaw).rem_euclid(std::f64::consts::TAU);
        self.pitch = (self.pitch + d_pitch).clamp(-MAX_PITCH_RAD, MAX_PITCH_RAD);
    }

    /// Slides target and eye in the image plane so that the target moves by `(dx, dy)` pixels
    /// on a view `height` pixels tall (the point under the cursor follows the cursor at the
    /// target's depth).
    pub fn pan(&mut self, dx: f64, dy: f64, height: f64) {
        if height.is_nan() || height <= 0.0 {
            return;
        }
        let metres_per_px = 2.0 * self.distance * (0.5 * self.fov_y_rad).tan() / height;
        let q = self.rotation();
        let right = rotate(q, [1.0, 0.0, 0.0]);
        let up = rotate(q, [0.0, 1.0, 0.0]);
        let shift = add(
            scale(right, -dx * metres_per_px),
            scale(up, dy * metres_per_px),
        );
        self.target = add(self.target, shift);
    }

    /// Dollies towards the target: `factor` < 1 comes closer.
    pub fn zoom(&mut self, factor: f64) {
        if factor.is_finite() && factor > 0.0 {
            self.distance = (self.distance * factor).clamp(MIN_DISTANCE_M, 0.5 * self.far);
        }
    }

    /// Looks at the sphere (`centre`, `radius`) from the current direction, close enough that it
    /// fills the smaller of the two fields of view of a view `aspect` = width / height.
    pub fn frame(&mut self, centre: V3, radius: f64, aspect: f64) {
        let radius = if radius.is_finite() && radius > 0.0 {
            radius
        } else {
            1.0
        };
        let half_y = 0.5 * self.fov_y_rad;
        let half_x = (half_y.tan() * aspect.max(0.1)).atan();
        let half = half_y.min(half_x);
        self.target = centre;
        self.distance = (1.1 * radius / half.sin()).max(MIN_DISTANCE_M);
    }

    /// The orbit camera looking like `camera` does: same eye, same viewing direction and field
    /// of view (a roll about the viewing axis is dropped, as the orbit camera keeps +y up). The
    /// target is put on the viewing ray at the depth of `focus`, at least 1 m away.
    pub fn from_browse(camera: &browse::Camera, focus: V3) -> Result<Self, browse::BrowseError> {
        let p = camera.projection()?;
        let forward = p.forward();
        let eye = p.position();
        let depth = dot(sub(focus, eye), forward).max(1.0);
        let back = scale(forward, -1.0);
        let pitch = back[1]
            .clamp(-1.0, 1.0)
            .asin()
            .clamp(-MAX_PITCH_RAD, MAX_PITCH_RAD);
        let yaw = back[0].atan2(back[2]);
        let fov_y_rad = match camera.intrinsics {
            Intrinsics::VerticalFov { fov_y_rad } => fov_y_rad,
            Intrinsics::Pinhole { fy, .. } => {
                2.0 * (0.5 * f64::from(camera.viewport.height) / fy).atan()
            }
        };
        Ok(Self {
            target: add(eye, scale(forward, depth)),
            yaw,
            pitch,
            distance: depth,
            fov_y_rad,
            near: camera.near,
            far: camera.far,
        })
    }
}

/// Rotates `v` by the unit quaternion `q`.
pub fn rotate(q: [f64; 4], v: V3) -> V3 {
    let u = [q[0], q[1], q[2]];
    let w = q[3];
    let uv = crate::math::cross(u, v);
    let uuv = crate::math::cross(u, uv);
    add(v, add(scale(uv, 2.0 * w), scale(uuv, 2.0)))
}

/// Bounding sphere of points (centre of their box, radius to the farthest).
pub fn bounding_sphere(points: impl Iterator<Item = V3> + Clone) -> Option<(V3, f64)> {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    let mut any = false;
    for p in points.clone() {
        if p.iter().all(|c| c.is_finite()) {
            any = true;
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
    }
    if !any {
        return None;
    }
    let c = scale(add(lo, hi), 0.5);
    let r = points
        .filter(|p| p.iter().all(|c| c.is_finite()))
        .map(|p| len(sub(p, c)))
        .fold(0.0, f64::max);
    Some((c, r.max(0.1)))
}

/// The direction from the eye through the centre of the view (unit).
pub fn forward_of(camera: &OrbitCamera) -> V3 {
    normalize(scale(camera.back(), -1.0)).unwrap_or([0.0, 0.0, -1.0])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn vp() -> Viewport {
        Viewport {
            width: 800,
            height: 600,
        }
    }

    #[test]
    fn the_target_projects_to_the_view_centre_and_the_eye_looks_at_it() {
        for (yaw, pitch) in [(0.0, 0.0), (0.6, 0.45), (2.5, -0.7), (4.0, 1.5)] {
            let cam = OrbitCamera {
                yaw,
                pitch,
                target: [0.3, 0.2, -1.0],
                ..OrbitCamera::default()
            };
            let p = cam.browse_camera(vp()).projection().expect("valid camera");
            let (px, depth) = p.project(cam.target).expect("in front");
            assert!((px[0] - 400.0).abs() < 1e-9 && (px[1] - 300.0).abs() < 1e-9);
            assert!((depth - cam.distance).abs() < 1e-9);
            // World up stays up on screen (no roll): a point above the target is above it.
            let (above, _) = p
                .project(add(cam.target, [0.0, 0.1, 0.0]))
                .expect("in front");
            assert!(above[1] < 300.0 || pitch.abs() > 1.5);
        }
    }

    #[test]
    fn orbit_pan_zoom_frame() {
        let mut cam = OrbitCamera::default();
        cam.orbit(0.0, 10.0);
        assert_eq!(cam.pitch, MAX_PITCH_RAD);
        cam.zoom(0.5);
        assert_eq!(cam.distance, 4.0);
        cam.zoom(-1.0);
        assert_eq!(cam.distance, 4.0);
        let mut c2 = OrbitCamera::default();
        let before = c2.browse_camera(vp()).projection().expect("ok");
        let t0 = c2.target;
        c2.pan(10.0, 0.0, 600.0);
        // The old target moves 10 px right on the panned view.
        let after = c2.browse_camera(vp()).projection().expect("ok");
        let (a, _) = after.project(t0).expect("front");
        let (b, _) = before.project(t0).expect("front");
        assert!((a[0] - b[0] - 10.0).abs() < 1e-6 && (a[1] - b[1]).abs() < 1e-6);
        c2.frame([1.0, 2.0, 3.0], 2.0, 4.0 / 3.0);
        assert_eq!(c2.target, [1.0, 2.0, 3.0]);
        let p = c2.browse_camera(vp()).projection().expect("ok");
        // The sphere's top point is inside the view.
        let (top, _) = p.project([1.0, 4.0, 3.0]).expect("front");
        assert!(top[1] > 0.0 && top[1] < 300.0);
    }

    #[test]
    fn from_browse_keeps_eye_and_direction() {
        let cam = OrbitCamera {
            yaw: 1.0,
            pitch: 0.3,
            ..OrbitCamera::default()
        };
        let b = cam.browse_camera(vp());
        let back = OrbitCamera::from_browse(&b, cam.target).expect("valid");
        let b2 = back.browse_camera(vp());
        for k in 0..3 {
            assert!((b.position[k] - b2.position[k]).abs() < 1e-9);
        }
        for k in 0..4 {
            assert!((b.rotation[k] - b2.rotation[k]).abs() < 1e-9);
        }
    }
}
