use super::*;
use crate::browse::geom::{cross, normalize};
use crate::browse::{Camera, Intrinsics, Quat, ScreenRect, Viewport};
use proptest::prelude::*;

/// splitmix64: a tiny deterministic generator so that one `u64` seed describes a whole case.
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }
    fn vec3(&mut self, lo: f64, hi: f64) -> Vec3 {
        [self.range(lo, hi), self.range(lo, hi), self.range(lo, hi)]
    }
}

/// The rotation whose camera (−z forward, +y up) looks from `eye` at `target`.
fn look_at(eye: Vec3, target: Vec3) -> Quat {
    let f = normalize(sub(target, eye)).unwrap_or([0.0, 0.0, -1.0]);
    let up_hint = if f[1].abs() > 0.99 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let right = normalize(cross(f, up_hint)).unwrap_or([1.0, 0.0, 0.0]);
    let up = cross(right, f);
    let back = scale(f, -1.0);
    // Columns of the camera-to-world matrix: right, up, back. Shepperd's conversion.
    let m = [
        [right[0], up[0], back[0]],
        [right[1], up[1], back[1]],
        [right[2], up[2], back[2]],
    ];
    let trace = m[0][0] + m[1][1] + m[2][2];
    if trace > 0.0 {
        let s = (trace + 1.0).sqrt() * 2.0;
        [
            (m[2][1] - m[1][2]) / s,
            (m[0][2] - m[2][0]) / s,
            (m[1][0] - m[0][1]) / s,
            0.25 * s,
        ]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt() * 2.0;
        [
            0.25 * s,
            (m[0][1] + m[1][0]) / s,
            (m[0][2] + m[2][0]) / s,
            (m[2][1] - m[1][2]) / s,
        ]
    } else if m[1][1] > m[2][2] {
        let s = (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt() * 2.0;
        [
            (m[0][1] + m[1][0]) / s,
            0.25 * s,
            (m[1][2] + m[2][1]) / s,
            (m[0][2] - m[2][0]) / s,
        ]
    } else {
        let s = (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt() * 2.0;
        [
            (m[0][2] + m[2][0]) / s,
            (m[1][2] + m[2][1]) / s,
            0.25 * s,
            (m[1][0] - m[0][1]) / s,
        ]
    }
}

const FULL_RATE_DT: f64 = 1.0 / 120.0;
const LOW_RES_PERIOD: f64 = 0.25;

/// A ball thrown onto a floor at y = 0: a ballistic arc with damped bounces, 120 Hz for 3 s.
fn ballistic_path(rng: &mut Rng) -> Polyline {
    let mut p = [
        rng.range(-4.0, 4.0),
        rng.range(0.5, 4.0),
        rng.range(-4.0, 4.0),
    ];
    let mut v = [
        rng.range(-4.0, 4.0),
        rng.range(-2.0, 8.0),
        rng.range(-4.0, 4.0),
    ];
    let e = rng.range(0.3, 0.9);
    let mut points = vec![p];
    for _ in 0..360 {
        v[1] -= 9.81 * FULL_RATE_DT;
        p = add(p, scale(v, FULL_RATE_DT));
        if p[1] < 0.0 {
            p[1] *= -e;
            v[1] *= -e;
            v[0] *= 0.9;
            v[2] *= 0.9;
        }
        points.push(p);
    }
    Polyline::uniform(0.0, FULL_RATE_DT, points).expect("finite, increasing")
}

/// One never-miss case: a true full-rate path, its decoded version (within e_max per frame),
/// the low-res polyline indexed by the tree, and a camera box aimed near the path.
struct Case {
    decoded: Polyline,
    low: Polyline,
    radius: f64,
    frustum: Frustum,
    window: Option<TimeWindow>,
}

fn case(seed: u64) -> Case {
    let mut rng = Rng(seed);
    let truth = ballistic_path(&mut rng);
    let low = truth.subsample(LOW_RES_PERIOD);
    let deviation = low.max_deviation_from(&truth);
    // Stand-in for the codec: every decoded position within e_max of the true one.
    let e_max = rng.range(0.0, 0.01);
    let decoded_points = truth
        .points()
        .iter()
        .map(|&p| {
            let d = rng.vec3(-1.0, 1.0);
            let d = scale(d, e_max * rng.unit() / norm(d).max(1.0));
            add(p, d)
        })
        .collect();
    let decoded = Polyline::new(truth.times().to_vec(), decoded_points).expect("finite");

    // Aim at a random frame of the path from 2–15 m away; put the box near its projection.
    let k = (rng.unit() * truth.len() as f64) as usize % truth.len();
    let target = add(truth.points()[k], rng.vec3(-0.5, 0.5));
    let direction = normalize(rng.vec3(-1.0, 1.0)).unwrap_or([0.0, 0.0, 1.0]);
    let eye = add(target, scale(direction, rng.range(2.0, 15.0)));
    let (w, h) = (
        rng.range(320.0, 1920.0) as u32,
        rng.range(240.0, 1080.0) as u32,
    );
    let camera = Camera {
        position: eye,
        rotation: look_at(eye, target),
        intrinsics: Intrinsics::VerticalFov {
            fov_y_rad: rng.range(0.3, 1.6),
        },
        viewport: Viewport {
            width: w,
            height: h,
        },
        near: rng.range(0.05, 1.5),
        far: rng.range(3.0, 30.0),
    };
    let proj = camera.projection().expect("valid camera");
    let (centre, _) = proj
        .project(truth.points()[k])
        .unwrap_or(([0.5 * f64::from(w), 0.5 * f64::from(h)], 1.0));
    let (rw, rh) = (rng.range(2.0, 120.0), rng.range(2.0, 120.0));
    let (cx, cy) = (
        centre[0] + rng.range(-1.5, 1.5) * rw,
        centre[1] + rng.range(-1.5, 1.5) * rh,
    );
    let rect = ScreenRect {
        x0: cx - 0.5 * rw,
        y0: cy - 0.5 * rh,
        x1: cx + 0.5 * rw,
        y1: cy + 0.5 * rh,
    };
    let frustum = proj.frustum(&rect).expect("non-empty rect");
    let window = if rng.unit() < 0.4 {
        let a = rng.range(-0.2, 3.0);
        let b = a + rng.range(0.0, 1.5);
        TimeWindow::new(a, b).ok()
    } else {
        None
    };
    Case {
        decoded,
        low,
        radius: e_max + deviation,
        frustum,
        window,
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 400, ..ProptestConfig::default() })]

    /// The never-miss property: whenever brute force over the decoded full-rate segments finds
    /// the path in the frustum, the OBB tree over the 4 Hz polyline, inflated by e_max + the
    /// low-res deviation, finds it too (and no later than the true first entry's segment allows).
    #[test]
    fn inflated_tree_never_misses_a_full_rate_hit(seed in any::<u64>()) {
        let c = case(seed);
        let tree = PathTree::build(c.low.clone());
        prop_assert!(tree.depth() <= MAX_TREE_DEPTH);
        if let Some(t_true) = c.decoded.first_entry(&c.frustum, c.window) {
            let found = tree.first_entry(&c.frustum.inflated(c.radius), c.window);
            prop_assert!(found.is_some(), "missed a hit at t = {t_true} (radius {})", c.radius);
            prop_assert!(tree.intersects(&c.frustum, c.window, c.radius));
            // The decoded point at t_true is within `radius` of the low-res point at t_true,
            // which is inside the inflated frustum: so the low-res path enters no later.
            let t_found = found.unwrap_or(f64::INFINITY);
            prop_assert!(t_found <= t_true + 1e-9, "found {t_found} after {t_true}");
        }
    }

    /// Without inflation the tree answers exactly what brute force over its own polyline does.
    #[test]
    fn tree_equals_brute_force_on_its_polyline(seed in any::<u64>(), inflate in 0.0f64..0.3) {
        let c = case(seed);
        let tree = PathTree::build(c.low.clone());
        tree.check_boxes();
        for f in [c.frustum, c.frustum.inflated(inflate)] {
            prop_assert_eq!(tree.first_entry(&f, c.window), c.low.first_entry(&f, c.window));
            prop_assert_eq!(tree.first_entry(&f, None), c.low.first_entry(&f, None));
        }
        let full = PathTree::build(c.decoded.clone());
        prop_assert_eq!(full.first_entry(&c.frustum, c.window), c.decoded.first_entry(&c.frustum, c.window));
    }

    /// Exactness on erratic polylines too (random vertices, uneven times), where boxes overlap a
    /// lot and pruning is most delicate.
    #[test]
    fn tree_equals_brute_force_on_random_polylines(
        seed in any::<u64>(),
        n in 1usize..80,
    ) {
        let mut rng = Rng(seed);
        let mut t = 0.0;
        let mut times = Vec::new();
        let mut points = Vec::new();
        for _ in 0..n {
            t += rng.range(0.001, 0.5);
            times.push(t);
            points.push(rng.vec3(-3.0, 3.0));
        }
        let path = Polyline::new(times, points).expect("valid");
        let tree = PathTree::build(path.clone());
        tree.check_boxes();
        prop_assert!(tree.depth() <= MAX_TREE_DEPTH);
        let eye = rng.vec3(-10.0, 10.0);
        let camera = Camera {
            position: eye,
            rotation: look_at(eye, rng.vec3(-1.0, 1.0)),
            intrinsics: Intrinsics::VerticalFov { fov_y_rad: rng.range(0.2, 1.5) },
            viewport: Viewport { width: 640, height: 480 },
            near: 0.1,
            far: rng.range(1.0, 30.0),
        };
        let x0 = rng.range(0.0, 600.0);
        let y0 = rng.range(0.0, 450.0);
        let rect = ScreenRect { x0, y0, x1: x0 + rng.range(1.0, 200.0), y1: y0 + rng.range(1.0, 200.0) };
        let f = camera.frustum(&rect).expect("valid");
        let a = rng.range(0.0, t);
        let window = TimeWindow::new(a, a + rng.range(0.0, t)).ok();
        prop_assert_eq!(tree.first_entry(&f, window), path.first_entry(&f, window));
        prop_assert_eq!(tree.first_entry(&f, None), path.first_entry(&f, None));
    }
}

/// The generator is not trivial: over fixed seeds many cases hit, and some full-rate hits are
/// missed by the *uninflated* low-res query, so the inflation in the property above is doing
/// real work (the property would fail without it).
#[test]
fn never_miss_cases_need_the_inflation() {
    let (mut hits, mut missed_without_inflation) = (0, 0);
    for seed in 0..600u64 {
        let c = case(seed);
        let tree = PathTree::build(c.low.clone());
        if c.decoded.first_entry(&c.frustum, c.window).is_some() {
            hits += 1;
            if tree.first_entry(&c.frustum, c.window).is_none() {
                missed_without_inflation += 1;
            }
            assert!(
                tree.intersects(&c.frustum, c.window, c.radius),
                "seed {seed}"
            );
        }
    }
    assert!(hits > 100, "only {hits} of 600 cases hit");
    assert!(
        missed_without_inflation > 0,
        "no case needed inflation ({hits} hits)"
    );
}

#[test]
fn tree_shape_respects_the_depth_limit() {
    let points: Vec<Vec3> = (0..400)
        .map(|i| [i as f64, (i as f64).sin(), 0.0])
        .collect();
    let tree = PathTree::build(Polyline::uniform(0.0, 0.25, points).expect("valid"));
    assert_eq!(tree.depth(), MAX_TREE_DEPTH);
    assert_eq!(tree.node_count(), 15);
    tree.check_boxes();
    let short = PathTree::build(
        Polyline::uniform(0.0, 0.25, vec![[0.0; 3], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
            .expect("valid"),
    );
    assert_eq!((short.depth(), short.node_count()), (0, 1));
    let single = PathTree::build(Polyline::new(vec![1.0], vec![[0.0, 0.0, -5.0]]).expect("valid"));
    assert_eq!(single.path().segment_count(), 1);
    assert!(single.heap_bytes() > 0);
}

#[test]
fn single_point_path_and_windows() {
    let camera = Camera {
        position: [0.0; 3],
        rotation: [0.0, 0.0, 0.0, 1.0],
        intrinsics: Intrinsics::VerticalFov { fov_y_rad: 1.0 },
        viewport: Viewport {
            width: 100,
            height: 100,
        },
        near: 0.1,
        far: 10.0,
    };
    let f = camera
        .frustum(&ScreenRect {
            x0: 40.0,
            y0: 40.0,
            x1: 60.0,
            y1: 60.0,
        })
        .expect("valid");
    let single = PathTree::build(Polyline::new(vec![1.0], vec![[0.0, 0.0, -5.0]]).expect("valid"));
    assert_eq!(single.first_entry(&f, None), Some(1.0));
    assert_eq!(single.first_entry(&f, TimeWindow::new(0.0, 0.5).ok()), None);
    assert_eq!(
        single.first_entry(&f, TimeWindow::new(1.0, 1.0).ok()),
        Some(1.0)
    );
    // A straight pass along x at depth 5, crossing the box around t = 5 (x = 0).
    let pass = Polyline::uniform(
        0.0,
        1.0,
        (0..11).map(|i| [f64::from(i) - 5.0, 0.0, -5.0]).collect(),
    )
    .expect("valid");
    let tree = PathTree::build(pass.clone());
    let t = tree.first_entry(&f, None).expect("hits");
    assert!(t > 4.0 && t < 5.0, "{t}");
    // The window cuts the segment: entering at the window start, not before.
    let t = tree
        .first_entry(&f, TimeWindow::new(4.95, 6.0).ok())
        .expect("hits");
    assert!((t - 4.95).abs() < 1e-12, "{t}");
    assert_eq!(tree.first_entry(&f, TimeWindow::new(5.6, 9.0).ok()), None);
}

#[test]
fn subsample_and_deviation() {
    // Free fall sampled at 120 Hz, reduced to 4 Hz: the chord of y = −g t²/2 over h seconds is
    // g h²/8 from the arc at the middle of the interval, a full-rate frame here.
    let full = Polyline::uniform(
        0.0,
        FULL_RATE_DT,
        (0..=360)
            .map(|i| {
                let t = f64::from(i) * FULL_RATE_DT;
                [t, -0.5 * 9.81 * t * t, 0.0]
            })
            .collect(),
    )
    .expect("valid");
    let low = full.subsample(LOW_RES_PERIOD);
    assert_eq!(low.len(), 13);
    assert_eq!(low.times()[0], 0.0);
    assert!((low.times()[12] - 3.0).abs() < 1e-12);
    assert!((low.times()[1] - 0.25).abs() < 1e-12);
    let dev = low.max_deviation_from(&full);
    let want = 9.81 * LOW_RES_PERIOD * LOW_RES_PERIOD / 8.0;
    assert!((dev - want).abs() < 1e-9, "{dev} vs {want}");
    assert_eq!(full.max_deviation_from(&full), 0.0);
    // Uniform straight motion loses nothing.
    let line = Polyline::uniform(
        0.0,
        FULL_RATE_DT,
        (0..100).map(|i| [f64::from(i), 2.0, 3.0]).collect(),
    )
    .expect("valid");
    assert!(line.subsample(0.25).max_deviation_from(&line) < 1e-9);
    // Positions are held beyond the ends.
    assert_eq!(line.position_at(-1.0), [0.0, 2.0, 3.0]);
    assert_eq!(line.position_at(100.0), [99.0, 2.0, 3.0]);
}

#[test]
fn polyline_validation_names_the_field() {
    assert_eq!(
        Polyline::new(vec![], vec![]),
        Err(BrowseError::Empty {
            field: "path.times"
        })
    );
    assert!(matches!(
        Polyline::new(vec![0.0, 1.0], vec![[0.0; 3]]),
        Err(BrowseError::LengthMismatch { .. })
    ));
    assert!(matches!(
        Polyline::new(vec![0.0, 0.0], vec![[0.0; 3]; 2]),
        Err(BrowseError::TimesNotIncreasing { at: 1, .. })
    ));
    assert!(matches!(
        Polyline::new(vec![0.0], vec![[f64::NAN, 0.0, 0.0]]),
        Err(BrowseError::NonFinite { .. })
    ));
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, ..ProptestConfig::default() })]

    /// The error-bounded simplification the store indexes: every full-rate frame lies within the
    /// tolerance of the polyline at the same time, the reported deviation is the true one, and
    /// the never-miss test over the simplified path (radius e_max + deviation) finds every hit.
    #[test]
    fn simplified_path_is_bounded_and_never_misses(seed in any::<u64>(), tol in 0.0f64..0.05) {
        let c = case(seed);
        let (simple, dev) = Polyline::simplify(0.0, FULL_RATE_DT, c.decoded.points(), tol)
            .expect("valid path");
        prop_assert!(dev <= tol + 1e-12, "deviation {dev} above tolerance {tol}");
        let measured = simple.max_deviation_from(&c.decoded);
        prop_assert!((measured - dev).abs() < 1e-9, "reported {dev}, measured {measured}");
        prop_assert_eq!(simple.times()[0], 0.0);
        prop_assert_eq!(simple.times().last(), c.decoded.times().last());
        if tol == 0.0 {
            prop_assert!(simple.len() <= c.decoded.len());
        }
        let tree = PathTree::build(simple);
        if c.decoded.first_entry(&c.frustum, c.window).is_some() {
            // The decoded path itself is the reference here, so only the simplification error
            // needs covering.
            prop_assert!(tree.intersects(&c.frustum, c.window, dev));
        }
    }
}

#[test]
fn simplify_collapses_rest_and_keeps_corners() {
    // 1 s at rest, then a straight slide, then rest: three segments suffice at any tolerance.
    let mut pts = vec![[0.0, 0.0, 0.0]; 120];
    pts.extend((1..=120).map(|i| [f64::from(i) / 120.0, 0.0, 0.0]));
    pts.extend(std::iter::repeat_n([1.0, 0.0, 0.0], 120));
    let (p, dev) = Polyline::simplify(0.0, FULL_RATE_DT, &pts, 1e-6).expect("valid");
    assert_eq!(p.len(), 4, "{:?}", p.times());
    assert!(dev < 1e-12);
    // A parabola needs more vertices at a tighter tolerance.
    let arc: Vec<Vec3> = (0..=360)
        .map(|i| {
            let t = f64::from(i) * FULL_RATE_DT;
            [t, -0.5 * 9.81 * t * t, 0.0]
        })
        .collect();
    let (coarse, d1) = Polyline::simplify(0.0, FULL_RATE_DT, &arc, 0.05).expect("valid");
    let (fine, d2) = Polyline::simplify(0.0, FULL_RATE_DT, &arc, 0.005).expect("valid");
    assert!(fine.len() > coarse.len() && d1 <= 0.05 && d2 <= 0.005);
    // Chord error of g h²/8 ≤ tol gives h ≈ √(8·tol/g): about 0.2 s at 5 cm.
    assert!(coarse.len() >= 12 && coarse.len() <= 20, "{}", coarse.len());
    assert!(matches!(
        Polyline::simplify(0.0, 0.0, &arc, 0.01),
        Err(BrowseError::OutOfRange {
            field: "frame_dt",
            ..
        })
    ));
    assert!(matches!(
        Polyline::simplify(0.0, FULL_RATE_DT, &[], 0.01),
        Err(BrowseError::Empty { .. })
    ));
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 300, ..ProptestConfig::default() })]

    /// `Obb::apart` (plane + separating-axis test on the region's vertices) never separates a
    /// box from the inflated region it overlaps — the region bounded by the planes moved out by
    /// `r`, corners included, which is what segment clipping tests. Boxes are fitted around
    /// path points, or put at a corner of the inflated region (where it reaches furthest beyond
    /// "within r of the frustum"); points of the box inside the region are searched by
    /// sampling, and whenever one is found the test must say "not apart".
    #[test]
    fn apart_never_separates_overlapping_boxes(seed in any::<u64>(), r in 0.0f64..0.2, at_corner in any::<bool>()) {
        let c = case(seed);
        let region = c.frustum.inflated_bounded(r);
        prop_assert!(region.hull().is_some(), "a camera frustum inflated by {r} is bounded");
        let mut rng = Rng(seed ^ 0xA5A5);
        let (centre, spread) = match (at_corner, region.hull()) {
            (true, Some(hull)) => {
                let v = hull[(rng.unit() * hull.len() as f64) as usize % hull.len()];
                (v, rng.range(0.001, 0.3))
            }
            _ => {
                let k = (rng.unit() * c.decoded.len() as f64) as usize % c.decoded.len();
                (c.decoded.points()[k], 0.5)
            }
        };
        let pts: Vec<Vec3> = (0..rng.range(1.0, 12.0) as usize)
            .map(|_| add(centre, rng.vec3(-spread, spread)))
            .collect();
        let obb = Obb::fit(&pts);
        let mut overlap = false;
        for _ in 0..2000 {
            let mut x = obb.center;
            for k in 0..3 {
                x = add(x, scale(obb.axes[k], rng.range(-1.0, 1.0) * obb.half[k]));
            }
            if region.contains(x) {
                overlap = true;
                break;
            }
        }
        if overlap {
            prop_assert!(!obb.apart(&region));
        }
        // Inflating only ever makes "apart" harder.
        if !obb.apart(&c.frustum.inflated_bounded(0.0)) {
            prop_assert!(!obb.apart(&region));
        }
        // And the tree decides exactly as segment clipping on the same region does.
        let tree = PathTree::build(c.low.clone());
        prop_assert_eq!(
            tree.intersects(&c.frustum, None, r),
            c.low.first_entry(&c.frustum.inflated(r), None).is_some()
        );
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 300, ..ProptestConfig::default() })]

    /// Plane masking is sound: `classify` drops a plane only when every corner of the box is
    /// strictly inside it, and answers `None` only when one plane has every corner outside.
    /// The tree, which masks planes down its nodes, then decides exactly as clipping every
    /// segment against the region does, windows included. Boxes sit around path points or at a
    /// corner of the region, where the planes are closest to straddling.
    #[test]
    fn plane_masks_are_sound_and_keep_the_tree_exact(
        seed in any::<u64>(),
        r in 0.0f64..0.2,
        at_corner in any::<bool>(),
        windowed in any::<bool>(),
    ) {
        let (c, region, obb) = mask_case(seed, r, at_corner);
        let corners: Vec<Vec3> = (0..8)
            .map(|k: usize| {
                (0..3).fold(obb.center, |x, i| {
                    let sign = if k >> i & 1 == 1 { 1.0 } else { -1.0 };
                    add(x, scale(obb.axes[i], sign * obb.half[i]))
                })
            })
            .collect();
        let got = obb.classify(&region, ALL_PLANES);
        match got {
            None => {
                let separated = region
                    .planes()
                    .iter()
                    .any(|p| corners.iter().all(|&x| p.distance(x) > 0.0));
                prop_assert!(separated);
            }
            Some(mask) => {
                for (k, p) in region.planes().iter().enumerate() {
                    let inside = corners.iter().all(|&x| p.distance(x) < 0.0);
                    prop_assert!(inside || mask & (1 << k) != 0, "plane {}", k);
                }
                // Testing again from the mask changes nothing.
                prop_assert_eq!(obb.classify(&region, mask), Some(mask));
            }
        }

        let tree = PathTree::build(c.low.clone());
        let window = if windowed { c.window } else { None };
        let truth = c.low.first_entry(&region, window);
        prop_assert_eq!(tree.intersects_region(&region, window), truth.is_some());
        prop_assert_eq!(tree.first_entry(&region, window), truth);
    }
}

/// A case of [`plane_masks_are_sound_and_keep_the_tree_exact`]: the frustum inflated by `r`
/// and a box at a corner of that region, or else around its centre or a path point.
fn mask_case(seed: u64, r: f64, at_corner: bool) -> (Case, Frustum, Obb) {
    let c = case(seed);
    let region = c.frustum.inflated(r);
    let mut rng = Rng(seed ^ 0x5A5A);
    let centre = match (at_corner, c.frustum.inflated_bounded(r).hull()) {
        (true, Some(hull)) => hull[(rng.unit() * hull.len() as f64) as usize % hull.len()],
        // The centroid of the vertices: inside the region.
        (false, Some(hull)) if rng.unit() < 0.5 => scale(
            hull.iter().fold([0.0; 3], |a, &v| add(a, v)),
            1.0 / hull.len() as f64,
        ),
        _ => {
            let k = (rng.unit() * c.decoded.len() as f64) as usize % c.decoded.len();
            c.decoded.points()[k]
        }
    };
    // Sizes from 1 mm to 1 m, evenly on a log scale.
    let spread = 10f64.powf(rng.range(-3.0, 0.0));
    let pts: Vec<Vec3> = (0..rng.range(1.0, 12.0) as usize)
        .map(|_| add(centre, rng.vec3(-spread, spread)))
        .collect();
    (c, region, Obb::fit(&pts))
}

/// The generator above is not trivial: boxes get rejected, kept wholly inside, and kept
/// straddling some planes but inside others.
#[test]
fn mask_cases_cover_every_outcome() {
    let (mut outside, mut inside, mut partial) = (0, 0, 0);
    for seed in 0..400u64 {
        let (_, region, obb) = mask_case(seed, 0.01 * (seed % 7) as f64, seed % 2 == 0);
        match obb.classify(&region, ALL_PLANES) {
            None => outside += 1,
            Some(0) => inside += 1,
            Some(m) if m != ALL_PLANES => partial += 1,
            Some(_) => {}
        }
    }
    assert!(
        outside > 20 && inside > 20 && partial > 20,
        "outside {outside}, inside {inside}, partial {partial}"
    );
}

/// A frustum holding the whole path: the root box is inside every plane (mask 0), no segment
/// is clipped, and the answers (first entry, with and without windows) are still exactly the
/// segment-by-segment ones.
#[test]
fn a_box_inside_every_plane_answers_without_clipping() {
    let points: Vec<Vec3> = (0..60)
        .map(|i| {
            let t = f64::from(i) * 0.05;
            [t, 1.0 + (3.0 * t).sin(), 0.2 * t]
        })
        .collect();
    let times: Vec<f64> = (0..60).map(|i| 0.1 + f64::from(i) / 30.0).collect();
    let path = Polyline::new(times, points).expect("valid");
    let tree = PathTree::build(path.clone());
    assert!(tree.node_count() > 1, "the tree has children");
    let region = Frustum::aabb([-10.0; 3], [10.0; 3]).expect("finite");
    assert_eq!(tree.root_box().classify(&region, ALL_PLANES), Some(0));
    for window in [
        None,
        TimeWindow::new(0.0, 0.05).ok(),
        TimeWindow::new(0.7, 0.71).ok(),
        TimeWindow::new(1.234_567, 9.0).ok(),
        TimeWindow::new(2.05, 2.1).ok(),
        TimeWindow::new(2.5, 3.0).ok(),
    ] {
        assert_eq!(
            tree.first_entry(&region, window),
            path.first_entry(&region, window),
            "{window:?}"
        );
        assert_eq!(
            tree.intersects_region(&region, window),
            path.first_entry(&region, window).is_some(),
            "{window:?}"
        );
    }
    assert_eq!(tree.first_entry(&region, None), Some(0.1));
    // The path ends at 2.07 s; its body rests at the last vertex, inside the box, from then on.
    assert_eq!(
        tree.first_entry(&region, TimeWindow::new(2.5, 3.0).ok()),
        Some(2.5)
    );
}

/// Brute force on decoded motion, frame by frame, with the rule of issue 24: once its world has
/// ended a body stays at its final pose, so a window reaching past the last frame sees that
/// pose. Uses nothing of the index (no segment clipping): frames and `Frustum::contains`.
fn frames_hit(decoded: &Polyline, frustum: &Frustum, window: Option<TimeWindow>) -> bool {
    let in_window = |t: f64| window.is_none_or(|w| w.contains(t));
    let (end, t_end) = decoded.end();
    decoded
        .times()
        .iter()
        .zip(decoded.points())
        .any(|(&t, &p)| in_window(t) && frustum.contains(p))
        || (window.is_none_or(|w| w.end() >= t_end) && frustum.contains(end))
}

/// A case for the rest-pose properties: the never-miss case, a box near the final pose (so that
/// final poses are often inside), and windows past the end and across it.
fn rest_case(seed: u64) -> (Case, Frustum, [Option<TimeWindow>; 3]) {
    let c = case(seed);
    let mut rng = Rng(seed ^ 0x7E57);
    let (end, t_end) = c.decoded.end();
    let centre = add(end, rng.vec3(-0.3, 0.3));
    let half = rng.range(0.01, 0.4);
    let near_end = Frustum::aabb(
        [centre[0] - half, centre[1] - half, centre[2] - half],
        [centre[0] + half, centre[1] + half, centre[2] + half],
    )
    .expect("finite");
    let after = rng.range(1e-6, 3.0);
    let past = TimeWindow::new(t_end + after, t_end + after + rng.range(0.0, 3.0)).ok();
    let from = t_end - rng.range(0.0, 0.5);
    let across = TimeWindow::new(from, t_end + rng.range(0.0, 3.0)).ok();
    let windows = [c.window, past, across];
    (c, near_end, windows)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 300, ..ProptestConfig::default() })]

    /// Issue 24, never miss with rest poses: whenever brute force on the decoded frames (final
    /// pose held after the end) finds the body in the volume during a window — before, across
    /// or wholly after the world's end — the OBB tree over the low-res polyline, inflated by
    /// its radius, finds it too; a final-pose test likewise. On the decoded polyline itself a
    /// window wholly past the end and the final-pose test answer exactly what brute force does,
    /// and the tree always answers exactly what its own polyline does.
    #[test]
    fn rest_poses_and_final_states_are_never_missed(seed in any::<u64>()) {
        let (c, near_end, windows) = rest_case(seed);
        let low = PathTree::build(c.low.clone());
        let decoded = PathTree::build(c.decoded.clone());
        let (end, t_end) = c.decoded.end();
        prop_assert_eq!(c.low.end(), (c.low.points()[c.low.len() - 1], t_end));
        for frustum in [c.frustum, near_end] {
            let inflated = frustum.inflated(c.radius);
            for window in windows {
                if frames_hit(&c.decoded, &frustum, window) {
                    prop_assert!(
                        low.first_entry(&inflated, window).is_some(),
                        "missed {window:?} (end {t_end}, radius {})", c.radius
                    );
                    prop_assert!(low.intersects(&frustum, window, c.radius));
                }
                prop_assert_eq!(low.first_entry(&inflated, window), c.low.first_entry(&inflated, window));
                prop_assert_eq!(decoded.first_entry(&frustum, window), c.decoded.first_entry(&frustum, window));
                if let Some(w) = window.filter(|w| w.start() > t_end) {
                    // Past the end only the final pose is left: exact, and entered at the start.
                    let inside = frustum.contains(end);
                    prop_assert_eq!(decoded.first_entry(&frustum, window).is_some(), inside);
                    if inside {
                        prop_assert_eq!(decoded.first_entry(&frustum, window), Some(w.start()));
                    }
                }
            }
            let final_inside = frustum.contains(end);
            prop_assert_eq!(decoded.final_pose_inside(&frustum), final_inside);
            if final_inside {
                prop_assert!(low.final_pose_inside(&inflated), "final pose missed");
            }
            // The final pose is part of the motion: a final-pose hit is a hit without a window.
            if low.final_pose_inside(&inflated) {
                prop_assert!(low.first_entry(&inflated, None).is_some());
            }
        }
    }
}

/// The generator exercises what the property is about: many windows wholly past the end find
/// the resting body (a segments-only test finds none of them: every segment ends before the
/// window), and many final poses are inside their box.
#[test]
fn rest_cases_hit_after_the_end() {
    let (mut late_hits, mut final_hits) = (0, 0);
    for seed in 0..300u64 {
        let (c, near_end, windows) = rest_case(seed);
        let (_, t_end) = c.decoded.end();
        let past = windows[1].filter(|w| w.start() > t_end);
        if let Some(w) = past
            && frames_hit(&c.decoded, &near_end, past)
        {
            late_hits += 1;
            let segments_only = (0..c.decoded.segment_count())
                .find_map(|i| c.decoded.segment_entry(i, &near_end, ALL_PLANES, Some(w)));
            assert_eq!(segments_only, None, "seed {seed}");
        }
        final_hits += usize::from(near_end.contains(c.decoded.end().0));
    }
    assert!(late_hits > 50, "{late_hits} late hits");
    assert!(final_hits > 50, "{final_hits} final poses inside");
}
