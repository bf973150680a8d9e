//! Scene limit checks (issue 19): what the simulator cannot do faithfully, found from the scene
//! alone, before a single world is sampled. `mwb scene` and job submission print the
//! [`Finding`]s; a [`Severity::Refuse`] stops a job.
//!
//! Pure: [`check`] reads a scene instance and the [`SimPlan`] the samplers would build from it
//! (substeps, length unit, speed cap, CCD), and nothing else.
//!
//! Every limit here is a number measured by the extremes matrix (`tests/extremes.rs`, rapier
//! 0.36.1 f32, dt 1/120) or a constant of rapier's own that those measurements confirmed; each
//! constant says which. The measurements, in short (docs/fidelity.md has the tables):
//!
//! * **Soft contacts.** rapier solves a contact as a spring-damper of fixed natural frequency
//!   (30 Hz between two dynamic bodies, 60 Hz against a fixed one; ζ = 10), whatever the
//!   substeps or iterations. A contact carrying a load `L` between bodies of reduced mass `m*`
//!   settles `L / m* · g / ω²` inside: 69 µm for any body resting on the ground (measured
//!   −6.9e-5 m from 1 mm to 1 m boxes), 0.28 mm per unit of mass ratio for a heavy body on a
//!   light one (measured 3 mm at 10, 27 mm at 100, a 0.2 m box crushed at 300 and above, at
//!   draft, standard, final and reference alike), and `n (n − 1) · g / ω²` of sag for a stack of
//!   `n` equal boxes (measured 23 mm at 10, 0.67 m at 50). More iterations do not help: the
//!   messages say so instead of suggesting a preset.
//! * **Tunnelling.** With CCD on, a 0.1 m ball passed through a static wall once its travel in
//!   one step (speed × dt) reached 5.0 m at a 2 cm wall, 5.8 m at 5 cm, 7.5 m at 0.1 m, 11.7 m
//!   at 0.2 m and 17.5 m at 0.4 m and 1 m (the same at draft, standard and final, and whether
//!   or not the wall was reached in the first step).
//! * **Sleeping.** rapier puts a body to sleep once it has been slower than `0.05 · length_unit`
//!   m/s for 0.5 s: at a length unit of 100 (chosen for 100 m bodies) a box dropped from rest
//!   fell asleep in mid-air after 1.3 m. The plan now keeps that speed at 0.05 m/s for units
//!   above 1 ([`SimPlan::sleep_speed`]), so there is nothing left to check.
//! * **Restitution.** A ball with restitution 1 lost 1.1 % of its apex per bounce at standard
//!   (3.6 % at draft, 0.9 % at final): at rest after 60 s at standard.

use mwb_core::frames::rotate_vector;
use mwb_core::scene::{CcdPolicy, Scene, SceneTemplate, Shape, SimPreset};

use crate::plan::SimPlan;
use crate::world::{ccd_bodies, speed_bound};

/// How serious a finding is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Severity {
    /// The scene runs, but some of its motion will not be what the scene describes.
    Warn,
    /// The simulator cannot do this scene: sampling it would produce worlds that are wrong
    /// where it matters (bodies crushed, tunnelling, frozen in mid-air).
    Refuse,
}

/// One limit a scene reaches.
#[derive(Debug, Clone, PartialEq)]
pub struct Finding {
    pub severity: Severity,
    /// The body it is about, as the scene names it (none for scene-wide settings).
    pub body: Option<String>,
    /// The scene field to change (`"material"`, `"linvel"`, `"settings.sim"`, …).
    pub field: &'static str,
    /// What is wrong, with the numbers and what to do.
    pub message: String,
}

/// rapier's contact spring between two dynamic bodies (`SpringCoefficients::contact_defaults`,
/// 30 Hz). Confirmed by the stack sag and the mass-ratio overlaps of the extremes matrix.
pub const CONTACT_HZ: f64 = 30.0;
/// rapier's contact spring against a fixed body (`contact_static_defaults`, 60 Hz). Confirmed:
/// every box resting on the ground sat 6.9e-5 m = g / (2π·60)² inside it.
pub const STATIC_CONTACT_HZ: f64 = 60.0;
/// rapier's allowed penetration at length unit 1 (`normalized_allowed_linear_error`, 5 mm): a
/// contact that settles deeper than this is visibly inside.
pub const ALLOWED_ERROR: f64 = 0.005;
/// A resting contact that settles deeper than this fraction of the lower body's half-thickness
/// crushes it: measured, a 0.2 m box under a 100× heavier one (27 % of its half-thickness)
/// held, under a 300× heavier one (predicted 83 %) it was squeezed out and the heavy box fell
/// to the ground, at every preset.
pub const CRUSH_FRACTION: f64 = 0.5;
/// A stack warns when its predicted sag exceeds this (m): ten times the standard codec bound
/// (1 mm), where a stack is visibly shorter. The 10-box stack of the analytic suite sags 23 mm,
/// a 5-box one 5.5 mm (predicted).
pub const STACK_SAG: f64 = 0.01;
/// A body warns when its resting penetration against the ground (69 µm, see
/// [`STATIC_CONTACT_HZ`]) exceeds this fraction of its size: 1 %, i.e. bodies smaller than
/// about 7 mm (the 1 mm box of the matrix sat 6.9 % of its size inside the ground).
pub const SINK_FRACTION: f64 = 0.01;
/// … and is refused above this fraction (25 %: a quarter of the body inside the ground; bodies
/// under about 0.3 mm).
pub const SINK_REFUSE_FRACTION: f64 = 0.25;
/// Travel in one step (m) beyond which a body may pass through a wall even with CCD on, as a
/// function of the wall's thickness `w` (m): `4 + 33 w`, at most 16. A lower envelope of the
/// measured first failures (5.0 m at 2 cm … 17.5 m at 0.4 m and thicker); walls thinner than
/// 2 cm were not measured and get the same formula.
pub fn max_travel_per_step(wall_thickness: f64) -> f64 {
    (4.0 + 33.0 * wall_thickness).min(16.0)
}
/// Restitution from which bounces are long-lived enough for the solver's loss per bounce to
/// show (1.1 % of the apex per bounce at standard, measured at e = 1 and 0.8).
pub const BOUNCY: f64 = 0.95;
/// Tallest stack (bodies in a column) draft holds without leaning more than 1 cm: measured at
/// draft over 10 s, 3 to 8 boxes leaned at most 7 mm, 10 boxes 2.5 cm (3.7 mm at standard),
/// 50 boxes 14 cm (8 mm at standard).
pub const DRAFT_STACK: usize = 8;
/// f32 keeps 24 bits of a coordinate: a body this many metres from the origin is placed to
/// within `|x| · 2⁻²⁴`.
const F32_EPSILON: f64 = 1.0 / 16_777_216.0;

/// The limits `scene` reaches, refusals first, then warnings (each in the order the checks
/// run: resting contacts, mass ratio, sizes, speeds, restitution, joints).
pub fn check(scene: &Scene) -> Vec<Finding> {
    let plan = SimPlan::of(scene);
    let geo = Geometry::of(scene);
    let mut out = Vec::new();
    resting_contacts(scene, &plan, &geo, &mut out);
    mass_ratio(scene, &geo, &mut out);
    sizes(scene, &geo, &mut out);
    speeds(scene, &plan, &mut out);
    restitution(scene, &plan, &mut out);
    joints(scene, &plan, &geo, &mut out);
    out.sort_by_key(|f| std::cmp::Reverse(f.severity));
    out
}

/// Instances [`check_template`] checks: a scene with distributions may reach a limit in some
/// worlds only (the fastest throw, the heaviest draw).
pub const CHECKED_INSTANCES: u64 = 8;

/// [`check`] over the first [`CHECKED_INSTANCES`] instances of a template (one for a scene
/// without distributions), each finding once (by severity, body and field), refusals first.
pub fn check_template(template: &SceneTemplate) -> Vec<Finding> {
    let mut out: Vec<Finding> = Vec::new();
    let instances = if template.has_distributions() {
        CHECKED_INSTANCES
    } else {
        1
    };
    for seed in 0..instances {
        for f in check(&template.instantiate(seed)) {
            if !out
                .iter()
                .any(|o| o.body == f.body && o.field == f.field && o.severity == f.severity)
            {
                out.push(f);
            }
        }
    }
    out.sort_by_key(|f| std::cmp::Reverse(f.severity));
    out
}

impl Finding {
    /// The finding as one line: `file: refused|warning: body "b": field `f`: message`.
    pub fn line(&self, file: &str) -> String {
        let what = match self.severity {
            Severity::Refuse => "refused",
            Severity::Warn => "warning",
        };
        let body = self
            .body
            .as_ref()
            .map(|b| format!("body {b:?}: "))
            .unwrap_or_default();
        format!(
            "{file}: {what}: {body}field `{}`: {}",
            self.field, self.message
        )
    }
}

/// Whether any finding refuses the scene.
pub fn refuses(findings: &[Finding]) -> bool {
    findings.iter().any(|f| f.severity == Severity::Refuse)
}

/// Per body: mass, bounding box at its initial pose, half-thickness; and the up axis.
struct Geometry {
    g: f64,
    /// Index of the axis gravity is along (its dominant component), and the sign of up on it.
    up: Option<(usize, f64)>,
    mass: Vec<f64>,
    aabb: Vec<([f64; 3], [f64; 3])>,
    half: Vec<f64>,
    /// Statics' bounding boxes (planes: the half-space's box on the up axis, else unbounded).
    statics: Vec<([f64; 3], [f64; 3])>,
}

impl Geometry {
    fn of(scene: &Scene) -> Self {
        let [gx, gy, gz] = scene.settings.gravity;
        let g = (gx * gx + gy * gy + gz * gz).sqrt();
        let up = (g > 0.0).then(|| {
            let a = [gx.abs(), gy.abs(), gz.abs()];
            let k = (0..3).fold(0, |m, k| if a[k] > a[m] { k } else { m });
            (k, -scene.settings.gravity[k].signum())
        });
        let mass = scene
            .bodies
            .iter()
            .map(|b| {
                b.shape
                    .placed_parts(b.material)
                    .iter()
                    .map(|p| volume(p.shape) * scene.materials[p.material].density)
                    .sum()
            })
            .collect();
        let boxes = scene
            .bodies
            .iter()
            .map(|b| aabb(&b.shape, b.position, b.rotation))
            .collect();
        let half = scene
            .bodies
            .iter()
            .map(|b| b.shape.min_half_thickness())
            .collect();
        let statics = scene
            .statics
            .iter()
            .map(|s| match (&s.shape, up) {
                // A ground plane: everything below its surface on the up axis.
                (Shape::Plane { normal }, Some((k, sign)))
                    if (normal[k] * sign) > 0.999 && {
                        let r = rotate_vector(s.rotation, *normal);
                        r[k] * sign > 0.999
                    } =>
                {
                    let mut lo = [f64::NEG_INFINITY; 3];
                    let mut hi = [f64::INFINITY; 3];
                    if sign > 0.0 {
                        hi[k] = s.position[k];
                    } else {
                        lo[k] = s.position[k];
                    }
                    (lo, hi)
                }
                (Shape::Plane { .. }, _) => ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]),
                _ => aabb(&s.shape, s.position, s.rotation),
            })
            .collect();
        Self {
            g,
            up,
            mass,
            aabb: boxes,
            half,
            statics,
        }
    }
}

/// `g / ω²` for a contact spring of `hz`: how far one unit of load per unit of reduced mass
/// settles inside.
fn settle(g: f64, hz: f64) -> f64 {
    let w = 2.0 * std::f64::consts::PI * hz;
    g / (w * w)
}

/// Resting contacts at the start: which body rests on which (bounding boxes touching along the
/// up axis and overlapping across it), the load each contact carries, and what the soft
/// contacts make of it: a light body crushed under a heavy one (refused), a contact sinking
/// deeper than rapier's allowed error, a stack that sags or (at draft) leans.
fn resting_contacts(scene: &Scene, plan: &SimPlan, geo: &Geometry, out: &mut Vec<Finding>) {
    let Some((k, sign)) = geo.up else { return };
    let n = scene.bodies.len();
    let top = |b: &([f64; 3], [f64; 3])| if sign > 0.0 { b.1[k] } else { -b.0[k] };
    let bottom = |b: &([f64; 3], [f64; 3])| if sign > 0.0 { b.0[k] } else { -b.1[k] };
    let across = |a: &([f64; 3], [f64; 3]), b: &([f64; 3], [f64; 3])| {
        (0..3)
            .filter(|&j| j != k)
            .all(|j| a.0[j] < b.1[j] && b.0[j] < a.1[j])
    };
    // Touching: the gap between the boxes on the up axis within rapier's own 2 cm contact
    // margin (not the plan's, which may be wider for fast scenes: resting is about gaps
    // closed, not about contacts made early).
    let margin = crate::plan::DEFAULT_PREDICTION * plan.length_unit;
    let touches = |upper: &([f64; 3], [f64; 3]), lower: &([f64; 3], [f64; 3])| {
        let gap = bottom(upper) - top(lower);
        gap.abs() <= margin && across(upper, lower)
    };
    // supports[i]: the bodies body i rests on; grounded[i]: it rests on a static.
    // Sweep and prune along a horizontal axis, so 100 000 bodies (the scene format's most) cost
    // O(n log n) plus their neighbours, not n².
    let h = (k + 1) % 3;
    let mut by_h: Vec<usize> = (0..n).collect();
    by_h.sort_by(|&a, &b| geo.aabb[a].0[h].total_cmp(&geo.aabb[b].0[h]));
    let mut supports: Vec<Vec<usize>> = vec![Vec::new(); n];
    for (x, &a) in by_h.iter().enumerate() {
        for &b in &by_h[x + 1..] {
            if geo.aabb[b].0[h] >= geo.aabb[a].1[h] {
                break;
            }
            if touches(&geo.aabb[a], &geo.aabb[b]) {
                supports[a].push(b);
            }
            if touches(&geo.aabb[b], &geo.aabb[a]) {
                supports[b].push(a);
            }
        }
    }
    let grounded: Vec<bool> = (0..n)
        .map(|i| geo.statics.iter().any(|s| touches(&geo.aabb[i], s)))
        .collect();
    // Loads, top down: a body carries itself and its share of everything resting on it.
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| top(&geo.aabb[b]).total_cmp(&top(&geo.aabb[a])));
    let mut load = geo.mass.clone();
    // Sag accumulated from a body down to the ground, and bodies in its column below it.
    for &i in &order {
        let m = supports[i].len() + usize::from(grounded[i]);
        if m == 0 {
            continue;
        }
        let share = load[i] / m as f64;
        for &j in &supports[i] {
            load[j] += share;
        }
    }
    let dyn_settle = settle(geo.g, CONTACT_HZ);
    let allowed = ALLOWED_ERROR * plan.length_unit;
    // Depth of each resting contact (upper on lower), and the sag below each body.
    let mut below_sag = vec![0.0f64; n];
    let mut below_count = vec![0usize; n];
    // Bottom up: a body's sag is its deepest support's sag plus its own contact.
    for &i in order.iter().rev() {
        let m = supports[i].len() + usize::from(grounded[i]);
        if m == 0 {
            continue;
        }
        let share = load[i] / m as f64;
        let mut sag = if grounded[i] {
            share / geo.mass[i] * settle(geo.g, STATIC_CONTACT_HZ)
        } else {
            0.0
        };
        let mut count = 0;
        for &j in &supports[i] {
            let (mi, mj) = (geo.mass[i], geo.mass[j]);
            let reduced = mi * mj / (mi + mj);
            let depth = share / reduced * dyn_settle;
            let (upper, lower) = (&scene.bodies[i].name, &scene.bodies[j].name);
            let ratio = share / mj;
            if depth > CRUSH_FRACTION * geo.half[j] {
                out.push(Finding {
                    severity: Severity::Refuse,
                    body: Some(lower.clone()),
                    field: "material",
                    message: format!(
                        "`{lower}` carries {ratio:.3e} times its own mass (`{upper}` rests on it): \
                         the solver's soft contacts ({CONTACT_HZ} Hz) would sink it about {} m \
                         into `{lower}`, more than half its thickness, and crush it; no preset \
                         changes the contact stiffness: make `{lower}` denser or `{upper}` lighter \
                         (below {:.0}× its mass)",
                        fmt_len(depth),
                        CRUSH_FRACTION * geo.half[j] / dyn_settle
                    ),
                });
            } else if depth > allowed && mi > mj {
                // Heavy on light only: equal bodies in a stack are the stack's finding.
                out.push(Finding {
                    severity: Severity::Warn,
                    body: Some(upper.clone()),
                    field: "material",
                    message: format!(
                        "`{upper}` rests on `{lower}` with {ratio:.3e} times its mass on it: the \
                         solver's soft contacts ({CONTACT_HZ} Hz) settle it about {} m inside \
                         `{lower}` (more than the {} m rapier allows); no preset changes that",
                        fmt_len(depth),
                        fmt_len(allowed)
                    ),
                });
            }
            if below_sag[j] + depth > sag {
                sag = below_sag[j] + depth;
                count = below_count[j] + 1;
            }
        }
        below_sag[i] = sag;
        below_count[i] = count;
    }
    // The stacks: bodies nothing rests on, with a column below them. One finding each for the
    // worst stack (a scene of many columns, like the tower, would otherwise repeat itself).
    let mut carries = vec![false; n];
    for &j in supports.iter().flatten() {
        carries[j] = true;
    }
    let tops: Vec<usize> = (0..n)
        .filter(|&i| below_count[i] > 0 && !carries[i])
        .collect();
    let others = |count: usize| match count {
        0 => String::new(),
        1 => " (and 1 other stack)".to_owned(),
        c => format!(" (and {c} other stacks)"),
    };
    let sagging: Vec<usize> = tops
        .iter()
        .copied()
        .filter(|&i| below_sag[i] > STACK_SAG)
        .collect();
    if let Some(&i) = sagging
        .iter()
        .max_by(|&&a, &&b| below_sag[a].total_cmp(&below_sag[b]))
    {
        let name = &scene.bodies[i].name;
        out.push(Finding {
            severity: Severity::Warn,
            body: Some(name.clone()),
            field: "position",
            message: format!(
                "the stack under `{name}` ({} bodies){} sags about {} m under its own weight: the \
                 solver's contacts are soft springs ({CONTACT_HZ} Hz) whatever the preset \
                 (measured: 23 mm for 10 boxes, 0.67 m for 50)",
                below_count[i] + 1,
                others(sagging.len() - 1),
                fmt_len(below_sag[i])
            ),
        });
    }
    let leaning: Vec<usize> = tops
        .iter()
        .copied()
        .filter(|&i| below_count[i] + 1 > DRAFT_STACK)
        .collect();
    if plan.substeps < 4
        && let Some(&i) = leaning.iter().max_by_key(|&&i| below_count[i])
    {
        let name = &scene.bodies[i].name;
        out.push(Finding {
            severity: Severity::Warn,
            body: Some(name.clone()),
            field: "settings.sim",
            message: format!(
                "the stack under `{name}` is {} bodies tall{} and {} substep{} lean it (measured \
                 at draft: 2.5 cm for 10 boxes, 14 cm for 50): use standard or final",
                below_count[i] + 1,
                others(leaning.len() - 1),
                plan.substeps,
                if plan.substeps == 1 { "" } else { "s" }
            ),
        });
    }
}

/// The conservative check: any two bodies could end up one on the other. Warns when the
/// heaviest resting on the lightest would crush it (the resting-contact check refuses what
/// already rests so at the start).
fn mass_ratio(scene: &Scene, geo: &Geometry, out: &mut Vec<Finding>) {
    if geo.up.is_none() || scene.bodies.len() < 2 {
        return;
    }
    let by_mass = |a: &usize, b: &usize| geo.mass[*a].total_cmp(&geo.mass[*b]);
    let (Some(light), Some(heavy)) = (
        (0..scene.bodies.len()).min_by(by_mass),
        (0..scene.bodies.len()).max_by(by_mass),
    ) else {
        return;
    };
    let ratio = geo.mass[heavy] / geo.mass[light];
    let depth = (ratio + 1.0) * settle(geo.g, CONTACT_HZ);
    if depth > CRUSH_FRACTION * geo.half[light] {
        let (h, l) = (&scene.bodies[heavy].name, &scene.bodies[light].name);
        let limit = CRUSH_FRACTION * geo.half[light] / settle(geo.g, CONTACT_HZ) - 1.0;
        out.push(Finding {
            severity: Severity::Warn,
            body: Some(l.clone()),
            field: "material",
            message: format!(
                "mass ratio {ratio:.0e} between `{h}` and `{l}` exceeds {limit:.0e}: if `{h}` comes \
                 to rest on `{l}`, the solver's soft contacts ({CONTACT_HZ} Hz) sink it about {} m \
                 in and crush `{l}` (measured: a 0.2 m box crushed from 300×, at every preset; \
                 more iterations do not help)",
                fmt_len(depth)
            ),
        });
    }
}

/// Small bodies against the resting penetration (69 µm, whatever the length unit), and bodies
/// so far from the origin that f32 cannot place them to 1 % of their size.
fn sizes(scene: &Scene, geo: &Geometry, out: &mut Vec<Finding>) {
    if geo.up.is_none() {
        return;
    }
    let sink = settle(geo.g, STATIC_CONTACT_HZ);
    for (i, b) in scene.bodies.iter().enumerate() {
        let size = 2.0 * geo.half[i];
        let fraction = sink / size;
        let severity = if fraction > SINK_REFUSE_FRACTION {
            Severity::Refuse
        } else if fraction > SINK_FRACTION {
            Severity::Warn
        } else {
            continue;
        };
        out.push(Finding {
            severity,
            body: Some(b.name.clone()),
            field: "size",
            message: format!(
                "`{}` is {} m thick: resting on anything fixed, the solver's soft contacts \
                 ({STATIC_CONTACT_HZ} Hz) hold it {} m inside ({:.1} % of its size; measured \
                 6.9 % for a 1 mm box); the length unit does not change that; scale the scene up",
                b.name,
                fmt_len(size),
                fmt_len(sink),
                100.0 * fraction
            ),
        });
    }
    for (i, b) in scene.bodies.iter().enumerate() {
        let far = b.position.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        let quantum = far * F32_EPSILON;
        if quantum > SINK_FRACTION * geo.half[i] {
            out.push(Finding {
                severity: Severity::Warn,
                body: Some(b.name.clone()),
                field: "position",
                message: format!(
                    "`{}` is {} m from the origin, where the simulator's f32 positions step by \
                     {} m, more than 1 % of its half-thickness: move the scene to the origin",
                    b.name,
                    fmt_len(far),
                    fmt_len(quantum)
                ),
            });
        }
    }
}

/// Speeds against the tunnelling measured with CCD on, CCD switched off where a body can
/// tunnel, and a speed cap below what the scene's bodies can reach.
fn speeds(scene: &Scene, plan: &SimPlan, out: &mut Vec<Finding>) {
    if scene.bodies.is_empty() {
        return;
    }
    let dt = scene.settings.dt;
    let bound = speed_bound(scene);
    // The thinnest static a body could hit (planes and meshes: no thickness to pass through
    // in the measurement's sense; they get the thick-wall limit).
    let wall = scene
        .statics
        .iter()
        .flat_map(|s| s.shape.placed_parts(s.material))
        .filter(|p| !matches!(p.shape, Shape::Plane { .. } | Shape::TriMesh { .. }))
        .map(|p| 2.0 * p.shape.min_half_thickness())
        .fold(f64::INFINITY, f64::min);
    let fastest = scene
        .bodies
        .iter()
        .max_by(|a, b| norm(a.linvel).total_cmp(&norm(b.linvel)));
    let travel = bound * dt;
    let limit = max_travel_per_step(wall);
    // Without statics there is no wall to pass through (the measurement was against one; and
    // the bound of a scene without a floor grows with its end time).
    if travel > limit
        && !scene.statics.is_empty()
        && let Some(b) = fastest
    {
        out.push(Finding {
            severity: Severity::Refuse,
            body: Some(b.name.clone()),
            field: "linvel",
            message: format!(
                "bodies here can reach {bound:.0} m/s ({} m per step of {dt:.4} s): beyond {} m \
                 per step, bodies passed through {}walls even with CCD (measured: a 0.1 m wall \
                 at 900 m/s); lower the speed or the time step",
                fmt_len(travel),
                fmt_len(limit),
                if wall.is_finite() {
                    format!("{} m ", fmt_len(wall))
                } else {
                    String::new()
                }
            ),
        });
    }
    if plan.max_speed < bound {
        out.push(Finding {
            severity: Severity::Warn,
            body: fastest.map(|b| b.name.clone()),
            field: "settings.max_speed",
            message: format!(
                "the solver caps speeds at {:.0} m/s but bodies here can reach {bound:.0} m/s: \
                 faster bodies are slowed without a word; raise max_speed or leave it unset",
                plan.max_speed
            ),
        });
    }
    if plan.ccd_policy == CcdPolicy::Off {
        let can_tunnel = ccd_bodies(scene);
        if let Some((b, _)) = scene.bodies.iter().zip(&can_tunnel).find(|(_, t)| **t) {
            let n = can_tunnel.iter().filter(|t| **t).count();
            out.push(Finding {
                severity: Severity::Warn,
                body: Some(b.name.clone()),
                field: "settings.ccd",
                message: format!(
                    "ccd = \"off\" but {n} bod{} can move further than {} half-thickness in one \
                     step (`{}` first) and may pass through what it hits: use ccd = \"auto\"",
                    if n == 1 { "y" } else { "ies" },
                    if n == 1 { "its" } else { "their" },
                    b.name
                ),
            });
        }
    }
}

/// Long-lived bounces show the solver's loss per bounce.
fn restitution(scene: &Scene, plan: &SimPlan, out: &mut Vec<Finding>) {
    let loss = match plan.substeps {
        0..=1 => 3.6,
        2..=7 => 1.1,
        _ => 0.9,
    };
    for b in &scene.bodies {
        let e = scene.materials[b.material].restitution;
        if e >= BOUNCY {
            out.push(Finding {
                severity: Severity::Warn,
                body: Some(b.name.clone()),
                field: "material",
                message: format!(
                    "`{}` has restitution {e}: the solver loses about {loss} % of the rebound \
                     height per bounce beyond e² at {} substeps (measured at e = 1: at rest \
                     within 60 s at standard); do not expect bounces to last",
                    b.name, plan.substeps
                ),
            });
        }
    }
}

/// Joints between bodies of very different masses: rapier's joints are stiff springs solved
/// per substep, and a heavy body on a light one pulls them apart. Measured (a 0.4 kg arm hung
/// from the world, a weight on its end, largest stretch over 5 s): 10× — 2.4 cm at draft,
/// 3 mm at standard and final; 1000× — 1.85 m at draft, 13 cm at standard, 2.1 cm at final;
/// 1e5× — 95 m, 9.9 m and 1.6 m (the joint fails at every preset).
fn joints(scene: &Scene, plan: &SimPlan, geo: &Geometry, out: &mut Vec<Finding>) {
    use mwb_core::scene::BodyRef;
    let final_substeps = SimPreset::Final.apply(&scene.settings).solver_iterations;
    for j in &scene.joints {
        let (BodyRef::Body(a), BodyRef::Body(b)) = (j.body1, j.body2) else {
            continue;
        };
        let ratio = (geo.mass[a] / geo.mass[b]).max(geo.mass[b] / geo.mass[a]);
        let (severity, advice) = if ratio > JOINT_REFUSE_RATIO {
            (
                Severity::Refuse,
                "the joint comes apart at every preset (measured 1e5×: 9.9 m at standard, 1.6 m \
                 at final): make the masses closer"
                    .to_owned(),
            )
        } else if ratio > JOINT_RATIO && plan.substeps < JOINT_SUBSTEPS {
            (
                Severity::Warn,
                format!(
                    "at {} substeps the joint stretches (measured 1000×: 13 cm at standard, 2 cm \
                     at final): use final ({final_substeps} substeps)",
                    plan.substeps
                ),
            )
        } else if ratio > JOINT_FINAL_RATIO {
            (
                Severity::Warn,
                format!(
                    "even at {} substeps the joint stretches (measured 1000×: 2 cm at final): \
                     make the masses closer",
                    plan.substeps
                ),
            )
        } else {
            continue;
        };
        out.push(Finding {
            severity,
            body: Some(j.name.clone()),
            field: "settings.sim",
            message: format!(
                "joint `{}` joins bodies whose masses differ {ratio:.0}×: {advice}",
                j.name
            ),
        });
    }
}

/// Mass ratio across a joint above which fewer than [`JOINT_SUBSTEPS`] substeps let it stretch
/// (more than 1 cm: 10× held within 3 mm at standard, 1000× stretched 13 cm).
pub const JOINT_RATIO: f64 = 100.0;
/// Substeps from which such joints hold (final: 2 cm at 1000×).
pub const JOINT_SUBSTEPS: u32 = 8;
/// Mass ratio across a joint above which even final stretches it by more than 1 cm.
pub const JOINT_FINAL_RATIO: f64 = 1000.0;
/// Mass ratio across a joint above which it comes apart at every preset (1e5× measured).
pub const JOINT_REFUSE_RATIO: f64 = 1e4;

fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

/// A length for a message: three significant digits.
fn fmt_len(x: f64) -> String {
    if x == 0.0 || !x.is_finite() {
        return format!("{x}");
    }
    let digits = (2 - x.abs().log10().floor() as i32).max(0) as usize;
    format!("{x:.digits$}")
}

/// The volume of a dynamic shape (m³). Convex hulls: the volume of their points' bounding box
/// times 1/2 (a hull fills between a sixth and all of its box; mass here only ranks bodies).
fn volume(shape: &Shape) -> f64 {
    use std::f64::consts::PI;
    match shape {
        Shape::Box { half_extents: h } => 8.0 * h[0] * h[1] * h[2],
        Shape::Sphere { radius: r } => 4.0 / 3.0 * PI * r * r * r,
        Shape::Capsule {
            half_height,
            radius: r,
        } => PI * r * r * (2.0 * half_height + 4.0 / 3.0 * r),
        Shape::Cylinder {
            half_height,
            radius: r,
        } => PI * r * r * 2.0 * half_height,
        Shape::ConvexHull { points } => {
            let (lo, hi) = points_box(points.iter().copied());
            0.5 * (0..3).map(|k| (hi[k] - lo[k]).max(0.0)).product::<f64>()
        }
        Shape::Compound { parts } => parts.iter().map(|p| volume(&p.shape)).sum(),
        Shape::Plane { .. } | Shape::TriMesh { .. } => 0.0,
    }
}

fn points_box(points: impl Iterator<Item = [f64; 3]>) -> ([f64; 3], [f64; 3]) {
    points.fold(
        ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]),
        |(lo, hi), p| {
            (
                [0, 1, 2].map(|k| lo[k].min(p[k])),
                [0, 1, 2].map(|k| hi[k].max(p[k])),
            )
        },
    )
}

fn mul(a: [f64; 4], b: [f64; 4]) -> [f64; 4] {
    let [ax, ay, az, aw] = a;
    let [bx, by, bz, bw] = b;
    [
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ]
}

/// The world-axis bounding box of a shape at a pose.
fn aabb(shape: &Shape, position: [f64; 3], rotation: [f64; 4]) -> ([f64; 3], [f64; 3]) {
    let corners = |h: [f64; 3]| {
        (0..8).map(move |c| {
            let local = [0, 1, 2].map(|k| if c >> k & 1 == 1 { h[k] } else { -h[k] });
            let r = rotate_vector(rotation, local);
            [0, 1, 2].map(|k| position[k] + r[k])
        })
    };
    match shape {
        Shape::Box { half_extents } => points_box(corners(*half_extents)),
        Shape::Sphere { radius } => (position.map(|p| p - radius), position.map(|p| p + radius)),
        Shape::Capsule {
            half_height,
            radius,
        } => {
            let a = rotate_vector(rotation, [0.0, *half_height, 0.0]);
            let lo = [0, 1, 2].map(|k| position[k] - a[k].abs() - radius);
            let hi = [0, 1, 2].map(|k| position[k] + a[k].abs() + radius);
            (lo, hi)
        }
        Shape::Cylinder {
            half_height,
            radius,
        } => points_box(corners([*radius, *half_height, *radius])),
        Shape::ConvexHull { points }
        | Shape::TriMesh {
            vertices: points, ..
        } => points_box(points.iter().map(|p| {
            let r = rotate_vector(rotation, *p);
            [0, 1, 2].map(|k| position[k] + r[k])
        })),
        Shape::Compound { parts } => parts.iter().fold(
            ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]),
            |(lo, hi), p| {
                let r = rotate_vector(rotation, p.position);
                let at = [0, 1, 2].map(|k| position[k] + r[k]);
                let (a, b) = aabb(&p.shape, at, mul(rotation, p.rotation));
                (
                    [0, 1, 2].map(|k| lo[k].min(a[k])),
                    [0, 1, 2].map(|k| hi[k].max(b[k])),
                )
            },
        ),
        Shape::Plane { .. } => ([f64::NEG_INFINITY; 3], [f64::INFINITY; 3]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mwb_core::scene::SceneTemplate;

    fn scene(text: &str) -> Scene {
        SceneTemplate::parse(text, "t.toml")
            .unwrap_or_else(|e| panic!("{e}"))
            .instantiate(0)
    }

    fn with(settings: &str, bodies: &str) -> Scene {
        scene(&format!(
            "name = \"t\"\n[settings]\n{settings}\n\n[[material]]\nname = \"m\"\n\n\
             [[static]]\nname = \"ground\"\nshape = \"plane\"\nmaterial = \"m\"\n\n{bodies}"
        ))
    }

    fn two_boxes(lower_density: f64, upper_density: f64) -> Scene {
        with(
            "",
            &format!(
                "[[material]]\nname = \"lo\"\ndensity = {lower_density}\n\
                 [[material]]\nname = \"hi\"\ndensity = {upper_density}\n\
                 [[body]]\nname = \"cup\"\nshape = \"box\"\nsize = [0.2, 0.2, 0.2]\nmaterial = \"lo\"\nposition = [0, 0.1, 0]\n\
                 [[body]]\nname = \"anvil\"\nshape = \"box\"\nsize = [0.2, 0.2, 0.2]\nmaterial = \"hi\"\nposition = [0, 0.3, 0]\n"
            ),
        )
    }

    fn find<'a>(f: &'a [Finding], field: &str, severity: Severity) -> Option<&'a Finding> {
        f.iter()
            .find(|x| x.field == field && x.severity == severity)
    }

    #[test]
    fn an_everyday_scene_has_no_findings() {
        let f = check(&two_boxes(1000.0, 1000.0));
        assert!(f.is_empty(), "{f:#?}");
    }

    #[test]
    fn heavy_on_light_is_refused_light_on_heavy_is_not() {
        let f = check(&two_boxes(1.0, 1e4));
        let refusal = find(&f, "material", Severity::Refuse).unwrap_or_else(|| panic!("{f:#?}"));
        assert_eq!(refusal.body.as_deref(), Some("cup"));
        assert!(refusal.message.contains("`anvil`"), "{}", refusal.message);
        assert!(refuses(&f));
        // 100×: measured 27 mm of overlap, the box held: a warning.
        let f = check(&two_boxes(10.0, 1000.0));
        assert!(!refuses(&f), "{f:#?}");
        assert!(find(&f, "material", Severity::Warn).is_some(), "{f:#?}");
        // 10×: 3 mm, inside rapier's 5 mm.
        let f = check(&two_boxes(100.0, 1000.0));
        assert!(f.is_empty(), "{f:#?}");
        // Light on heavy: nothing at rest is in trouble, but the pair could swap.
        let f = check(&two_boxes(1e4, 1.0));
        assert!(!refuses(&f), "{f:#?}");
        let w = find(&f, "material", Severity::Warn).unwrap_or_else(|| panic!("{f:#?}"));
        assert!(
            w.message
                .starts_with("mass ratio 1e4 between `cup` and `anvil`"),
            "{}",
            w.message
        );
    }

    fn stack(n: usize, sim: &str) -> Scene {
        with(
            &format!("sim = \"{sim}\""),
            &format!(
                "[[body]]\nname = \"b\"\nshape = \"box\"\nsize = [0.2, 0.2, 0.2]\nmaterial = \"m\"\n\
                 position = [0, 0.1, 0]\nrow = {{ count = {n}, spacing = [0, 0.2, 0] }}\n"
            ),
        )
    }

    #[test]
    fn tall_stacks_sag_and_lean_at_draft() {
        // 5 boxes: 20 · 0.28 mm = 5.5 mm of sag, under the 1 cm; no finding.
        assert!(check(&stack(5, "standard")).is_empty());
        let f = check(&stack(10, "standard"));
        let sag = find(&f, "position", Severity::Warn).unwrap_or_else(|| panic!("{f:#?}"));
        assert_eq!(sag.body.as_deref(), Some("b[9]"));
        assert!(sag.message.contains("(10 bodies)"), "{}", sag.message);
        // 2 · (1 + … + 9) · g/(2π·30)² + 10 · g/(2π·60)² = 25.5 mm; measured 23.4 mm.
        assert!(sag.message.contains("0.0255"), "{}", sag.message);
        assert!(find(&f, "settings.sim", Severity::Warn).is_none());
        let f = check(&stack(50, "draft"));
        assert!(find(&f, "settings.sim", Severity::Warn).is_some(), "{f:#?}");
        assert!(!refuses(&f));
    }

    #[test]
    fn a_hundred_thousand_bodies_are_checked_quickly() {
        // 50 000 grains in 500 columns of 100: the sweep finds every column without n² pairs
        // (n² would be 2.5e9 touch tests).
        let s = with(
            "",
            "[[body]]\nname = \"g\"\nshape = \"box\"\nsize = [0.02, 0.02, 0.02]\nmaterial = \"m\"\n\
             position = [0, 0.01, 0]\ngrid = { count = [50, 100, 10], spacing = [0.03, 0.02, 0.03] }\n",
        );
        assert_eq!(s.bodies.len(), 50_000);
        let f = check(&s);
        let sag = find(&f, "position", Severity::Warn).unwrap_or_else(|| panic!("{f:#?}"));
        assert!(
            sag.message.contains("(100 bodies) (and 499 other stacks)"),
            "{}",
            sag.message
        );
    }

    #[test]
    fn tiny_bodies_warn_and_microscopic_ones_are_refused() {
        let body = |size: f64| {
            with(
                "",
                &format!(
                    "[[body]]\nname = \"grain\"\nshape = \"box\"\nsize = [{size}, {size}, {size}]\n\
                     material = \"m\"\nposition = [0, {}, 0]\n",
                    size / 2.0
                ),
            )
        };
        assert!(check(&body(0.01)).is_empty());
        let f = check(&body(0.001));
        let w = find(&f, "size", Severity::Warn).unwrap_or_else(|| panic!("{f:#?}"));
        assert!(w.message.contains("6.9 %"), "{}", w.message);
        assert!(refuses(&check(&body(0.0002))));
    }

    #[test]
    fn far_from_the_origin_warns() {
        let f = check(&with(
            "",
            "[[body]]\nname = \"far\"\nshape = \"sphere\"\nradius = 0.1\nmaterial = \"m\"\n\
             position = [1e6, 0.1, 0]\n",
        ));
        assert!(find(&f, "position", Severity::Warn).is_some(), "{f:#?}");
    }

    fn ball_at_wall(v: f64, settings: &str) -> Scene {
        scene(&format!(
            "name = \"t\"\n[settings]\n{settings}\n[[material]]\nname = \"m\"\n\
             [[static]]\nname = \"wall\"\nshape = \"box\"\nsize = [0.1, 2, 2]\nmaterial = \"m\"\nposition = [5, 1, 0]\n\
             [[body]]\nname = \"bullet\"\nshape = \"sphere\"\nradius = 0.05\nmaterial = \"m\"\n\
             position = [0, 1, 0]\nlinvel = [{v}, 0, 0]\n"
        ))
    }

    #[test]
    fn speeds_beyond_the_measured_tunnelling_are_refused() {
        // 800 m/s reached no further than the wall (6.7 m per step); 900 went through.
        assert!(!refuses(&check(&ball_at_wall(700.0, "alpha = 0"))));
        let f = check(&ball_at_wall(1000.0, "alpha = 0"));
        let r = find(&f, "linvel", Severity::Refuse).unwrap_or_else(|| panic!("{f:#?}"));
        assert_eq!(r.body.as_deref(), Some("bullet"));
        // The perturbation margin (α) counts: 700 m/s with α = 0.1 is 770.
        assert!(!refuses(&check(&ball_at_wall(650.0, ""))));
    }

    #[test]
    fn free_fall_without_statics_is_not_refused() {
        // 1000 s without a floor: the speed bound is g · t = 9810 m/s, but nothing to hit.
        let f = check(&scene(
            "name = \"t\"\n[settings]\nend_time = 1000\n[[material]]\nname = \"m\"\n\
             [[body]]\nname = \"b\"\nshape = \"sphere\"\nradius = 0.1\nmaterial = \"m\"\n",
        ));
        assert!(!refuses(&f), "{f:#?}");
    }

    #[test]
    fn a_speed_cap_below_the_scene_and_ccd_off_warn() {
        let f = check(&ball_at_wall(300.0, "max_speed = 100"));
        let w = find(&f, "settings.max_speed", Severity::Warn).unwrap_or_else(|| panic!("{f:#?}"));
        assert!(
            w.message.starts_with("the solver caps speeds at 100 m/s"),
            "{}",
            w.message
        );
        let f = check(&ball_at_wall(300.0, "ccd = \"off\""));
        assert!(find(&f, "settings.ccd", Severity::Warn).is_some(), "{f:#?}");
        assert!(check(&ball_at_wall(300.0, "")).is_empty());
    }

    #[test]
    fn a_large_length_unit_keeps_the_sleep_speed() {
        // rapier scales its 0.05 m/s sleep threshold by the length unit (5 m/s at 100 froze a
        // box let go from rest in mid-air); the plan keeps 0.05 m/s, so nothing is flagged.
        let b = "[[body]]\nname = \"b\"\nshape = \"box\"\nsize = [1, 1, 1]\nmaterial = \"m\"\nposition = [0, 5, 0]\n";
        let s = with("length_unit = 100", b);
        assert_eq!(SimPlan::of(&s).sleep_speed, crate::plan::SLEEP_SPEED);
        assert!(check(&s).is_empty(), "{:#?}", check(&s));
        assert_eq!(
            SimPlan::of(&with("length_unit = 0.01", b)).sleep_speed,
            crate::plan::SLEEP_SPEED * 0.01
        );
    }

    #[test]
    fn bouncy_bodies_warn() {
        let f = check(&with(
            "",
            "[[material]]\nname = \"super\"\nrestitution = 1\n\
             [[body]]\nname = \"ball\"\nshape = \"sphere\"\nradius = 0.1\nmaterial = \"super\"\nposition = [0, 1, 0]\n",
        ));
        let w = find(&f, "material", Severity::Warn).unwrap_or_else(|| panic!("{f:#?}"));
        assert!(w.message.contains("1.1 %"), "{}", w.message);
    }

    #[test]
    fn unequal_masses_on_a_joint_warn_below_final() {
        let text = |sim: &str| {
            format!(
                "name = \"t\"\n[settings]\nsim = \"{sim}\"\n[[material]]\nname = \"m\"\n\
                 [[material]]\nname = \"lead\"\ndensity = 50000\n\
                 [[body]]\nname = \"arm\"\nshape = \"box\"\nsize = [0.02, 1, 0.02]\nmaterial = \"m\"\nposition = [0, 1.5, 0]\n\
                 [[body]]\nname = \"weight\"\nshape = \"sphere\"\nradius = 0.1\nmaterial = \"lead\"\nposition = [0, 0.9, 0]\n\
                 [[joint]]\nname = \"elbow\"\nkind = \"spherical\"\nbody1 = \"arm\"\nbody2 = \"weight\"\n\
                 anchor1 = [0, -0.5, 0]\nanchor2 = [0, 0.1, 0]\n"
            )
        };
        let f = check(&scene(&text("standard")));
        let w = find(&f, "settings.sim", Severity::Warn).unwrap_or_else(|| panic!("{f:#?}"));
        assert_eq!(w.body.as_deref(), Some("elbow"));
        assert!(
            find(
                &check(&scene(&text("final"))),
                "settings.sim",
                Severity::Warn
            )
            .is_none()
        );
    }
}
