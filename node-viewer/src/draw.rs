//! The 3D view as egui shapes: every point goes through `mwb_core::browse::Projection::project`
//! (the projection constraints are built with), clipped at the near plane, and is painted as
//! egui lines and triangle meshes (flat-shaded, painter-sorted). No GPU state: the view looks
//! the same on any egui backend and in the software rasteriser.

use std::sync::Arc;

use egui::{Color32, Mesh, Pos2, Rect, Shape, Stroke, pos2, vec2};
use mwb_core::browse::{Polarity, Projection, ProjectionMatrix, Viewport};
use mwb_core::scene::Shape as SceneShape;

use crate::camera::{OrbitCamera, rotate};
use crate::math::{V3, add, cross, dot, lerp, normalize, scale, sub};
use crate::state::ViewerState;

/// Colours of the view (premultiplied where translucent).
pub mod palette {
    use egui::Color32;
    pub const SKY_TOP: Color32 = Color32::from_rgb(38, 42, 50);
    pub const SKY_BOTTOM: Color32 = Color32::from_rgb(18, 19, 23);
    pub const GRID: Color32 = Color32::from_rgb(58, 62, 70);
    pub const GRID_MAJOR: Color32 = Color32::from_rgb(80, 85, 95);
    pub const SURVIVOR: [u8; 3] = [90, 180, 255];
    pub const REJECTED: [u8; 3] = [150, 150, 150];
    pub const SELECTED: Color32 = Color32::from_rgb(255, 176, 64);
    pub const POSITIVE: [u8; 3] = [80, 220, 120];
    pub const NEGATIVE: [u8; 3] = [240, 80, 80];
    pub const STATIC: [f32; 3] = [0.55, 0.56, 0.6];
    pub const BODIES: [[f32; 3]; 6] = [
        [0.86, 0.55, 0.32],
        [0.45, 0.7, 0.9],
        [0.6, 0.82, 0.45],
        [0.88, 0.76, 0.36],
        [0.74, 0.52, 0.86],
        [0.9, 0.45, 0.5],
    ];
}

/// How a view rectangle maps to the pixels a browse camera sees.
#[derive(Debug, Clone, Copy)]
pub struct View {
    pub proj: Projection,
    pub rect: Rect,
    pub ppp: f32,
    pub viewport: Viewport,
    eye: V3,
    /// `proj` as a matrix: every path vertex of every world goes through it each frame (a
    /// third of the cost of projecting by the camera's quaternion, `mwb bench viewer`).
    m: ProjectionMatrix,
    near: f64,
}

/// The pixel viewport of a view rectangle at `ppp` physical pixels per point.
pub fn viewport_of(rect: Rect, ppp: f32) -> Viewport {
    Viewport {
        width: (rect.width() * ppp).round().max(1.0) as u32,
        height: (rect.height() * ppp).round().max(1.0) as u32,
    }
}

impl View {
    pub fn new(camera: &OrbitCamera, rect: Rect, ppp: f32) -> Option<Self> {
        let viewport = viewport_of(rect, ppp);
        let proj = camera.browse_camera(viewport).projection().ok()?;
        Some(Self {
            proj,
            rect,
            ppp,
            viewport,
            eye: proj.position(),
            m: proj.matrix(),
            near: camera.near,
        })
    }

    /// Screen point (egui points) → browse pixel coordinates of this view.
    pub fn pixel(&self, p: Pos2) -> [f64; 2] {
        [
            f64::from((p.x - self.rect.min.x) * self.ppp),
            f64::from((p.y - self.rect.min.y) * self.ppp),
        ]
    }

    fn screen(&self, px: [f64; 2]) -> Pos2 {
        pos2(
            self.rect.min.x + px[0] as f32 / self.ppp,
            self.rect.min.y + px[1] as f32 / self.ppp,
        )
    }

    /// Depth along the viewing axis.
    fn depth(&self, p: V3) -> f64 {
        -self.m.local(p)[2]
    }

    /// The screen point of `p`, if it is in front of the near plane.
    pub fn project(&self, p: V3) -> Option<Pos2> {
        let local = self.m.local(p);
        if -local[2] < self.near {
            return None;
        }
        self.m.pixel(local).map(|(px, _)| self.screen(px))
    }

    /// A segment clipped to the near plane, on screen.
    pub fn segment(&self, a: V3, b: V3) -> Option<[Pos2; 2]> {
        let (da, db) = (self.depth(a) - self.near, self.depth(b) - self.near);
        if da < 0.0 && db < 0.0 {
            return None;
        }
        let cut = |from: V3, to: V3, df: f64, dt: f64| lerp(from, to, df / (df - dt));
        let (a, b) = if da < 0.0 {
            (cut(a, b, da, db), b)
        } else if db < 0.0 {
            (a, cut(a, b, da, db))
        } else {
            (a, b)
        };
        Some([self.project_unchecked(a)?, self.project_unchecked(b)?])
    }

    fn project_unchecked(&self, p: V3) -> Option<Pos2> {
        self.m.project(p).map(|(px, _)| self.screen(px))
    }

    /// Calls `f` with every segment of a polyline on screen, each vertex projected once;
    /// segments behind the near plane are clipped, and those wholly to one side of the view
    /// rectangle skipped.
    pub fn for_each_segment(&self, points: &[V3], mut f: impl FnMut(Pos2, Pos2)) {
        let r = self.rect;
        let mut prev: Option<(V3, f64, Option<Pos2>)> = None;
        for &p in points {
            let local = self.m.local(p);
            let d = -local[2] - self.near;
            let sp = if d >= 0.0 {
                self.m.pixel(local).map(|(px, _)| self.screen(px))
            } else {
                None
            };
            if let Some((q, dq, sq)) = prev {
                let seg = match (sq, sp) {
                    (Some(a), Some(b)) if dq >= 0.0 && d >= 0.0 => Some([a, b]),
                    _ => self.segment(q, p),
                };
                if let Some([a, b]) = seg {
                    let outside = (a.x < r.min.x && b.x < r.min.x)
                        || (a.x > r.max.x && b.x > r.max.x)
                        || (a.y < r.min.y && b.y < r.min.y)
                        || (a.y > r.max.y && b.y > r.max.y);
                    if !outside {
                        f(a, b);
                    }
                }
            }
            prev = Some((p, d, sp));
        }
    }

    /// A polyline on screen, split where it leaves the near side.
    pub fn polyline(&self, points: &[V3]) -> Vec<Vec<Pos2>> {
        let mut runs = Vec::new();
        let mut run: Vec<Pos2> = Vec::new();
        for w in points.windows(2) {
            match self.segment(w[0], w[1]) {
                Some([a, b]) => {
                    if run.is_empty() {
                        run.push(a);
                    }
                    run.push(b);
                    if self.depth(w[1]) < self.near {
                        runs.push(std::mem::take(&mut run));
                    }
                }
                None => {
                    if run.len() > 1 {
                        runs.push(std::mem::take(&mut run));
                    }
                    run.clear();
                }
            }
        }
        if run.len() > 1 {
            runs.push(run);
        }
        runs
    }
}

/// Many thin lines as one mesh: a quad per segment, no joins and no feathering. Thousands of
/// faint paths drawn as egui paths (each joined, feathered and tessellated on its own) cost
/// several times more per frame; at a point or two wide and low alpha the difference does not
/// show. The few paths that stand out (hovered, selected) are still drawn as egui paths.
#[derive(Default)]
pub struct LineBatch {
    mesh: Mesh,
}

impl LineBatch {
    /// A batch filling `mesh`'s buffers (emptied first), with room for `segments` segments.
    pub fn reusing(mut mesh: Mesh, segments: usize) -> Self {
        // (`Mesh::clear` would free the vertex buffer.)
        mesh.indices.clear();
        mesh.vertices.clear();
        mesh.vertices.reserve(4 * segments);
        mesh.indices.reserve(6 * segments);
        Self { mesh }
    }

    pub fn segment(&mut self, a: Pos2, b: Pos2, width: f32, color: Color32) {
        let d = b - a;
        // (`Vec2::length` is `hypot`, a libm call: several times slower than this.)
        let len = (d.x * d.x + d.y * d.y).sqrt();
        if len < 1e-3 {
            return;
        }
        let n = vec2(-d.y, d.x) * (0.5 * width / len);
        let i = self.mesh.vertices.len() as u32;
        self.mesh.colored_vertex(a + n, color);
        self.mesh.colored_vertex(a - n, color);
        self.mesh.colored_vertex(b - n, color);
        self.mesh.colored_vertex(b + n, color);
        self.mesh.add_triangle(i, i + 1, i + 2);
        self.mesh.add_triangle(i, i + 2, i + 3);
    }

    /// Segments drawn so far.
    pub fn len(&self) -> usize {
        self.mesh.vertices.len() / 4
    }

    pub fn is_empty(&self) -> bool {
        self.mesh.vertices.is_empty()
    }
}

fn rgba(c: [u8; 3], a: u8) -> Color32 {
    Color32::from_rgba_unmultiplied(c[0], c[1], c[2], a)
}

/// A shape's triangles in its local frame; `closed` shapes may drop back faces.
fn local_triangles(shape: &SceneShape) -> (Vec<[V3; 3]>, bool) {
    match shape {
        SceneShape::Box { half_extents: h } => {
            let c = |i: usize| -> V3 {
                [
                    if i & 1 == 0 { -h[0] } else { h[0] },
                    if i & 2 == 0 { -h[1] } else { h[1] },
                    if i & 4 == 0 { -h[2] } else { h[2] },
                ]
            };
            let faces = [
                [0, 2, 6, 4], // −x
                [1, 5, 7, 3], // +x
                [0, 4, 5, 1], // −y
                [2, 3, 7, 6], // +y
                [0, 1, 3, 2], // −z
                [4, 6, 7, 5], // +z
            ];
            let mut out = Vec::with_capacity(12);
            for f in faces {
                out.push([c(f[0]), c(f[2]), c(f[1])]);
                out.push([c(f[0]), c(f[3]), c(f[2])]);
            }
            (out, true)
        }
        SceneShape::Sphere { radius } => (round_body(*radius, 0.0), true),
        SceneShape::Capsule {
            half_height,
            radius,
        } => (round_body(*radius, *half_height), true),
        SceneShape::Cylinder {
            half_height,
            radius,
        } => {
            let n = 20;
            let ring = |i: usize, y: f64| -> V3 {
                let a = std::f64::consts::TAU * i as f64 / n as f64;
                [radius * a.cos(), y, -radius * a.sin()]
            };
            let mut out = Vec::new();
            for i in 0..n {
                let (a0, a1) = (ring(i, -half_height), ring(i + 1, -half_height));
                let (b0, b1) = (ring(i, *half_height), ring(i + 1, *half_height));
                out.push([a0, a1, b1]);
                out.push([a0, b1, b0]);
                out.push([[0.0, *half_height, 0.0], b0, b1]);
                out.push([[0.0, -half_height, 0.0], a1, a0]);
            }
            (out, true)
        }
        SceneShape::ConvexHull { points } => (hull_triangles(points), true),
        SceneShape::TriMesh { vertices, indices } => (
            indices
                .iter()
                .filter_map(|t| {
                    Some([
                        *vertices.get(t[0] as usize)?,
                        *vertices.get(t[1] as usize)?,
                        *vertices.get(t[2] as usize)?,
                    ])
                })
                .collect(),
            false,
        ),
        SceneShape::Plane { .. } => (Vec::new(), false),
        // Every part at its pose in the body's frame; back faces may go only if every part is
        // closed (a static compound may hold an open mesh).
        SceneShape::Compound { parts } => {
            let mut out = Vec::new();
            let mut all_closed = true;
            for part in parts {
                let (tris, closed) = local_triangles(&part.shape);
                all_closed &= closed;
                out.extend(
                    tris.into_iter()
                        .map(|t| t.map(|v| add(part.position, rotate(part.rotation, v)))),
                );
            }
            (out, all_closed)
        }
    }
}

/// A sphere (`half_height` 0) or a capsule along local y: latitude rings, the two hemispheres
/// pulled apart by ±`half_height`.
fn round_body(radius: f64, half_height: f64) -> Vec<[V3; 3]> {
    let (rings, segs) = (10usize, 18usize);
    // Ring list: upper hemisphere (pole to equator), then lower (equator to pole).
    let mut lat: Vec<(f64, f64)> = Vec::new();
    for i in 0..=rings / 2 {
        lat.push((std::f64::consts::PI * i as f64 / rings as f64, half_height));
    }
    for i in rings / 2..=rings {
        lat.push((std::f64::consts::PI * i as f64 / rings as f64, -half_height));
    }
    let point = |(theta, dy): (f64, f64), j: usize| -> V3 {
        let phi = std::f64::consts::TAU * j as f64 / segs as f64;
        [
            radius * theta.sin() * phi.cos(),
            radius * theta.cos() + dy,
            -radius * theta.sin() * phi.sin(),
        ]
    };
    let mut out = Vec::new();
    for r in 0..lat.len() - 1 {
        for j in 0..segs {
            let (a, b) = (point(lat[r], j), point(lat[r], j + 1));
            let (c, d) = (point(lat[r + 1], j), point(lat[r + 1], j + 1));
            out.push([a, c, d]);
            out.push([a, d, b]);
        }
    }
    out
}

/// Faces of the convex hull of a few points (brute force over triples; scenes give tens of
/// points). Outward-wound.
fn hull_triangles(points: &[V3]) -> Vec<[V3; 3]> {
    let n = points.len().min(48);
    let pts = &points[..n];
    let centre = scale(
        pts.iter().fold([0.0; 3], |a, &p| add(a, p)),
        1.0 / n.max(1) as f64,
    );
    let size = pts
        .iter()
        .map(|p| crate::math::len(sub(*p, centre)))
        .fold(0.0, f64::max);
    let eps = 1e-9 * size.max(1e-9);
    let mut out = Vec::new();
    for i in 0..n {
        for j in i + 1..n {
            for k in j + 1..n {
                let nrm = cross(sub(pts[j], pts[i]), sub(pts[k], pts[i]));
                if crate::math::len(nrm) < 1e-12 * size * size {
                    continue;
                }
                let side = |p: V3| dot(nrm, sub(p, pts[i]));
                let (mut pos, mut neg) = (false, false);
                for (m, &p) in pts.iter().enumerate() {
                    if m == i || m == j || m == k {
                        continue;
                    }
                    let s = side(p);
                    pos |= s > eps;
                    neg |= s < -eps;
                }
                match (pos, neg) {
                    (false, _) => out.push([pts[i], pts[j], pts[k]]),
                    (true, false) => out.push([pts[i], pts[k], pts[j]]),
                    _ => {}
                }
            }
        }
    }
    out
}

/// A world-space triangle to shade.
struct Tri {
    p: [V3; 3],
    colour: [f32; 3],
    alpha: f32,
    closed: bool,
}

/// Adds a posed shape's triangles.
fn push_shape(
    out: &mut Vec<Tri>,
    shape: &SceneShape,
    pos: V3,
    rot: [f64; 4],
    colour: [f32; 3],
    alpha: f32,
) {
    let (tris, closed) = local_triangles(shape);
    for t in tris {
        out.push(Tri {
            p: t.map(|v| add(pos, rotate(rot, v))),
            colour,
            alpha,
            closed,
        });
    }
}

/// Flat-shades and painter-sorts triangles into one mesh.
fn shaded_mesh(view: &View, tris: Vec<Tri>) -> Mesh {
    let light = normalize([0.35, 1.0, 0.55]).unwrap_or([0.0, 1.0, 0.0]);
    let mut keyed: Vec<(f64, [Pos2; 3], Color32)> = Vec::with_capacity(tris.len());
    for t in tris {
        let n = match normalize(cross(sub(t.p[1], t.p[0]), sub(t.p[2], t.p[0]))) {
            Some(n) => n,
            None => continue,
        };
        let centroid = scale(add(add(t.p[0], t.p[1]), t.p[2]), 1.0 / 3.0);
        let to_eye = sub(view.eye, centroid);
        let facing = dot(n, to_eye);
        if t.closed && facing <= 0.0 {
            continue;
        }
        let n = if facing < 0.0 { scale(n, -1.0) } else { n };
        let Some(a) = view.project(t.p[0]) else {
            continue;
        };
        let Some(b) = view.project(t.p[1]) else {
            continue;
        };
        let Some(c) = view.project(t.p[2]) else {
            continue;
        };
        let lambert = dot(n, light).max(0.0) as f32;
        let rim = 0.12 * (1.0 - (facing / crate::math::len(to_eye).max(1e-9)).abs() as f32);
        let k = 0.32 + 0.6 * lambert + rim;
        let col = t.colour.map(|c| ((c * k).clamp(0.0, 1.0) * 255.0) as u8);
        let a8 = (t.alpha.clamp(0.0, 1.0) * 255.0) as u8;
        keyed.push((view.depth(centroid), [a, b, c], rgba(col, a8)));
    }
    keyed.sort_by(|x, y| y.0.total_cmp(&x.0));
    let mut mesh = Mesh::default();
    for (_, p, col) in keyed {
        let base = mesh.vertices.len() as u32;
        for q in p {
            mesh.colored_vertex(q, col);
        }
        mesh.add_triangle(base, base + 1, base + 2);
    }
    mesh
}

/// The height of the ground: the first static plane facing up, else 0.
fn ground_height(state: &ViewerState) -> f64 {
    state
        .statics()
        .iter()
        .find_map(|s| match &s.shape {
            SceneShape::Plane { normal } => {
                let n = rotate(s.rotation, *normal);
                (n[1] > 0.9).then_some(s.position[1])
            }
            _ => None,
        })
        .unwrap_or(0.0)
}

/// Opacity of a static pane ([`is_pane`]).
const PANE_ALPHA: f32 = 0.3;

/// Whether a static is a pane to look through: a box far thinner (< 1/10) than it is wide,
/// standing upright (its thin axis within 60° of horizontal) — pachinko's front glass, which
/// drawn opaque hides the peg board the balls fall through. (The view has no depth buffer:
/// triangles are painter-sorted, so pegs behind a big opaque pane would show through it in
/// places anyway.) Floors, ramps and walls of any thickness stay opaque.
pub fn is_pane(shape: &SceneShape, rotation: [f64; 4]) -> bool {
    let SceneShape::Box { half_extents: h } = shape else {
        return false;
    };
    let mut order = [0, 1, 2];
    order.sort_by(|&a, &b| h[a].total_cmp(&h[b]));
    let (thin, middle) = (h[order[0]], h[order[1]]);
    let mut axis = [0.0; 3];
    axis[order[0]] = 1.0;
    let up = rotate(rotation, axis)[1].abs();
    thin < 0.1 * middle && up < 0.5
}

/// Inputs the view needs besides the state.
#[derive(Debug, Clone, Copy, Default)]
pub struct Overlay {
    /// The rectangle being dragged, screen points, and whether it is negative.
    pub drag: Option<(Pos2, Pos2, bool)>,
    /// The world under the cursor.
    pub hovered: Option<u32>,
}

/// The faint path meshes of the last frame (rejected worlds, survivors) and a digest of what
/// they were drawn from. While nothing they show changes — a still camera while the user hovers,
/// plays a world back or works in the panels — a frame reuses them whole; otherwise their
/// buffers are refilled in place, so a frame of 10 000 worlds does not allocate (and fault in)
/// tens of megabytes of vertices again.
#[derive(Debug, Default)]
pub struct PathMeshes {
    key: Option<u64>,
    meshes: [Arc<Mesh>; 2],
}

impl PathMeshes {
    /// A digest of everything the path meshes depend on: the projection, the view rectangle,
    /// the chosen objects, and every world's index, survival and chosen paths (their length
    /// and last vertex: a world's paths do not change once it arrived).
    fn key_of(&self, state: &ViewerState, view: &View, chosen: &[u32]) -> u64 {
        let mut h = Mix::default();
        let m = &view.m;
        for v in m.rows.iter().flatten().chain(&m.t) {
            h.add(v.to_bits());
        }
        for v in [m.fx, m.fy, m.cx, m.cy, view.near] {
            h.add(v.to_bits());
        }
        for v in [
            view.rect.min.x,
            view.rect.min.y,
            view.rect.max.x,
            view.rect.max.y,
        ] {
            h.add(u64::from(v.to_bits()));
        }
        h.add(u64::from(view.ppp.to_bits()));
        h.add(chosen.len() as u64);
        for &o in chosen {
            h.add(u64::from(o));
        }
        h.add(state.worlds().len() as u64);
        for w in state.worlds() {
            h.add(u64::from(w.index) << 1 | u64::from(state.survives(w.index)));
            for &o in chosen {
                if let Some(p) = w.paths.get(o as usize) {
                    let points = p.tree.path().points();
                    h.add(points.len() as u64);
                    if let Some(last) = points.last() {
                        for c in last {
                            h.add(c.to_bits());
                        }
                    }
                }
            }
        }
        h.0
    }
}

/// A fast 64-bit mix (multiply, rotate) for [`PathMeshes`]' digest: not for adversaries.
#[derive(Default)]
struct Mix(u64);

impl Mix {
    fn add(&mut self, v: u64) {
        self.0 = (self.0 ^ v)
            .wrapping_mul(0x9E37_79B9_7F4A_7C15)
            .rotate_left(29);
    }
}

/// Every shape of the 3D view of `state` in `view`; the faint paths come from (and are kept
/// in) `paths`.
pub fn scene_shapes(
    state: &ViewerState,
    view: &View,
    overlay: Overlay,
    paths: &mut PathMeshes,
) -> Vec<Shape> {
    let mut shapes = Vec::new();
    let r = view.rect;
    // Background: a vertical gradient.
    let mut sky = Mesh::default();
    sky.colored_vertex(r.left_top(), palette::SKY_TOP);
    sky.colored_vertex(r.right_top(), palette::SKY_TOP);
    sky.colored_vertex(r.right_bottom(), palette::SKY_BOTTOM);
    sky.colored_vertex(r.left_bottom(), palette::SKY_BOTTOM);
    sky.add_triangle(0, 1, 2);
    sky.add_triangle(0, 2, 3);
    shapes.push(Shape::mesh(sky));

    // Ground grid, 0.5 m, around the scene.
    let y = ground_height(state);
    let (centre, radius) = state.bounds().unwrap_or(([0.0; 3], 3.0));
    let half = ((radius * 1.6).ceil()).clamp(3.0, 200.0);
    let (cx, cz) = (
        (centre[0] * 2.0).round() / 2.0,
        (centre[2] * 2.0).round() / 2.0,
    );
    let steps = (2.0 * half / 0.5).round() as i64;
    for i in 0..=steps {
        let o = -half + 0.5 * i as f64;
        let major = (o + cx).rem_euclid(1.0).abs() < 1e-9;
        let stroke = Stroke::new(
            if major { 1.0 } else { 0.6 },
            if major {
                palette::GRID_MAJOR
            } else {
                palette::GRID
            },
        );
        for (a, b) in [
            ([cx + o, y, cz - half], [cx + o, y, cz + half]),
            ([cx - half, y, cz + o], [cx + half, y, cz + o]),
        ] {
            if let Some(s) = view.segment(a, b) {
                shapes.push(Shape::line_segment(s, stroke));
            }
        }
    }
    // Axes at the origin: x red, y green, z blue, 1 m.
    for (d, c) in [
        ([1.0, 0.0, 0.0], Color32::from_rgb(220, 70, 70)),
        ([0.0, 1.0, 0.0], Color32::from_rgb(90, 200, 90)),
        ([0.0, 0.0, 1.0], Color32::from_rgb(80, 130, 240)),
    ] {
        if let Some(s) = view.segment([0.0, y, 0.0], add([0.0, y, 0.0], d)) {
            shapes.push(Shape::line_segment(s, Stroke::new(2.0, c)));
        }
    }

    // Static geometry; panes see-through.
    let mut tris = Vec::new();
    for s in state.statics() {
        let alpha = if is_pane(&s.shape, s.rotation) {
            PANE_ALPHA
        } else {
            1.0
        };
        push_shape(
            &mut tris,
            &s.shape,
            s.position,
            s.rotation,
            palette::STATIC,
            alpha,
        );
    }
    if !tris.is_empty() {
        shapes.push(Shape::mesh(shaded_mesh(view, std::mem::take(&mut tris))));
    }

    // Paths: rejected dim first, survivors over them, the selected / hovered world on top.
    let chosen = state.chosen_objects();
    let key = paths.key_of(state, view, &chosen);
    if paths.key != Some(key) {
        paths.key = Some(key);
        let n = state.worlds().len().max(1) as f32;
        // Fainter the more worlds overlap.
        let survivor_alpha = (255.0 * (6.0 / n.sqrt()).clamp(0.12, 0.8)) as u8;
        let rejected_alpha = (survivor_alpha / 4).max(10);
        for (pass, slot) in [false, true].into_iter().zip(paths.meshes.iter_mut()) {
            let (width, colour) = if pass {
                (1.2, rgba(palette::SURVIVOR, survivor_alpha))
            } else {
                (1.0, rgba(palette::REJECTED, rejected_alpha))
            };
            let drawn = state
                .worlds()
                .iter()
                .filter(|w| state.survives(w.index) == pass);
            let segments = drawn
                .clone()
                .flat_map(|w| chosen.iter().filter_map(|&o| w.paths.get(o as usize)))
                .map(|p| p.tree.path().len().saturating_sub(1))
                .sum();
            // Last frame's buffers, refilled (egui let go of them after that frame).
            let mut batch = LineBatch::reusing(std::mem::take(Arc::make_mut(slot)), segments);
            for w in drawn {
                for &o in &chosen {
                    if let Some(p) = w.paths.get(o as usize) {
                        view.for_each_segment(p.tree.path().points(), |a, b| {
                            batch.segment(a, b, width, colour);
                        });
                    }
                }
            }
            *Arc::make_mut(slot) = batch.mesh;
        }
    }
    for mesh in &paths.meshes {
        if !mesh.is_empty() {
            shapes.push(Shape::Mesh(Arc::clone(mesh)));
        }
    }
    for (w, stroke) in [
        (
            overlay.hovered,
            Stroke::new(2.0, Color32::from_rgb(235, 235, 235)),
        ),
        (state.selected(), Stroke::new(2.5, palette::SELECTED)),
    ] {
        if let Some(world) = w.and_then(|w| state.world(w)) {
            for &o in &chosen {
                if let Some(p) = world.paths.get(o as usize) {
                    for run in view.polyline(p.tree.path().points()) {
                        shapes.push(Shape::line(run, stroke));
                    }
                }
            }
        }
    }

    // Bodies of the shown world at the playback time (once its motion is loaded); while no
    // world is shown, where the scene starts them (a scene preview, or before worlds arrive).
    let alpha = |b: usize| if state.is_chosen(b as u32) { 1.0 } else { 0.55 };
    let colour = |b: usize| palette::BODIES[b % palette::BODIES.len()];
    if let Some(motion) = state.shown_world().and_then(|w| w.motion.as_ref()) {
        let t = state.playback().time;
        for (b, body) in motion.scene.bodies.iter().enumerate() {
            if let Some((p, q)) = motion.pose_at(b, t) {
                push_shape(&mut tris, &body.shape, p, q, colour(b), alpha(b));
            }
        }
        shapes.push(Shape::mesh(shaded_mesh(view, tris)));
    } else if state.shown_world().is_none() && !state.initial().is_empty() {
        for (b, body) in state.initial().iter().enumerate() {
            push_shape(
                &mut tris,
                &body.shape,
                body.position,
                body.rotation,
                colour(b),
                alpha(b),
            );
        }
        shapes.push(Shape::mesh(shaded_mesh(view, tris)));
    }

    // Constraints: their frustum's four side edges from the eye they were drawn with to the
    // depth of the scene, and the cross-section there.
    for c in state.constraint_list() {
        let Some(k) = c.frustum.corners() else {
            continue;
        };
        let col = match c.polarity {
            Polarity::Positive => palette::POSITIVE,
            Polarity::Negative => palette::NEGATIVE,
        };
        let stroke = Stroke::new(1.5, rgba(col, 200));
        let mut section = [[0.0; 3]; 4];
        for (e, (ni, fi)) in [(0, 4), (1, 5), (3, 7), (2, 6)].into_iter().enumerate() {
            let (a, b) = (k[ni], k[fi]);
            let d = sub(b, a);
            let s = (dot(sub(centre, a), d) / dot(d, d).max(1e-300)).clamp(0.0, 1.0);
            // Reach a little past the scene's centre.
            let s = (s + 1.2 * radius / dot(d, d).sqrt().max(1e-9)).min(1.0);
            section[e] = lerp(a, b, s);
            if let Some(seg) = view.segment(a, section[e]) {
                shapes.push(Shape::line_segment(seg, Stroke::new(1.0, rgba(col, 110))));
            }
        }
        for e in 0..4 {
            if let Some(seg) = view.segment(section[e], section[(e + 1) % 4]) {
                shapes.push(Shape::line_segment(seg, stroke));
            }
        }
    }

    // The rectangle being drawn.
    if let Some((a, b, negative)) = overlay.drag {
        let col = if negative {
            palette::NEGATIVE
        } else {
            palette::POSITIVE
        };
        let rect = Rect::from_two_pos(a, b);
        shapes.push(Shape::rect_filled(rect, 0.0, rgba(col, 40)));
        shapes.push(Shape::rect_stroke(
            rect,
            0.0,
            Stroke::new(1.5, rgba(col, 230)),
            egui::StrokeKind::Inside,
        ));
    }
    shapes
}

/// The world whose drawn path passes closest to `p` (within `max_px` screen points), among the
/// chosen objects' paths; survivors win ties over rejected worlds.
pub fn pick_world(state: &ViewerState, view: &View, p: Pos2, max_px: f32) -> Option<u32> {
    let mut best: Option<(f32, u32)> = None;
    for w in state.worlds() {
        let bias = if state.survives(w.index) { 0.0 } else { 2.0 };
        for o in state.chosen_objects() {
            let Some(path) = w.paths.get(o as usize) else {
                continue;
            };
            view.for_each_segment(path.tree.path().points(), |a, b| {
                let d = dist_to_segment(p, a, b) + bias;
                if d <= max_px && best.is_none_or(|(bd, _)| d < bd) {
                    best = Some((d, w.index));
                }
            });
        }
    }
    best.map(|(_, w)| w)
}

fn dist_to_segment(p: Pos2, a: Pos2, b: Pos2) -> f32 {
    let ab = b - a;
    let t = ((p - a).dot(ab) / ab.length_sq().max(1e-12)).clamp(0.0, 1.0);
    (a + ab * t - p).length()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shapes_have_closed_outward_meshes() {
        for shape in [
            SceneShape::Box {
                half_extents: [0.5, 0.2, 0.3],
            },
            SceneShape::Sphere { radius: 0.4 },
            SceneShape::Capsule {
                half_height: 0.3,
                radius: 0.2,
            },
            SceneShape::Cylinder {
                half_height: 0.3,
                radius: 0.2,
            },
            SceneShape::ConvexHull {
                points: vec![
                    [0.0, 0.0, 0.0],
                    [1.0, 0.0, 0.0],
                    [0.0, 1.0, 0.0],
                    [0.0, 0.0, 1.0],
                ],
            },
        ] {
            let (tris, closed) = local_triangles(&shape);
            assert!(closed && !tris.is_empty(), "{shape:?}");
            // Outward: the signed volume (divergence theorem) is positive.
            let vol: f64 = tris
                .iter()
                .map(|t| dot(t[0], cross(t[1], t[2])) / 6.0)
                .sum();
            assert!(vol > 0.0, "{shape:?}: volume {vol}");
        }
        let (tris, _) = local_triangles(&SceneShape::Box {
            half_extents: [1.0, 1.0, 1.0],
        });
        let vol: f64 = tris
            .iter()
            .map(|t| dot(t[0], cross(t[1], t[2])) / 6.0)
            .sum();
        assert!((vol - 8.0).abs() < 1e-12);
    }

    #[test]
    fn a_compound_draws_every_part_where_it_sits() {
        let unit_box = SceneShape::Box {
            half_extents: [1.0, 1.0, 1.0],
        };
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let part = |position, rotation| mwb_core::scene::Part {
            shape: unit_box.clone(),
            position,
            rotation,
            material: 0,
        };
        let compound = SceneShape::Compound {
            parts: vec![
                part([0.0; 3], [0.0, 0.0, 0.0, 1.0]),
                part([5.0, 0.0, 0.0], [0.0, h, 0.0, h]),
            ],
        };
        let (tris, closed) = local_triangles(&compound);
        assert!(closed);
        assert_eq!(tris.len(), 24, "both boxes");
        // The second box, turned, sits 5 m along x: x in [4, 6], still outward.
        let far: Vec<_> = tris[12..].iter().flatten().map(|v| v[0]).collect();
        assert!(far.iter().all(|x| (3.999..=6.001).contains(x)), "{far:?}");
        let vol: f64 = tris
            .iter()
            .map(|t| dot(t[0], cross(t[1], t[2])) / 6.0)
            .sum();
        assert!((vol - 16.0).abs() < 1e-9, "{vol}");
    }

    #[test]
    fn upright_thin_boxes_are_panes_and_floors_ramps_and_walls_are_not() {
        let plate = |h: [f64; 3]| SceneShape::Box { half_extents: h };
        let level = [0.0, 0.0, 0.0, 1.0];
        // Pachinko's glass (thin along z) is a pane; its side walls and a cup's walls are not.
        assert!(is_pane(&plate([0.65, 1.0, 0.01]), level));
        assert!(!is_pane(&plate([0.025, 1.0, 0.1]), level));
        assert!(!is_pane(&plate([0.02, 0.1, 0.24]), level));
        // A ramp (thin along y, tilted 15°) and a floor plate are not; the floor plate turned
        // upright (90° about x) is.
        let s = (7.5f64).to_radians().sin();
        let c = (7.5f64).to_radians().cos();
        assert!(!is_pane(&plate([0.6, 0.02, 0.15]), [0.0, 0.0, -s, c]));
        assert!(!is_pane(&plate([2.0, 0.01, 2.0]), level));
        let h = std::f64::consts::FRAC_1_SQRT_2;
        assert!(is_pane(&plate([2.0, 0.01, 2.0]), [h, 0.0, 0.0, h]));
        assert!(!is_pane(&SceneShape::Sphere { radius: 1.0 }, level));
    }
}
