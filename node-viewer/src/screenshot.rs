//! Headless screenshots of the real UI: a few egui passes of [`ViewerApp::ui`] at a given size,
//! painted by [`SoftPainter`] (no window, no display, no GPU).

use egui::{Pos2, RawInput, Rect, ViewportId, vec2};

use crate::ViewerError;
use crate::softpaint::SoftPainter;
use crate::ui::ViewerApp;

/// Parses `WIDTHxHEIGHT` (pixels, each 64..=8192).
pub fn parse_size(text: &str) -> Result<[u32; 2], ViewerError> {
    let bad = || ViewerError::Size(text.to_owned());
    let (w, h) = text.split_once(['x', 'X']).ok_or_else(bad)?;
    let w: u32 = w.trim().parse().map_err(|_| bad())?;
    let h: u32 = h.trim().parse().map_err(|_| bad())?;
    if !(64..=8192).contains(&w) || !(64..=8192).contains(&h) {
        return Err(bad());
    }
    Ok([w, h])
}

/// Renders `app` at `size` pixels (`ppp` pixels per point) after `passes` UI passes (layout
/// settles in two; the first frames the camera when it was not placed).
pub fn screenshot(
    app: &mut ViewerApp,
    size: [u32; 2],
    ppp: f32,
    passes: usize,
) -> image::RgbaImage {
    let ctx = egui::Context::default();
    ctx.all_styles_mut(|style| {
        style.animation_time = 0.0;
    });
    let points = vec2(size[0] as f32, size[1] as f32) / ppp;
    let mut painter = SoftPainter::new();
    let mut last = None;
    for _ in 0..passes.max(2) {
        let mut input = RawInput {
            screen_rect: Some(Rect::from_min_size(Pos2::ZERO, points)),
            ..Default::default()
        };
        if let Some(v) = input.viewports.get_mut(&ViewportId::ROOT) {
            v.native_pixels_per_point = Some(ppp);
        }
        let mut out = ctx.run_ui(input, |ui| app.ui(ui));
        painter.handle_delta(&out.textures_delta);
        // Applied to the painter: an output dropped with pending deltas panics in epaint.
        out.textures_delta.clear();
        last = Some(out);
    }
    let Some(out) = last else {
        return image::RgbaImage::new(size[0], size[1]);
    };
    let clear = ctx.global_style().visuals.panel_fill;
    painter.paint_shapes(&ctx, out.shapes, out.pixels_per_point, size, clear)
}

/// What one UI frame cost, milliseconds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameTime {
    /// CPU time of the thread that built and tessellated the frame (what the frame costs,
    /// whatever else the machine runs; 0 where the thread clock is unavailable).
    pub cpu_ms: f64,
    /// Wall-clock time (longer when other processes take the core).
    pub wall_ms: f64,
}

/// The cost of whole UI frames of `app` at `size` pixels: egui's pass over
/// [`ViewerApp::ui`] (panels, the 3D view's projection into shapes) plus tessellation into
/// triangles — everything a frame costs before the GPU (or [`SoftPainter`]) draws it. The
/// camera orbits a little every frame so that nothing is reused between frames.
pub fn frame_times(app: &mut ViewerApp, size: [u32; 2], frames: usize) -> Vec<FrameTime> {
    let ctx = egui::Context::default();
    ctx.all_styles_mut(|style| {
        style.animation_time = 0.0;
    });
    let points = vec2(size[0] as f32, size[1] as f32);
    let mut times = Vec::with_capacity(frames);
    for i in 0..frames + 2 {
        let input = RawInput {
            screen_rect: Some(Rect::from_min_size(Pos2::ZERO, points)),
            ..Default::default()
        };
        let (start, cpu_start) = (std::time::Instant::now(), mwb_node::cpu_time());
        let mut out = ctx.run_ui(input, |ui| app.ui(ui));
        let primitives = ctx.tessellate(std::mem::take(&mut out.shapes), out.pixels_per_point);
        let time = FrameTime {
            cpu_ms: (mwb_node::cpu_time() - cpu_start) * 1e3,
            wall_ms: start.elapsed().as_secs_f64() * 1e3,
        };
        std::hint::black_box(primitives);
        out.textures_delta.clear();
        // The first two passes lay the UI out (and build the font atlas): not counted.
        if i >= 2 {
            times.push(time);
        }
        // Orbiting cannot fail.
        app.state
            .update(crate::Msg::Orbit {
                d_yaw: 0.01,
                d_pitch: 0.0,
            })
            .ok();
    }
    times
}

/// Encodes an image as PNG bytes.
pub fn png_bytes(img: &image::RgbaImage) -> Result<Vec<u8>, image::ImageError> {
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png)?;
    Ok(out.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_and_bad_ones_are_named() {
        assert_eq!(parse_size("1280x720"), Ok([1280, 720]));
        assert_eq!(parse_size("640X480"), Ok([640, 480]));
        for bad in ["1280", "x720", "10x10", "1280x-1", "axb", "99999x100"] {
            assert_eq!(
                parse_size(bad),
                Err(ViewerError::Size(bad.to_owned())),
                "{bad}"
            );
        }
    }
}
