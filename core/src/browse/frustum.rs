//! Screen rectangles seen through a pinhole camera, as world-space frusta (§4.4.1).
//!
//! §4.4.1 draws every query in screen space: it is less precise than a 3D prism but much faster
//! to draw, and a rectangle on the image plane of a pinhole camera sweeps out a frustum in the
//! world. Camera conventions follow glTF: the camera looks down its local −z with +y up and +x
//! to the right; pixel coordinates start at the top-left corner of the viewport, x to the right,
//! y down.

use serde::{Deserialize, Serialize};

use super::geom::{
    Quat, Vec3, add, cross, dot, norm, normalize, quat_conj, quat_normalize, quat_rotate, scale,
    sub,
};
use super::{BrowseError, finite};

/// Default near clip distance, metres (along the viewing axis).
pub const DEFAULT_NEAR_M: f64 = 0.01;
/// Default far clip distance, metres. Finite so that every frustum is bounded and its corners
/// can be drawn (§4.4.2 draws constraint frusta with fractional alpha for click-to-remove).
pub const DEFAULT_FAR_M: f64 = 1000.0;

fn default_near() -> f64 {
    DEFAULT_NEAR_M
}

fn default_far() -> f64 {
    DEFAULT_FAR_M
}

/// Pinhole intrinsics, either as a vertical field of view (square pixels, principal point at the
/// viewport centre, like glTF's `perspective.yfov`) or as a calibrated matrix in pixels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "model", rename_all = "snake_case")]
pub enum Intrinsics {
    VerticalFov {
        /// Full vertical field of view, radians, in (0, π).
        fov_y_rad: f64,
    },
    Pinhole {
        /// Focal lengths, pixels.
        fx: f64,
        fy: f64,
        /// Principal point, pixels from the top-left corner.
        cx: f64,
        cy: f64,
    },
}

/// The size of the image the rectangle was drawn on, pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Viewport {
    pub width: u32,
    pub height: u32,
}

/// A camera pose plus intrinsics, as the viewer sends it with a constraint.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    /// Centre of projection, world space.
    pub position: Vec3,
    /// Orientation `[x, y, z, w]` taking camera axes to world axes (normalised on use).
    pub rotation: Quat,
    pub intrinsics: Intrinsics,
    pub viewport: Viewport,
    /// Near and far clip distances along the viewing axis, metres; 0 < near < far < ∞.
    #[serde(default = "default_near")]
    pub near: f64,
    #[serde(default = "default_far")]
    pub far: f64,
}

/// A rectangle in pixel coordinates (corners in any order).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ScreenRect {
    pub x0: f64,
    pub y0: f64,
    pub x1: f64,
    pub y1: f64,
}

/// A validated camera: everything needed to go between pixels and world points.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Projection {
    position: Vec3,
    rotation: Quat,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    near: f64,
    far: f64,
}

/// A [`Projection`] as a rotation matrix, translation and intrinsics ([`Projection::matrix`]):
/// nine multiplications and one division a point, for drawing many points.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProjectionMatrix {
    /// World → camera rotation, row by row (the camera's x, y and z axes in world space).
    pub rows: [Vec3; 3],
    /// World → camera translation (applied after the rotation).
    pub t: Vec3,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl ProjectionMatrix {
    /// `p` in camera space.
    #[inline]
    pub fn local(&self, p: Vec3) -> Vec3 {
        let [a, b, c] = &self.rows;
        [
            a[0] * p[0] + a[1] * p[1] + a[2] * p[2] + self.t[0],
            b[0] * p[0] + b[1] * p[1] + b[2] * p[2] + self.t[1],
            c[0] * p[0] + c[1] * p[1] + c[2] * p[2] + self.t[2],
        ]
    }

    /// The pixel of a camera-space point (see [`local`](Self::local)) and its depth; `None`
    /// at or behind the centre of projection.
    #[inline]
    pub fn pixel(&self, local: Vec3) -> Option<([f64; 2], f64)> {
        let depth = -local[2];
        (depth > 0.0).then(|| {
            let inv = 1.0 / depth;
            (
                [
                    self.cx + self.fx * local[0] * inv,
                    self.cy - self.fy * local[1] * inv,
                ],
                depth,
            )
        })
    }

    /// [`Projection::project`], by the matrix.
    #[inline]
    pub fn project(&self, p: Vec3) -> Option<([f64; 2], f64)> {
        self.pixel(self.local(p))
    }
}

impl Camera {
    /// Checks every field and returns the camera ready for projecting.
    pub fn projection(&self) -> Result<Projection, BrowseError> {
        for (i, field) in ["position.x", "position.y", "position.z"]
            .into_iter()
            .enumerate()
        {
            finite(field, self.position[i])?;
        }
        for (i, field) in ["rotation.x", "rotation.y", "rotation.z", "rotation.w"]
            .into_iter()
            .enumerate()
        {
            finite(field, self.rotation[i])?;
        }
        let rotation =
            quat_normalize(self.rotation).ok_or(BrowseError::ZeroVector { field: "rotation" })?;
        let (w, h) = (self.viewport.width, self.viewport.height);
        if w == 0 || h == 0 {
            return Err(BrowseError::OutOfRange {
                field: if w == 0 {
                    "viewport.width"
                } else {
                    "viewport.height"
                },
                value: 0.0,
                expected: "at least 1 pixel",
            });
        }
        let (fx, fy, cx, cy) = match self.intrinsics {
            Intrinsics::VerticalFov { fov_y_rad } => {
                let fov = finite("intrinsics.fov_y_rad", fov_y_rad)?;
                if !(fov > 0.0 && fov < std::f64::consts::PI) {
                    return Err(BrowseError::OutOfRange {
                        field: "intrinsics.fov_y_rad",
                        value: fov,
                        expected: "a field of view in (0, π) radians",
                    });
                }
                let f = 0.5 * f64::from(h) / (0.5 * fov).tan();
                (f, f, 0.5 * f64::from(w), 0.5 * f64::from(h))
            }
            Intrinsics::Pinhole { fx, fy, cx, cy } => {
                for (field, v) in [("intrinsics.fx", fx), ("intrinsics.fy", fy)] {
                    if finite(field, v)? <= 0.0 {
                        return Err(BrowseError::OutOfRange {
                            field,
                            value: v,
                            expected: "a positive focal length in pixels",
                        });
                    }
                }
                (
                    fx,
                    fy,
                    finite("intrinsics.cx", cx)?,
                    finite("intrinsics.cy", cy)?,
                )
            }
        };
        let near = finite("near", self.near)?;
        if near <= 0.0 {
            return Err(BrowseError::OutOfRange {
                field: "near",
                value: near,
                expected: "a positive distance",
            });
        }
        let far = finite("far", self.far)?;
        if far <= near {
            return Err(BrowseError::OutOfRange {
                field: "far",
                value: far,
                expected: "a finite distance beyond near",
            });
        }
        Ok(Projection {
            position: self.position,
            rotation,
            fx,
            fy,
            cx,
            cy,
            near,
            far,
        })
    }

    /// The world-space frustum seen through `rect` (see [`Projection::frustum`]). Pixels count
    /// from the viewport's top-left corner, x to the right, y down. A rectangle reaching past
    /// the viewport's edges is kept as drawn, but one lying entirely outside it (nothing drawn
    /// there is on screen: a typo, or y measured upwards) is refused, naming the coordinate.
    pub fn frustum(&self, rect: &ScreenRect) -> Result<Frustum, BrowseError> {
        let projection = self.projection()?;
        let frustum = projection.frustum(rect)?;
        let (w, h) = (self.viewport.width, self.viewport.height);
        let (x0, x1) = if rect.x0 <= rect.x1 {
            (("rect.x0", rect.x0), ("rect.x1", rect.x1))
        } else {
            (("rect.x1", rect.x1), ("rect.x0", rect.x0))
        };
        let (y0, y1) = if rect.y0 <= rect.y1 {
            (("rect.y0", rect.y0), ("rect.y1", rect.y1))
        } else {
            (("rect.y1", rect.y1), ("rect.y0", rect.y0))
        };
        let outside = if x1.1 <= 0.0 {
            Some(x1)
        } else if x0.1 >= f64::from(w) {
            Some(x0)
        } else if y1.1 <= 0.0 {
            Some(y1)
        } else if y0.1 >= f64::from(h) {
            Some(y0)
        } else {
            None
        };
        match outside {
            Some((field, value)) => Err(BrowseError::RectOutsideViewport {
                field,
                value,
                width: w,
                height: h,
            }),
            None => Ok(frustum),
        }
    }
}

impl Projection {
    pub fn position(&self) -> Vec3 {
        self.position
    }

    /// The unit viewing direction (camera −z in world space).
    pub fn forward(&self) -> Vec3 {
        quat_rotate(self.rotation, [0.0, 0.0, -1.0])
    }

    /// The world-space direction through pixel `(u, v)`, scaled to depth 1 along the viewing
    /// axis (not unit length).
    pub fn ray(&self, pixel: [f64; 2]) -> Vec3 {
        let local = [
            (pixel[0] - self.cx) / self.fx,
            -(pixel[1] - self.cy) / self.fy,
            -1.0,
        ];
        quat_rotate(self.rotation, local)
    }

    /// The world point seen at `pixel` at `depth` metres along the viewing axis.
    pub fn unproject(&self, pixel: [f64; 2], depth: f64) -> Vec3 {
        add(self.position, scale(self.ray(pixel), depth))
    }

    /// [`project`](Self::project) as a matrix, for projecting many points: a point `p` is at
    /// `local = rows · p + t` in camera space (x right, y up, looking along −z), and
    /// [`ProjectionMatrix::project`] finishes the division. Same numbers as `project` up to
    /// rounding.
    pub fn matrix(&self) -> ProjectionMatrix {
        let inv = quat_conj(self.rotation);
        let rows = [
            quat_rotate(self.rotation, [1.0, 0.0, 0.0]),
            quat_rotate(self.rotation, [0.0, 1.0, 0.0]),
            quat_rotate(self.rotation, [0.0, 0.0, 1.0]),
        ];
        let t = quat_rotate(inv, scale(self.position, -1.0));
        ProjectionMatrix {
            rows,
            t,
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
        }
    }

    /// The pixel a world point projects to and its depth along the viewing axis; `None` for
    /// points at or behind the centre of projection.
    pub fn project(&self, point: Vec3) -> Option<([f64; 2], f64)> {
        let local = quat_rotate(quat_conj(self.rotation), sub(point, self.position));
        let depth = -local[2];
        (depth > 0.0).then(|| {
            (
                [
                    self.cx + self.fx * local[0] / depth,
                    self.cy - self.fy * local[1] / depth,
                ],
                depth,
            )
        })
    }

    /// The frustum of world points that project into `rect` at a depth in [near, far].
    pub fn frustum(&self, rect: &ScreenRect) -> Result<Frustum, BrowseError> {
        let x0 = finite("rect.x0", rect.x0)?;
        let y0 = finite("rect.y0", rect.y0)?;
        let x1 = finite("rect.x1", rect.x1)?;
        let y1 = finite("rect.y1", rect.y1)?;
        let (left, right) = (x0.min(x1), x0.max(x1));
        let (top, bottom) = (y0.min(y1), y0.max(y1));
        if !(right > left && bottom > top) {
            return Err(BrowseError::EmptyRect {
                width: right - left,
                height: bottom - top,
            });
        }
        let top_left = self.ray([left, top]);
        let top_right = self.ray([right, top]);
        let bottom_left = self.ray([left, bottom]);
        let bottom_right = self.ray([right, bottom]);
        let centre = self.ray([0.5 * (left + right), 0.5 * (top + bottom)]);
        // A side plane holds the centre of projection and two corner rays; its normal is turned
        // away from the centre ray so that "outside" is positive.
        let side = |d1: Vec3, d2: Vec3| -> Result<Plane, BrowseError> {
            let mut n =
                normalize(cross(d1, d2)).ok_or(BrowseError::ZeroVector { field: "rect" })?;
            if dot(n, centre) > 0.0 {
                n = scale(n, -1.0);
            }
            Ok(Plane {
                normal: n,
                offset: dot(n, self.position),
            })
        };
        let f = self.forward();
        let along = dot(f, self.position);
        Ok(Frustum::with_hull([
            side(top_left, bottom_left)?,
            side(top_right, bottom_right)?,
            side(bottom_left, bottom_right)?,
            side(top_left, top_right)?,
            // Inside: f·(x − p) ≥ near, i.e. −f·x − (−f·p − near) ≤ 0.
            Plane {
                normal: scale(f, -1.0),
                offset: -along - self.near,
            },
            // Inside: f·(x − p) ≤ far.
            Plane {
                normal: f,
                offset: along + self.far,
            },
        ]))
    }
}

/// Every plane of a [`Frustum`] (bit k = plane k), for the plane masks of box tests and
/// [`Frustum::clip_segment_masked`].
pub const ALL_PLANES: u8 = 0b11_1111;

/// An oriented plane `normal·x = offset` with a unit normal pointing *out* of the region it
/// bounds: `distance(x) ≤ 0` is inside.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Plane {
    pub normal: Vec3,
    pub offset: f64,
}

impl Plane {
    /// Signed distance of `x` from the plane, positive outside.
    #[inline]
    pub fn distance(&self, x: Vec3) -> f64 {
        dot(self.normal, x) - self.offset
    }
}

/// A convex region bounded by six planes: left, right, bottom, top, near, far (in that order for
/// frusta built by [`Camera::frustum`]; any six planes are accepted by [`Frustum::from_planes`],
/// e.g. a 3D box drawn by a script).
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
#[serde(try_from = "RawFrustum")]
pub struct Frustum {
    planes: [Plane; 6],
    /// The region's vertices when it is provably bounded (see [`Frustum::hull`]); recomputed
    /// from the planes on every construction, never sent.
    #[serde(skip)]
    hull: Option<Hull>,
}

/// Two frusta are equal when their planes are (the vertex set is derived from them, and an
/// inflated frustum does not carry one).
impl PartialEq for Frustum {
    fn eq(&self, other: &Self) -> bool {
        self.planes == other.planes
    }
}

/// The vertices of a bounded six-plane region (a convex polyhedron with six faces has at most
/// eight vertices).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Hull {
    points: [Vec3; 8],
    len: u8,
}

/// Finds the vertices of the region, or `None` when that cannot be done safely: the region may
/// be unbounded, or there seem to be more than eight vertices (numerical trouble).
/// A returned set always spans a hull that *contains* the region (feasibility is tested with a
/// generous tolerance, so a borderline point is kept rather than lost; merged near-duplicates
/// are at most `tol` apart, which the separating-axis users absorb with their margin), which
/// is what makes a separating-axis test against it never reject a box that overlaps the region.
fn compute_hull(planes: &[Plane; 6]) -> Option<Hull> {
    // Bounded ⟺ no direction d ≠ 0 with n_i·d ≤ 0 for every plane. Such a recession cone, if
    // any, has an extreme ray on two of its facets: along ±(n_i × n_j).
    let mut any_cross = false;
    for i in 0..6 {
        for j in i + 1..6 {
            let c = cross(planes[i].normal, planes[j].normal);
            let Some(d) = normalize(c) else { continue };
            any_cross = true;
            for s in [1.0, -1.0] {
                if planes.iter().all(|p| s * dot(p.normal, d) <= 1e-9) {
                    return None;
                }
            }
        }
    }
    if !any_cross {
        return None;
    }
    let scale_m = planes.iter().fold(1.0f64, |m, p| m.max(p.offset.abs()));
    let tol = 1e-7 * scale_m;
    let mut hull = Hull {
        points: [[0.0; 3]; 8],
        len: 0,
    };
    for i in 0..6 {
        for j in i + 1..6 {
            for k in j + 1..6 {
                let (a, b, c) = (planes[i], planes[j], planes[k]);
                let bc = cross(b.normal, c.normal);
                let det = dot(a.normal, bc);
                if det.abs() < 1e-12 {
                    // Normals in one plane (up to rounding): the three planes share a direction
                    // and meet in a line or nowhere, never in an isolated vertex. (Left, right
                    // and near of a camera frustum are such a triple: all contain "up".)
                    continue;
                }
                if det.abs() < 1e-8 {
                    // Too ill-conditioned to tell a far vertex from rounding: offer no vertex
                    // set rather than one that might miss part of the region.
                    return None;
                }
                let x = scale(
                    add(
                        add(
                            scale(bc, a.offset),
                            scale(cross(c.normal, a.normal), b.offset),
                        ),
                        scale(cross(a.normal, b.normal), c.offset),
                    ),
                    1.0 / det,
                );
                // An ill-conditioned vertex is known only to about ε·|x|/|det|: allow for it,
                // so that a true vertex is kept (a slightly outside point only grows the hull).
                let slack = tol + 1e-12 * norm(x) / det.abs();
                let known = hull.points[..usize::from(hull.len)]
                    .iter()
                    .any(|v| norm(sub(*v, x)) <= tol);
                if !known && planes.iter().all(|p| p.distance(x) <= slack) {
                    if usize::from(hull.len) == hull.points.len() {
                        return None;
                    }
                    hull.points[usize::from(hull.len)] = x;
                    hull.len += 1;
                }
            }
        }
    }
    (hull.len >= 4).then_some(hull)
}

#[derive(Deserialize)]
struct RawFrustum {
    planes: [Plane; 6],
}

impl TryFrom<RawFrustum> for Frustum {
    type Error = BrowseError;
    fn try_from(raw: RawFrustum) -> Result<Self, BrowseError> {
        Frustum::from_planes(raw.planes)
    }
}

impl Frustum {
    /// A frustum from six outward planes; normals are normalised (offsets scaled with them).
    pub fn from_planes(planes: [Plane; 6]) -> Result<Self, BrowseError> {
        let mut out = planes;
        for p in &mut out {
            for v in p.normal {
                finite("plane.normal", v)?;
            }
            finite("plane.offset", p.offset)?;
            let len = dot(p.normal, p.normal).sqrt();
            let n = normalize(p.normal).ok_or(BrowseError::ZeroVector {
                field: "plane.normal",
            })?;
            *p = Plane {
                normal: n,
                offset: p.offset / len,
            };
        }
        Ok(Self::with_hull(out))
    }

    /// A frustum from planes already unit-length and finite.
    fn with_hull(planes: [Plane; 6]) -> Self {
        Self {
            planes,
            hull: compute_hull(&planes),
        }
    }

    /// The vertices of the region when it is provably bounded (camera frusta and boxes are), for
    /// separating-axis tests; `None` otherwise (then only the plane test applies).
    pub fn hull(&self) -> Option<&[Vec3]> {
        self.hull.as_ref().map(|h| &h.points[..usize::from(h.len)])
    }

    pub fn planes(&self) -> &[Plane; 6] {
        &self.planes
    }

    /// An axis-aligned world-space box `min..max` as six planes (for scripts that think in
    /// world coordinates rather than screen rectangles).
    pub fn aabb(min: Vec3, max: Vec3) -> Result<Self, BrowseError> {
        for i in 0..3 {
            finite("box.min", min[i])?;
            finite("box.max", max[i])?;
            if min[i] > max[i] {
                return Err(BrowseError::OutOfRange {
                    field: "box.max",
                    value: max[i],
                    expected: "max ≥ min on every axis",
                });
            }
        }
        // Per axis: the −x side (normal −e, offset −min), then the +x side.
        Frustum::from_planes(std::array::from_fn(|j| {
            let (i, sign) = (j / 2, if j % 2 == 0 { -1.0 } else { 1.0 });
            let mut normal = [0.0; 3];
            normal[i] = sign;
            Plane {
                normal,
                offset: if j % 2 == 0 { -min[i] } else { max[i] },
            }
        }))
    }

    /// The frustum with every plane moved outward by `r` metres. The result contains every point
    /// within `r` of the original (each half-space grows by `r`), which is what makes an
    /// inflated test never miss a path that deviates from the tested one by at most `r`.
    /// A NaN radius means "unknown error": the planes move to infinity and everything is inside,
    /// so a never-miss test stays never-miss. Negative radii are treated as 0. The result has no
    /// vertex set ([`hull`](Self::hull) is `None`): cheap, for clipping segments; use
    /// [`inflated_bounded`](Self::inflated_bounded) where boxes are tested against the region.
    pub fn inflated(&self, r: f64) -> Frustum {
        let r = if r.is_nan() {
            f64::INFINITY
        } else {
            r.max(0.0)
        };
        let mut planes = self.planes;
        for p in &mut planes {
            p.offset += r;
        }
        Frustum { planes, hull: None }
    }

    /// [`inflated`](Self::inflated) with the vertex set of the inflated region (when the
    /// original has one and `r` is finite), so that box tests against it can use the
    /// separating-axis test. The vertices are those of the region the inflated *planes* bound,
    /// which near a sharp corner reaches further than "within `r` of the frustum": box tests
    /// and segment clipping then decide about the very same region. Costs a few hundred
    /// floating-point operations (the store's path hierarchy builds one per query).
    pub fn inflated_bounded(&self, r: f64) -> Frustum {
        let mut out = self.inflated(r);
        if self.hull.is_some() && out.planes.iter().all(|p| p.offset.is_finite()) {
            out.hull = compute_hull(&out.planes);
        }
        out
    }

    /// Whether `x` is inside or on the boundary.
    pub fn contains(&self, x: Vec3) -> bool {
        self.planes.iter().all(|p| p.distance(x) <= 0.0)
    }

    /// Clips the segment `a + s·(b − a)`, `s ∈ [s0, s1]`, against all six planes and returns the
    /// parameter interval inside the frustum, if any. This is the exact leaf test of the path
    /// index: each plane either keeps the interval, rejects it or cuts it at its crossing.
    pub fn clip_segment(&self, a: Vec3, b: Vec3, s0: f64, s1: f64) -> Option<(f64, f64)> {
        self.clip_segment_masked(a, b, s0, s1, ALL_PLANES)
    }

    /// [`clip_segment`](Self::clip_segment) against the planes in `mask` only (bit k = plane
    /// k), for a segment known to be inside the others.
    pub fn clip_segment_masked(
        &self,
        a: Vec3,
        b: Vec3,
        s0: f64,
        s1: f64,
        mask: u8,
    ) -> Option<(f64, f64)> {
        let (mut lo, mut hi) = (s0, s1);
        for (k, p) in self.planes.iter().enumerate() {
            if mask & (1 << k) == 0 {
                continue;
            }
            let da = p.distance(a);
            let db = p.distance(b);
            match (da > 0.0, db > 0.0) {
                (true, true) => return None,
                (false, false) => {}
                // Entering: outside at a, inside at b.
                (true, false) => lo = lo.max(da / (da - db)),
                // Leaving.
                (false, true) => hi = hi.min(da / (da - db)),
            }
            if lo > hi {
                return None;
            }
        }
        Some((lo, hi))
    }

    /// The smallest `s ≥ 0` at which the ray `origin + s·dir` is inside, if any (§4.4.2 picks a
    /// drawn constraint by a ray–frustum test to remove it).
    pub fn ray_hit(&self, origin: Vec3, dir: Vec3) -> Option<f64> {
        let (mut lo, mut hi) = (0.0f64, f64::INFINITY);
        for p in &self.planes {
            let d0 = p.distance(origin);
            let slope = dot(p.normal, dir);
            if slope == 0.0 || !slope.is_finite() {
                if d0 > 0.0 {
                    return None;
                }
                continue;
            }
            let s = -d0 / slope;
            if slope > 0.0 {
                hi = hi.min(s);
            } else {
                lo = lo.max(s);
            }
            if lo > hi {
                return None;
            }
        }
        Some(lo)
    }

    /// The eight corners, as intersections of (left|right, bottom|top, near|far) planes, for
    /// drawing the constraint; `None` if some three planes do not meet in a point.
    pub fn corners(&self) -> Option<[Vec3; 8]> {
        let mut out = [[0.0; 3]; 8];
        for (k, corner) in out.iter_mut().enumerate() {
            let p1 = self.planes[k & 1];
            let p2 = self.planes[2 + ((k >> 1) & 1)];
            let p3 = self.planes[4 + ((k >> 2) & 1)];
            let det = dot(p1.normal, cross(p2.normal, p3.normal));
            if det.abs() < 1e-12 {
                return None;
            }
            let x = add(
                add(
                    scale(cross(p2.normal, p3.normal), p1.offset),
                    scale(cross(p3.normal, p1.normal), p2.offset),
                ),
                scale(cross(p1.normal, p2.normal), p3.offset),
            );
            *corner = scale(x, 1.0 / det);
        }
        Some(out)
    }
}

/// The regions of one frustum inflated by the radii a query meets ([`Frustum::inflated`]: the
/// path trees test boxes and clip segments against planes only), computed once per distinct
/// radius. Stores round path radii up to a grid, so a query over thousands of paths meets only
/// a handful of radii. Holds at most
/// [`RegionCache::CAPACITY`] regions (then recomputes the oldest slot's radius in turn), so any
/// mix of radii costs bounded memory.
#[derive(Debug, Clone)]
pub struct RegionCache<'a> {
    base: &'a Frustum,
    regions: Vec<(u64, Frustum)>,
    next: usize,
}

impl<'a> RegionCache<'a> {
    pub const CAPACITY: usize = 32;

    pub fn new(base: &'a Frustum) -> Self {
        Self {
            base,
            regions: Vec::new(),
            next: 0,
        }
    }

    /// The frustum this cache inflates.
    pub fn base(&self) -> &'a Frustum {
        self.base
    }

    /// The region within `r` of the base frustum's planes. A NaN radius is
    /// "unknown error" (everything inside), negative radii count as 0 (as in
    /// [`Frustum::inflated`]).
    pub fn region(&mut self, r: f64) -> &Frustum {
        let r = if r.is_nan() {
            f64::INFINITY
        } else {
            r.max(0.0)
        };
        let key = r.to_bits();
        if let Some(i) = self.regions.iter().position(|(k, _)| *k == key) {
            return &self.regions[i].1;
        }
        let region = self.base.inflated(r);
        if self.regions.len() < Self::CAPACITY {
            self.regions.push((key, region));
            let last = self.regions.len() - 1;
            &self.regions[last].1
        } else {
            let i = self.next;
            self.next = (self.next + 1) % Self::CAPACITY;
            self.regions[i] = (key, region);
            &self.regions[i].1
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::browse::geom::norm;
    use proptest::prelude::*;

    #[test]
    fn hull_only_for_bounded_regions() {
        let b = Frustum::aabb([-1.0, 0.0, 2.0], [1.0, 0.5, 3.0]).expect("valid box");
        let hull = b.hull().expect("a box is bounded");
        assert_eq!(hull.len(), 8);
        for v in hull {
            assert!(b.inflated(1e-9).contains(*v), "{v:?}");
        }
        let cam = camera(
            [0.0, 1.0, 8.0],
            [0.0, 0.0, 0.0, 1.0],
            Intrinsics::VerticalFov { fov_y_rad: 0.9 },
        );
        let f = cam
            .frustum(&ScreenRect {
                x0: 300.0,
                y0: 200.0,
                x1: 310.0,
                y1: 212.0,
            })
            .expect("valid");
        assert_eq!(f.hull().map(<[Vec3]>::len), Some(8));
        assert_eq!(f.inflated(0.05).hull(), None);
        let g = f.inflated_bounded(0.05);
        assert_eq!(g.hull().map(<[Vec3]>::len), Some(8));
        for v in g.hull().into_iter().flatten() {
            assert!(g.inflated(1e-9).contains(*v), "{v:?}");
            assert!(!f.contains(*v), "{v:?} is a vertex of the grown region");
        }
        assert_eq!(f.inflated_bounded(f64::NAN).hull(), None);
        // Flip the far plane: the region beyond it is unbounded.
        let mut planes = *f.planes();
        planes[5].normal = scale(planes[5].normal, -1.0);
        planes[5].offset = -planes[5].offset;
        assert!(
            Frustum::from_planes(planes)
                .expect("valid")
                .hull()
                .is_none()
        );
        // Six planes all facing +x: a half-space.
        let half = Plane {
            normal: [1.0, 0.0, 0.0],
            offset: 1.0,
        };
        assert!(
            Frustum::from_planes([half; 6])
                .expect("valid")
                .hull()
                .is_none()
        );
        // Never sent: JSON has the planes only, and the hull comes back on the way in.
        let text = serde_json::to_string(&f).expect("serialises");
        assert!(!text.contains("hull"), "{text}");
        let back: Frustum = serde_json::from_str(&text).expect("parses");
        assert_eq!(back.hull().map(<[Vec3]>::len), Some(8));
    }

    #[test]
    fn aabb_contains_exactly_the_box() {
        let b = Frustum::aabb([-1.0, 0.0, 2.0], [1.0, 0.5, 3.0]).expect("valid box");
        assert!(b.contains([0.0, 0.25, 2.5]));
        assert!(b.contains([1.0, 0.5, 3.0]));
        assert!(!b.contains([1.01, 0.25, 2.5]));
        assert!(!b.contains([0.0, -0.01, 2.5]));
        assert!(!b.contains([0.0, 0.25, 3.01]));
        assert!(b.inflated(0.02).contains([1.01, 0.25, 2.5]));
        assert!(matches!(
            Frustum::aabb([0.0, 0.0, 0.0], [1.0, -1.0, 1.0]),
            Err(BrowseError::OutOfRange {
                field: "box.max",
                ..
            })
        ));
        assert!(Frustum::aabb([f64::NAN, 0.0, 0.0], [1.0, 1.0, 1.0]).is_err());
    }

    fn axis_angle(axis: Vec3, angle: f64) -> Quat {
        let (s, c) = (angle / 2.0).sin_cos();
        let a = normalize(axis).unwrap_or([1.0, 0.0, 0.0]);
        [a[0] * s, a[1] * s, a[2] * s, c]
    }

    fn camera(position: Vec3, rotation: Quat, intrinsics: Intrinsics) -> Camera {
        Camera {
            position,
            rotation,
            intrinsics,
            viewport: Viewport {
                width: 800,
                height: 600,
            },
            near: 0.1,
            far: 50.0,
        }
    }

    #[test]
    fn identity_camera_sees_down_minus_z() {
        let cam = camera(
            [0.0; 3],
            [0.0, 0.0, 0.0, 1.0],
            Intrinsics::VerticalFov { fov_y_rad: 1.0 },
        );
        let proj = cam.projection().expect("valid camera");
        let rect = ScreenRect {
            x0: 0.0,
            y0: 0.0,
            x1: 800.0,
            y1: 600.0,
        };
        let f = proj.frustum(&rect).expect("non-empty rect");
        assert!(f.contains([0.0, 0.0, -5.0]));
        assert!(!f.contains([0.0, 0.0, 5.0]), "behind the camera");
        assert!(!f.contains([0.0, 0.0, -0.05]), "before near");
        assert!(!f.contains([0.0, 0.0, -60.0]), "beyond far");
        // Top of the screen is +y: a point above the axis projects to a small pixel y.
        let (px, _) = proj.project([0.0, 1.0, -5.0]).expect("in front");
        assert!(px[1] < 300.0);
        let (px, _) = proj.project([1.0, 0.0, -5.0]).expect("in front");
        assert!(px[0] > 400.0);
    }

    #[test]
    fn bad_cameras_and_rects_are_refused_with_the_field() {
        let ok = camera(
            [0.0; 3],
            [0.0, 0.0, 0.0, 1.0],
            Intrinsics::VerticalFov { fov_y_rad: 1.0 },
        );
        let rect = ScreenRect {
            x0: 1.0,
            y0: 1.0,
            x1: 2.0,
            y1: 2.0,
        };
        let mut c = ok;
        c.rotation = [0.0; 4];
        assert_eq!(
            c.frustum(&rect),
            Err(BrowseError::ZeroVector { field: "rotation" })
        );
        let mut c = ok;
        c.intrinsics = Intrinsics::VerticalFov { fov_y_rad: 4.0 };
        assert!(matches!(
            c.frustum(&rect),
            Err(BrowseError::OutOfRange {
                field: "intrinsics.fov_y_rad",
                ..
            })
        ));
        let mut c = ok;
        c.far = 0.05;
        assert!(matches!(
            c.frustum(&rect),
            Err(BrowseError::OutOfRange { field: "far", .. })
        ));
        let mut c = ok;
        c.position[1] = f64::NAN;
        assert!(matches!(
            c.frustum(&rect),
            Err(BrowseError::NonFinite {
                field: "position.y",
                ..
            })
        ));
        let flat = ScreenRect { y1: 1.0, ..rect };
        assert!(matches!(
            ok.frustum(&flat),
            Err(BrowseError::EmptyRect { .. })
        ));
    }

    /// Issue 24: a rectangle entirely off the 800 × 600 viewport is refused, naming the
    /// coordinate that puts it there; one reaching past an edge is kept as drawn.
    #[test]
    fn rect_entirely_outside_the_viewport_is_refused() {
        let cam = camera(
            [0.0; 3],
            [0.0, 0.0, 0.0, 1.0],
            Intrinsics::VerticalFov { fov_y_rad: 1.0 },
        );
        let r = |x0, y0, x1, y1| ScreenRect { x0, y0, x1, y1 };
        for (rect, field) in [
            (r(-50.0, 10.0, -10.0, 20.0), "rect.x1"),
            (r(-10.0, 10.0, -50.0, 20.0), "rect.x0"), // corners in any order
            (r(800.0, 10.0, 900.0, 20.0), "rect.x0"),
            (r(10.0, -30.0, 20.0, 0.0), "rect.y1"),
            (r(10.0, 600.0, 20.0, 700.0), "rect.y0"),
            // y measured upwards from the bottom by mistake: 700 px up on a 600 px screen.
            (r(100.0, 650.0, 200.0, 700.0), "rect.y0"),
        ] {
            match cam.frustum(&rect) {
                Err(e @ BrowseError::RectOutsideViewport { .. }) => {
                    let text = e.to_string();
                    assert!(text.starts_with(field), "{rect:?}: {text}");
                    assert!(text.contains("800 × 600"), "{text}");
                }
                other => panic!("{rect:?}: {other:?}"),
            }
        }
        for inside in [
            r(-50.0, -50.0, 10.0, 10.0),
            r(790.0, 590.0, 900.0, 700.0),
            r(0.0, 0.0, 800.0, 600.0),
        ] {
            assert!(cam.frustum(&inside).is_ok(), "{inside:?}");
        }
    }

    #[test]
    fn serde_roundtrip_and_validation_on_deserialise() {
        let cam = camera(
            [1.0, 2.0, 3.0],
            axis_angle([0.0, 1.0, 0.0], 0.3),
            Intrinsics::Pinhole {
                fx: 500.0,
                fy: 510.0,
                cx: 400.0,
                cy: 300.0,
            },
        );
        let text = toml::to_string(&cam).expect("serialises");
        let back: Camera = toml::from_str(&text).expect("parses");
        assert_eq!(back, cam);
        let f = cam
            .frustum(&ScreenRect {
                x0: 10.0,
                y0: 20.0,
                x1: 30.0,
                y1: 40.0,
            })
            .expect("valid");
        #[derive(Serialize, Deserialize)]
        struct Wrap {
            f: Frustum,
        }
        let text = toml::to_string(&Wrap { f }).expect("serialises");
        let back: Wrap = toml::from_str(&text).expect("parses");
        for (a, b) in back.f.planes().iter().zip(f.planes()) {
            assert!(norm(sub(a.normal, b.normal)) < 1e-15);
            assert!((a.offset - b.offset).abs() < 1e-12);
        }
        let zero = text.replacen("normal = [", "normal = [0.0, 0.0, 0.0] #", 1);
        assert!(toml::from_str::<Wrap>(&zero).is_err(), "{zero}");
    }

    #[test]
    fn inflated_moves_every_plane_out_by_r() {
        let cam = camera(
            [0.0; 3],
            [0.0, 0.0, 0.0, 1.0],
            Intrinsics::VerticalFov { fov_y_rad: 1.0 },
        );
        let rect = ScreenRect {
            x0: 390.0,
            y0: 290.0,
            x1: 410.0,
            y1: 310.0,
        };
        let f = cam.frustum(&rect).expect("valid");
        let g = f.inflated(0.5);
        for (p, q) in f.planes().iter().zip(g.planes()) {
            assert_eq!(p.normal, q.normal);
            assert!((q.offset - p.offset - 0.5).abs() < 1e-12);
        }
        // A point 0.4 m beside the thin frustum is inside the inflated one only.
        let x = [0.4 + 0.1, 0.0, -5.0];
        assert!(!f.contains(x));
        assert!(g.contains(x));
        // NaN radius: unknown error, nothing may be excluded.
        assert!(f.inflated(f64::NAN).contains([1e6, -1e6, 1e6]));
        assert_eq!(f.inflated(-1.0), f);
    }

    #[test]
    fn corners_are_the_unprojected_rect_corners() {
        let cam = camera(
            [1.0, -2.0, 0.5],
            axis_angle([0.3, 1.0, -0.2], 0.8),
            Intrinsics::VerticalFov { fov_y_rad: 0.9 },
        );
        let proj = cam.projection().expect("valid");
        let rect = ScreenRect {
            x0: 100.0,
            y0: 50.0,
            x1: 300.0,
            y1: 400.0,
        };
        let corners = proj
            .frustum(&rect)
            .expect("valid")
            .corners()
            .expect("bounded");
        // k: bit 0 left/right, bit 1 bottom/top, bit 2 near/far.
        for (k, c) in corners.iter().enumerate() {
            let u = if k & 1 == 0 { 100.0 } else { 300.0 };
            let v = if k & 2 == 0 { 400.0 } else { 50.0 };
            let d = if k & 4 == 0 { 0.1 } else { 50.0 };
            let want = proj.unproject([u, v], d);
            assert!(norm(sub(*c, want)) < 1e-9, "corner {k}: {c:?} vs {want:?}");
        }
    }

    #[test]
    fn clip_segment_and_ray() {
        let cam = camera(
            [0.0; 3],
            [0.0, 0.0, 0.0, 1.0],
            Intrinsics::VerticalFov { fov_y_rad: 1.0 },
        );
        let f = cam
            .frustum(&ScreenRect {
                x0: 0.0,
                y0: 0.0,
                x1: 800.0,
                y1: 600.0,
            })
            .expect("valid");
        // Along the axis from z = +10 to z = −100: inside from depth 0.1 to depth 50.
        let (a, b) = ([0.0, 0.0, 10.0], [0.0, 0.0, -100.0]);
        let (lo, hi) = f.clip_segment(a, b, 0.0, 1.0).expect("crosses");
        assert!((lo - 10.1 / 110.0).abs() < 1e-12);
        assert!((hi - 60.0 / 110.0).abs() < 1e-12);
        assert!(f.clip_segment(a, b, 0.0, 0.05).is_none());
        let s = f.ray_hit([0.0, 0.0, 10.0], [0.0, 0.0, -1.0]).expect("hits");
        assert!((s - 10.1).abs() < 1e-12);
        assert!(f.ray_hit([0.0, 0.0, 10.0], [0.0, 0.0, 1.0]).is_none());
    }

    fn arb_camera() -> impl Strategy<Value = Camera> {
        (
            prop::array::uniform3(-20.0f64..20.0),
            prop::array::uniform3(-1.0f64..1.0),
            -3.1f64..3.1,
            0.2f64..2.5,
            (1u32..2000, 1u32..2000),
            (0.01f64..1.0, 2.0f64..200.0),
        )
            .prop_map(|(position, axis, angle, fov, (w, h), (near, far))| Camera {
                position,
                rotation: axis_angle(add(axis, [0.0, 1e-3, 0.0]), angle),
                intrinsics: Intrinsics::VerticalFov { fov_y_rad: fov },
                viewport: Viewport {
                    width: w,
                    height: h,
                },
                near,
                far,
            })
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

        /// The matrix form projects every point where the quaternion form does.
        #[test]
        fn the_matrix_projects_like_the_camera(
            cam in arb_camera(),
            p in proptest::array::uniform3(-50.0f64..50.0),
        ) {
            let proj = cam.projection().expect("strategy gives valid cameras");
            let m = proj.matrix();
            match (proj.project(p), m.project(p)) {
                (Some((a, da)), Some((b, db))) => {
                    prop_assert!((da - db).abs() <= 1e-9 * (1.0 + da.abs()), "{da} {db}");
                    // Pixels: relative to the focal length over depth (points near the eye
                    // project far out).
                    let tol = 1e-9 * (1.0 + proj.fx.max(proj.fy) * (1.0 + norm(p)) / da.abs());
                    prop_assert!((a[0] - b[0]).abs() <= tol && (a[1] - b[1]).abs() <= tol,
                        "{a:?} {b:?}");
                }
                (None, None) => {}
                // Only a point on the camera plane can fall either way.
                (x, y) => prop_assert!(
                    m.local(p)[2].abs() < 1e-9 * (1.0 + norm(p)),
                    "{x:?} {y:?}"
                ),
            }
        }

        /// The centre of the rectangle, unprojected at any depth between near and far, is in
        /// the frustum; pushed outside the rectangle or the depth range, it is not.
        #[test]
        fn frustum_contains_what_projects_into_the_rect(
            cam in arb_camera(),
            fx in 0.0f64..1.0, fy in 0.0f64..1.0, fw in 0.01f64..0.5, fh in 0.01f64..0.5,
            t in 0.01f64..0.99,
        ) {
            let proj = cam.projection().expect("strategy gives valid cameras");
            let (w, h) = (f64::from(cam.viewport.width), f64::from(cam.viewport.height));
            let (rw, rh) = (fw * w, fh * h);
            let x0 = fx * w;
            let y0 = fy * h;
            let rect = ScreenRect { x0, y0, x1: x0 + rw, y1: y0 + rh };
            let f = proj.frustum(&rect).expect("non-empty");
            let centre = [x0 + 0.5 * rw, y0 + 0.5 * rh];
            let depth = cam.near + t * (cam.far - cam.near);
            let p = proj.unproject(centre, depth);
            prop_assert!(f.contains(p), "centre at depth {depth} not inside");
            for depth in [cam.near * 1.001, cam.far * 0.999] {
                prop_assert!(f.contains(proj.unproject(centre, depth)));
            }
            // Round trip through project.
            let (px, d) = proj.project(p).expect("in front");
            prop_assert!((px[0] - centre[0]).abs() < 1e-6 * (1.0 + w) && (px[1] - centre[1]).abs() < 1e-6 * (1.0 + h));
            prop_assert!((d - depth).abs() < 1e-9 * (1.0 + depth));
            // Outside the rectangle by a quarter of its size, or outside [near, far].
            prop_assert!(!f.contains(proj.unproject([x0 - 0.25 * rw, centre[1]], depth)));
            prop_assert!(!f.contains(proj.unproject([x0 + 1.25 * rw, centre[1]], depth)));
            prop_assert!(!f.contains(proj.unproject([centre[0], y0 - 0.25 * rh], depth)));
            prop_assert!(!f.contains(proj.unproject([centre[0], y0 + 1.25 * rh], depth)));
            prop_assert!(!f.contains(proj.unproject(centre, cam.near * 0.9)));
            prop_assert!(!f.contains(proj.unproject(centre, cam.far * 1.1)));
        }

        /// The vertex set of an inflated frustum spans a hull that contains the region: every
        /// true vertex of the region (a point where three planes meet and which no plane
        /// excludes, found here independently by solving each triple in another way) lies
        /// within the hull along the coordinate axes and random directions — so no separating
        /// axis can cut off any of the region.
        #[test]
        fn inflated_hull_contains_the_region(
            cam in arb_camera(),
            fx in 0.0f64..1.0, fy in 0.0f64..1.0, fw in 0.0005f64..0.5, fh in 0.0005f64..0.5,
            r in prop_oneof![Just(0.0), 0.0f64..0.5, 1e-6f64..1e-3],
            dirs in prop::collection::vec(prop::array::uniform3(-1.0f64..1.0), 8),
        ) {
            let proj = cam.projection().expect("strategy gives valid cameras");
            let (w, h) = (f64::from(cam.viewport.width), f64::from(cam.viewport.height));
            let (x0, y0) = (fx * w, fy * h);
            let rect = ScreenRect { x0, y0, x1: x0 + fw * w, y1: y0 + fh * h };
            let region = proj.frustum(&rect).expect("non-empty").inflated_bounded(r);
            // Sub-pixel rectangles may be too thin for a trustworthy vertex set (then there is
            // none, and box tests use the planes only); a pixel or more must have one.
            if fw * w >= 1.0 && fh * h >= 1.0 {
                prop_assert!(region.hull().is_some(), "no vertex set for a {}×{} px rect", fw * w, fh * h);
            }
            let Some(hull) = region.hull() else { return Ok(()) };
            let planes = region.planes();
            let scale_m = hull.iter().fold(1.0f64, |m, v| m.max(norm(*v)));
            let mut axes: Vec<Vec3> = vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
            axes.extend(dirs.iter().filter_map(|d| normalize(*d)));
            for i in 0..6 {
                for j in i + 1..6 {
                    for k in j + 1..6 {
                        // Cramer's rule on the 3×3 system [n_i; n_j; n_k] x = d.
                        let (a, b, c) = (planes[i], planes[j], planes[k]);
                        let m = [a.normal, b.normal, c.normal];
                        let det3 = |m: [Vec3; 3]| dot(m[0], cross(m[1], m[2]));
                        let det = det3(m);
                        if det.abs() < 1e-10 {
                            continue;
                        }
                        let rhs = [a.offset, b.offset, c.offset];
                        let mut x = [0.0; 3];
                        for (col, xc) in x.iter_mut().enumerate() {
                            let mut mc = m;
                            for row in 0..3 {
                                mc[row][col] = rhs[row];
                            }
                            *xc = det3(mc) / det;
                        }
                        let inside = planes.iter().all(|p| p.distance(x) <= 1e-9 * scale_m);
                        if !inside {
                            continue;
                        }
                        for d in &axes {
                            let top = hull.iter().map(|v| dot(*d, *v)).fold(f64::NEG_INFINITY, f64::max);
                            let low = hull.iter().map(|v| dot(*d, *v)).fold(f64::INFINITY, f64::min);
                            let tol = 1e-6 * (1.0 + scale_m);
                            prop_assert!(dot(*d, x) <= top + tol && dot(*d, x) >= low - tol,
                                "vertex {x:?} of planes {i},{j},{k} outside the hull along {d:?}");
                        }
                    }
                }
            }
        }
    }
}
