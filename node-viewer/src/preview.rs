//! A scene as it starts, before any world exists: its statics and its bodies where an instance
//! of the scene places them, drawn by the viewer's own 3D view ([`crate::draw`]) and painted by
//! [`SoftPainter`](crate::softpaint::SoftPainter) — `mwb scene preview`, so an author sees pegs,
//! bins and bodies before sampling. Pure: no window, no display, no I/O.

use mwb_core::scene::SceneTemplate;

use crate::ViewerError;
use crate::camera::OrbitCamera;
use crate::screenshot::screenshot;
use crate::state::{Msg, ViewerState};
use crate::ui::ViewerApp;

/// The viewer state of `template` with no worlds: its statics, and its bodies where the
/// instance of `seed` starts them.
pub fn scene_state(template: &SceneTemplate, seed: u64) -> ViewerState {
    let scene = template.instantiate(seed);
    let names = scene.bodies.iter().map(|b| b.name.clone()).collect();
    ViewerState::new(template.name(), names, scene.statics).with_initial(scene.bodies)
}

/// Renders the 3D view alone (no panels) of `template`'s instance `seed` at `size` pixels,
/// seen from `camera` (the browsing camera of `mwb query` and the viewer's camera files), or
/// framed on the whole scene when `None`. A camera that does not project is an error.
pub fn render(
    template: &SceneTemplate,
    seed: u64,
    size: [u32; 2],
    camera: Option<&mwb_core::browse::Camera>,
) -> Result<image::RgbaImage, ViewerError> {
    let mut state = scene_state(template, seed);
    let placed = camera.is_some();
    if let Some(c) = camera {
        let focus = state.bounds().map_or([0.0; 3], |(c, _)| c);
        state.update(Msg::SetCamera(OrbitCamera::from_browse(c, focus)?))?;
    }
    let mut app = ViewerApp::new(state).view_only().with_camera_placed(placed);
    // Pass 1 lays out and frames the scene; the rest draw it from there.
    Ok(screenshot(&mut app, size, 1.0, 3))
}

#[cfg(test)]
mod tests {
    use super::*;

    const SCENE: &str = r#"
name = "preview"
[[material]]
name = "m"
friction = 0.5
restitution = 0.2
density = 1000.0
[[static]]
name = "ground"
shape = "plane"
normal = [0, 1, 0]
material = "m"
[[body]]
name = "crate"
shape = "box"
size = [1.0, 1.0, 1.0]
material = "m"
position = [0.0, 2.0, 0.0]
"#;

    fn template(text: &str) -> SceneTemplate {
        SceneTemplate::parse(text, "preview.toml").expect("scene parses")
    }

    /// Pixels that differ between two images of one size.
    fn differing(a: &image::RgbaImage, b: &image::RgbaImage) -> usize {
        a.pixels().zip(b.pixels()).filter(|(p, q)| p != q).count()
    }

    #[test]
    fn bodies_are_drawn_where_the_scene_starts_them() {
        let with = render(&template(SCENE), 0, [320, 240], None).expect("renders");
        assert_eq!(with.dimensions(), (320, 240));
        // The same scene without its body: only the body's pixels change, and there are many
        // (a 1 m crate framed in a 320×240 view).
        let empty = SCENE
            .split("[[body]]")
            .next()
            .expect("text before the body");
        let without = {
            let t = template(empty);
            let mut state = scene_state(&t, 0);
            // Same camera as the framed preview with the body: frame on the body's scene.
            let framed = scene_state(&template(SCENE), 0);
            let mut app = ViewerApp::new(framed).view_only();
            screenshot(&mut app, [320, 240], 1.0, 3);
            state.update(Msg::SetCamera(app.state.camera)).ok();
            let mut app = ViewerApp::new(state).view_only().with_camera_placed(true);
            screenshot(&mut app, [320, 240], 1.0, 3)
        };
        let changed = differing(&with, &without);
        assert!(changed > 2_000, "{changed} pixels show the body");
        // The crate is framed: the centre of the image is on it.
        let centre = with.get_pixel(160, 120);
        assert_ne!(
            centre,
            without.get_pixel(160, 120),
            "centre pixel {centre:?}"
        );
    }

    fn camera(json: &str) -> mwb_core::browse::Camera {
        serde_json::from_str(json).expect("camera JSON")
    }

    #[test]
    fn a_camera_file_places_the_view_and_a_bad_one_is_refused() {
        let t = template(SCENE);
        // 6 m in front of the crate, looking along -z at it; and the same camera turned away.
        let at = camera(
            r#"{"position":[0,2,6],"rotation":[0,0,0,1],
            "intrinsics":{"model":"vertical_fov","fov_y_rad":0.9},
            "viewport":{"width":320,"height":240}}"#,
        );
        let away = camera(
            r#"{"position":[0,2,6],"rotation":[0,1,0,0],
            "intrinsics":{"model":"vertical_fov","fov_y_rad":0.9},
            "viewport":{"width":320,"height":240}}"#,
        );
        let seen = render(&t, 0, [320, 240], Some(&at)).expect("renders");
        let behind = render(&t, 0, [320, 240], Some(&away)).expect("renders");
        assert!(differing(&seen, &behind) > 1_000);
        let bad = camera(
            r#"{"position":[0,2,6],"rotation":[0,0,0,1],
            "intrinsics":{"model":"vertical_fov","fov_y_rad":4.0},
            "viewport":{"width":320,"height":240}}"#,
        );
        let e = render(&t, 0, [320, 240], Some(&bad)).expect_err("a 229° field of view");
        assert!(e.to_string().contains("fov_y_rad"), "{e}");
    }

    #[test]
    fn the_state_holds_the_instance_of_the_seed() {
        let text = SCENE.replace(
            "position = [0.0, 2.0, 0.0]",
            "position = [{ uniform = [-1.0, 1.0] }, 2.0, 0.0]",
        );
        let t = template(&text);
        let a = scene_state(&t, 1);
        let b = scene_state(&t, 2);
        assert_eq!(a.initial().len(), 1);
        assert_eq!(a.initial()[0], t.instantiate(1).bodies[0]);
        assert_ne!(a.initial()[0].position, b.initial()[0].position);
        assert!(a.worlds().is_empty());
        // Framing all with no worlds frames the bodies and bounded statics.
        let (centre, r) = a.framing(None).expect("a scene with a body frames");
        let p = a.initial()[0].position;
        let d = crate::math::len(crate::math::sub(p, centre));
        assert!(
            d + 0.5 <= r + 1e-9,
            "body at {p:?} outside {centre:?} r {r}"
        );
    }
}
