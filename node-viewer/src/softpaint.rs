//! A software rasteriser for egui's output: the real UI's tessellated meshes and font atlas,
//! filled on the CPU into an RGBA image. Used for `mwb viewer --screenshot` and for image
//! snapshot tests, so neither needs a GPU, a display or a graphics driver, and a given build
//! gives the same pixels on every machine.
//!
//! It follows what egui's own painters do: vertex colours and textures are premultiplied sRGB
//! (gamma space), a fragment is vertex colour × texel, blended "over" in gamma space; clip
//! rectangles become scissor rectangles rounded to pixels. Triangles are sampled at pixel
//! centres with a top-left-style tie rule, so meshes that share an edge do not blend twice
//! along it; egui's tessellator already feathers edges for anti-aliasing.

use std::collections::HashMap;

use egui::epaint::{ClippedPrimitive, Primitive, Vertex};
use egui::{Color32, TextureFilter, TextureId, TexturesDelta};

struct Texture {
    size: [usize; 2],
    pixels: Vec<Color32>,
    linear: bool,
}

/// Keeps egui's textures (font atlas, images) and paints frames.
#[derive(Default)]
pub struct SoftPainter {
    textures: HashMap<TextureId, Texture>,
    pending_free: Vec<TextureId>,
}

impl SoftPainter {
    pub fn new() -> Self {
        Self::default()
    }

    /// Applies texture uploads, as a GPU painter does before painting a frame. Frees take
    /// effect at the next call (egui frees after the frame that still uses them is painted).
    pub fn handle_delta(&mut self, delta: &TexturesDelta) {
        for id in self.pending_free.drain(..) {
            self.textures.remove(&id);
        }
        for (id, deltas) in &delta.set {
            for d in deltas {
                let egui::ImageData::Color(img) = &d.image;
                let linear = d.options.magnification == TextureFilter::Linear;
                match d.pos {
                    None => {
                        self.textures.insert(
                            *id,
                            Texture {
                                size: img.size,
                                pixels: img.pixels.clone(),
                                linear,
                            },
                        );
                    }
                    Some([x0, y0]) => {
                        if let Some(t) = self.textures.get_mut(id) {
                            for y in 0..img.size[1] {
                                for x in 0..img.size[0] {
                                    let (tx, ty) = (x0 + x, y0 + y);
                                    if tx < t.size[0] && ty < t.size[1] {
                                        t.pixels[ty * t.size[0] + tx] =
                                            img.pixels[y * img.size[0] + x];
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
        self.pending_free.extend(delta.free.iter().copied());
    }

    /// Tessellates `shapes` with `ctx` and paints them on a `size` image cleared to `clear`.
    pub fn paint_shapes(
        &self,
        ctx: &egui::Context,
        shapes: Vec<egui::epaint::ClippedShape>,
        pixels_per_point: f32,
        size: [u32; 2],
        clear: Color32,
    ) -> image::RgbaImage {
        let prims = ctx.tessellate(shapes, pixels_per_point);
        self.paint(&prims, pixels_per_point, size, clear)
    }

    /// Paints tessellated primitives (paint callbacks are skipped: the viewer has none).
    pub fn paint(
        &self,
        prims: &[ClippedPrimitive],
        ppp: f32,
        size: [u32; 2],
        clear: Color32,
    ) -> image::RgbaImage {
        let (w, h) = (size[0] as usize, size[1] as usize);
        let c = clear.to_array().map(f32::from);
        let mut fb = vec![c; w * h];
        for p in prims {
            let Primitive::Mesh(mesh) = &p.primitive else {
                continue;
            };
            let clip = [
                (p.clip_rect.min.x * ppp).round().clamp(0.0, w as f32) as usize,
                (p.clip_rect.min.y * ppp).round().clamp(0.0, h as f32) as usize,
                (p.clip_rect.max.x * ppp).round().clamp(0.0, w as f32) as usize,
                (p.clip_rect.max.y * ppp).round().clamp(0.0, h as f32) as usize,
            ];
            if clip[0] >= clip[2] || clip[1] >= clip[3] {
                continue;
            }
            let tex = self.textures.get(&mesh.texture_id);
            for t in mesh.indices.chunks_exact(3) {
                let (Some(a), Some(b), Some(c)) = (
                    mesh.vertices.get(t[0] as usize),
                    mesh.vertices.get(t[1] as usize),
                    mesh.vertices.get(t[2] as usize),
                ) else {
                    continue;
                };
                fill_triangle(&mut fb, w, clip, ppp, [a, b, c], tex);
            }
        }
        let mut out = image::RgbaImage::new(size[0], size[1]);
        for (px, v) in out.pixels_mut().zip(&fb) {
            *px = image::Rgba(v.map(|c| c.round().clamp(0.0, 255.0) as u8));
        }
        out
    }
}

/// Whether a pixel centre exactly on edge `a → b` belongs to the triangle: for any edge
/// shared by two triangles of the same winding, exactly one of them owns it.
fn owns_edge(dx: f32, dy: f32) -> bool {
    dy > 0.0 || (dy == 0.0 && dx < 0.0)
}

fn sample(t: &Texture, uv: [f32; 2]) -> [f32; 4] {
    let (tw, th) = (t.size[0], t.size[1]);
    if tw == 0 || th == 0 {
        return [255.0; 4];
    }
    let fetch = |x: isize, y: isize| -> [f32; 4] {
        let x = x.clamp(0, tw as isize - 1) as usize;
        let y = y.clamp(0, th as isize - 1) as usize;
        t.pixels[y * tw + x].to_array().map(f32::from)
    };
    let (x, y) = (uv[0] * tw as f32, uv[1] * th as f32);
    if !t.linear {
        return fetch(x.floor() as isize, y.floor() as isize);
    }
    let (x, y) = (x - 0.5, y - 0.5);
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let (x0, y0) = (x0 as isize, y0 as isize);
    let (p00, p10, p01, p11) = (
        fetch(x0, y0),
        fetch(x0 + 1, y0),
        fetch(x0, y0 + 1),
        fetch(x0 + 1, y0 + 1),
    );
    let mut out = [0.0; 4];
    for k in 0..4 {
        let top = p00[k] + (p10[k] - p00[k]) * fx;
        let bottom = p01[k] + (p11[k] - p01[k]) * fx;
        out[k] = top + (bottom - top) * fy;
    }
    out
}

fn fill_triangle(
    fb: &mut [[f32; 4]],
    w: usize,
    clip: [usize; 4],
    ppp: f32,
    v: [&Vertex; 3],
    tex: Option<&Texture>,
) {
    let mut p = v.map(|v| [v.pos.x * ppp, v.pos.y * ppp]);
    let mut v = v;
    let edge = |a: [f32; 2], b: [f32; 2], c: [f32; 2]| {
        (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    };
    let mut area = edge(p[0], p[1], p[2]);
    if !area.is_finite() || area.abs() < 1e-12 {
        return;
    }
    if area < 0.0 {
        p.swap(1, 2);
        v.swap(1, 2);
        area = -area;
    }
    let min_x = p.iter().map(|q| q[0]).fold(f32::INFINITY, f32::min);
    let max_x = p.iter().map(|q| q[0]).fold(f32::NEG_INFINITY, f32::max);
    let min_y = p.iter().map(|q| q[1]).fold(f32::INFINITY, f32::min);
    let max_y = p.iter().map(|q| q[1]).fold(f32::NEG_INFINITY, f32::max);
    let x0 = (min_x - 0.5).floor().max(clip[0] as f32) as usize;
    let x1 = ((max_x - 0.5).ceil() + 1.0).min(clip[2] as f32).max(0.0) as usize;
    let y0 = (min_y - 0.5).floor().max(clip[1] as f32) as usize;
    let y1 = ((max_y - 0.5).ceil() + 1.0).min(clip[3] as f32).max(0.0) as usize;
    if x0 >= x1 || y0 >= y1 {
        return;
    }
    // Edge i is opposite vertex i.
    let edges = [(p[1], p[2]), (p[2], p[0]), (p[0], p[1])];
    let owns = edges.map(|(a, b)| owns_edge(b[0] - a[0], b[1] - a[1]));
    let col = v.map(|v| v.color.to_array().map(f32::from));
    let uv = v.map(|v| [v.uv.x, v.uv.y]);
    let inv = 1.0 / area;
    for y in y0..y1 {
        let py = y as f32 + 0.5;
        for x in x0..x1 {
            let q = [x as f32 + 0.5, py];
            let mut l = [0f32; 3];
            let mut inside = true;
            for i in 0..3 {
                let e = edge(edges[i].0, edges[i].1, q);
                if e < 0.0 || (e == 0.0 && !owns[i]) {
                    inside = false;
                    break;
                }
                l[i] = e * inv;
            }
            if !inside {
                continue;
            }
            let mut src = [0f32; 4];
            for k in 0..4 {
                src[k] = l[0] * col[0][k] + l[1] * col[1][k] + l[2] * col[2][k];
            }
            if let Some(t) = tex {
                let u = [
                    l[0] * uv[0][0] + l[1] * uv[1][0] + l[2] * uv[2][0],
                    l[0] * uv[0][1] + l[1] * uv[1][1] + l[2] * uv[2][1],
                ];
                let texel = sample(t, u);
                for k in 0..4 {
                    src[k] *= texel[k] / 255.0;
                }
            }
            let a = (src[3] / 255.0).clamp(0.0, 1.0);
            if a <= 0.0 && src[..3].iter().all(|&c| c <= 0.0) {
                continue;
            }
            let d = &mut fb[y * w + x];
            for k in 0..4 {
                d[k] = src[k] + d[k] * (1.0 - a);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use egui::epaint::Mesh;
    use egui::{Rect, pos2};

    fn quad(rect: Rect, colour: Color32) -> ClippedPrimitive {
        let mut mesh = Mesh::default();
        mesh.add_colored_rect(rect, colour);
        ClippedPrimitive {
            clip_rect: Rect::EVERYTHING,
            primitive: Primitive::Mesh(mesh),
        }
    }

    #[test]
    fn a_rect_fills_exactly_its_pixels_once() {
        let painter = SoftPainter::new();
        // Half-transparent white over black: blending twice along the diagonal would show.
        let half = Color32::from_white_alpha(128);
        let img = painter.paint(
            &[quad(
                Rect::from_min_max(pos2(2.0, 3.0), pos2(7.0, 9.0)),
                half,
            )],
            1.0,
            [10, 12],
            Color32::BLACK,
        );
        for y in 0..12 {
            for x in 0..10 {
                let inside = (2..7).contains(&x) && (3..9).contains(&y);
                let v = img.get_pixel(x, y).0[0];
                assert_eq!(v, if inside { 128 } else { 0 }, "pixel {x},{y}");
            }
        }
    }

    #[test]
    fn clip_rects_and_pixels_per_point_scale() {
        let painter = SoftPainter::new();
        let mut p = quad(
            Rect::from_min_max(pos2(0.0, 0.0), pos2(5.0, 5.0)),
            Color32::RED,
        );
        p.clip_rect = Rect::from_min_max(pos2(1.0, 1.0), pos2(3.0, 5.0));
        let img = painter.paint(&[p], 2.0, [10, 10], Color32::BLACK);
        assert_eq!(img.get_pixel(1, 5).0, [0, 0, 0, 255]);
        assert_eq!(img.get_pixel(2, 2).0, [255, 0, 0, 255]);
        assert_eq!(img.get_pixel(5, 9).0, [255, 0, 0, 255]);
        assert_eq!(img.get_pixel(6, 2).0, [0, 0, 0, 255]);
    }
}
