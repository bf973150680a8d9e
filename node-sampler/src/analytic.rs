//! The analytic suite (issue 19): scenes with a closed form, simulated as the sampler simulates
//! them, and the error of the simulation against the closed form.
//!
//! Each scene of `scenes/analytic/` (compiled in, [`AnalyticScene::source`]) is built with
//! [`SimWorld::build`] and stepped directly: no §4.1 perturbations (the scenes also set
//! `alpha = 0`, so `run_world` gives the same motion), no recording. What comes out is plain
//! data, one [`AnalyticCase`] per measured quantity, for `mwb bench fidelity` to print per
//! preset and for `tests/analytic.rs` to hold against its tolerances.
//!
//! ```no_run
//! use mwb_core::scene::SimPreset;
//! use mwb_sampler::analytic;
//!
//! for case in analytic::run_suite(SimPreset::Draft)? {
//!     println!("{}: {} = {} {} (closed form {})", case.name, case.quantity, case.measured,
//!         case.unit, case.expected);
//! }
//! # Ok::<(), analytic::AnalyticError>(())
//! ```
//!
//! Tolerances are stated per case where it is measured, with the reason; they follow the scene's
//! settings (a time-discretisation bias shrinks with `dt` and the substeps), so the same case
//! can be judged at every preset. [`AnalyticCase::passes`] compares.

use crate::world::{BuildError, SimWorld};
use mwb_core::scene::{Scene, SceneError, SceneTemplate, SimPreset};
use std::f64::consts::PI;

/// One closed-form quantity, simulated.
#[derive(Debug, Clone, PartialEq)]
pub struct AnalyticCase {
    /// The scene (`scenes/analytic/<name>.toml`).
    pub name: &'static str,
    /// What is measured (`"range"`, `"apex 2"`, `"stop distance"`, …).
    pub quantity: &'static str,
    /// Unit of `expected`, `measured`, `error` and `tolerance`.
    pub unit: &'static str,
    /// The closed form's value.
    pub expected: f64,
    /// The simulation's value.
    pub measured: f64,
    /// `measured − expected` (signed: a negative rest-height error is penetration).
    pub error: f64,
    /// The largest `|error|` the case accepts at these settings (reason at the case).
    pub tolerance: f64,
}

impl AnalyticCase {
    fn new(
        name: &'static str,
        quantity: &'static str,
        unit: &'static str,
        expected: f64,
        measured: f64,
        tolerance: f64,
    ) -> Self {
        Self {
            name,
            quantity,
            unit,
            expected,
            measured,
            error: measured - expected,
            tolerance,
        }
    }

    /// Whether the error is within the tolerance (a non-finite measurement never is).
    pub fn passes(&self) -> bool {
        self.error.is_finite() && self.error.abs() <= self.tolerance
    }

    /// The error relative to the closed form (`|error| / |expected|`; the absolute error when
    /// the closed form is 0).
    pub fn relative_error(&self) -> f64 {
        if self.expected == 0.0 {
            self.error.abs()
        } else {
            self.error.abs() / self.expected.abs()
        }
    }
}

/// Why the suite could not measure a scene.
#[derive(Debug, thiserror::Error)]
pub enum AnalyticError {
    #[error("{scene}: {source}")]
    Scene {
        scene: &'static str,
        /// Boxed: a scene error carries its file, line and message.
        #[source]
        source: Box<SceneError>,
    },
    #[error("{scene}: {source}")]
    Build {
        scene: &'static str,
        #[source]
        source: BuildError,
    },
    /// The scene does not hold what its measurement needs (edited away from the shipped file).
    #[error("{scene}: {what}")]
    Shape { scene: &'static str, what: String },
    /// The simulation never showed the event the quantity is read at.
    #[error("{scene}: {quantity}: {what}")]
    NotObserved {
        scene: &'static str,
        quantity: &'static str,
        what: &'static str,
    },
}

/// The scenes of the suite.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum AnalyticScene {
    /// Range v0² sin 2θ / g and apex v0² sin²θ / 2g.
    Projectile,
    /// Stop distance v0² / 2μg.
    Sliding,
    /// Apex sequence e^{2k} h.
    Bounce,
    /// Rest height of a box on the ground (penetration).
    Rest,
    /// Acceleration g (sin θ − μ cos θ) down a 30° incline.
    Incline,
    /// Rolling speed 5 v0 / 7 of a ball set sliding without spin.
    Rolling,
    /// Period of a compound pendulum on a revolute joint.
    Pendulum,
    /// Drift of a 10-box stack over 60 s.
    Stack,
}

impl AnalyticScene {
    /// Every scene of the suite, in the order of the table in docs/fidelity.md.
    pub const ALL: [AnalyticScene; 8] = [
        AnalyticScene::Projectile,
        AnalyticScene::Sliding,
        AnalyticScene::Bounce,
        AnalyticScene::Rest,
        AnalyticScene::Incline,
        AnalyticScene::Rolling,
        AnalyticScene::Pendulum,
        AnalyticScene::Stack,
    ];

    /// Its name: the file `scenes/analytic/<name>.toml`.
    pub fn name(self) -> &'static str {
        match self {
            AnalyticScene::Projectile => "projectile",
            AnalyticScene::Sliding => "sliding",
            AnalyticScene::Bounce => "bounce",
            AnalyticScene::Rest => "rest",
            AnalyticScene::Incline => "incline",
            AnalyticScene::Rolling => "rolling",
            AnalyticScene::Pendulum => "pendulum",
            AnalyticScene::Stack => "stack",
        }
    }

    /// The scene file's text (compiled in).
    pub fn source(self) -> &'static str {
        match self {
            AnalyticScene::Projectile => include_str!("../../scenes/analytic/projectile.toml"),
            AnalyticScene::Sliding => include_str!("../../scenes/analytic/sliding.toml"),
            AnalyticScene::Bounce => include_str!("../../scenes/analytic/bounce.toml"),
            AnalyticScene::Rest => include_str!("../../scenes/analytic/rest.toml"),
            AnalyticScene::Incline => include_str!("../../scenes/analytic/incline.toml"),
            AnalyticScene::Rolling => include_str!("../../scenes/analytic/rolling.toml"),
            AnalyticScene::Pendulum => include_str!("../../scenes/analytic/pendulum.toml"),
            AnalyticScene::Stack => include_str!("../../scenes/analytic/stack.toml"),
        }
    }

    /// The scene as written (its own `[settings]`, so the preset it names or standard's).
    pub fn scene(self) -> Result<Scene, AnalyticError> {
        let path = format!("scenes/analytic/{}.toml", self.name());
        SceneTemplate::parse(self.source(), &path)
            .map(|t| t.instantiate(0))
            .map_err(|source| AnalyticError::Scene {
                scene: self.name(),
                source: Box::new(source),
            })
    }

    /// Simulates `scene` (this suite's scene, its settings possibly changed: a preset, a time
    /// step) and measures its quantities against their closed forms.
    pub fn measure(self, scene: &Scene) -> Result<Vec<AnalyticCase>, AnalyticError> {
        let mut run = Run::new(self.name(), scene)?;
        match self {
            AnalyticScene::Projectile => projectile(&mut run),
            AnalyticScene::Sliding => sliding(&mut run),
            AnalyticScene::Bounce => bounce(&mut run),
            AnalyticScene::Rest => rest(&mut run),
            AnalyticScene::Incline => incline(&mut run),
            AnalyticScene::Rolling => rolling(&mut run),
            AnalyticScene::Pendulum => pendulum(&mut run),
            AnalyticScene::Stack => stack(&mut run),
        }
    }
}

/// The whole suite at `preset` (applied over each scene's own settings).
pub fn run_suite(preset: SimPreset) -> Result<Vec<AnalyticCase>, AnalyticError> {
    let mut cases = Vec::new();
    for s in AnalyticScene::ALL {
        let mut scene = s.scene()?;
        scene.settings = preset.apply(&scene.settings);
        cases.extend(s.measure(&scene)?);
    }
    Ok(cases)
}

/// One body's state after a step, in `f64` (rapier's `f32`, widened exactly).
#[derive(Debug, Clone, Copy)]
struct State {
    t: f64,
    x: [f64; 3],
    v: [f64; 3],
}

/// A scene being stepped without perturbations.
struct Run<'s> {
    name: &'static str,
    scene: &'s Scene,
    sim: SimWorld,
    steps: u64,
}

impl<'s> Run<'s> {
    fn new(name: &'static str, scene: &'s Scene) -> Result<Self, AnalyticError> {
        let sim = SimWorld::build(scene).map_err(|source| AnalyticError::Build {
            scene: name,
            source,
        })?;
        Ok(Self {
            name,
            scene,
            sim,
            steps: 0,
        })
    }

    fn dt(&self) -> f64 {
        self.scene.settings.dt
    }

    /// Time of one solver substep: rapier's `num_solver_iterations` are TGS substeps, each
    /// integrating `dt / n`, so a discretisation bias of the integrator scales with it.
    fn substep(&self) -> f64 {
        self.dt() / f64::from(self.scene.settings.solver_iterations.max(1))
    }

    fn g(&self) -> f64 {
        let [x, y, z] = self.scene.settings.gravity;
        (x * x + y * y + z * z).sqrt()
    }

    /// Steps in the scene's `end_time`.
    fn max_steps(&self) -> u64 {
        (self.scene.settings.end_time / self.dt()).ceil() as u64
    }

    fn body(&self, name: &str) -> Result<usize, AnalyticError> {
        self.scene
            .body_index(name)
            .ok_or_else(|| AnalyticError::Shape {
                scene: self.name,
                what: format!("no body {name:?}"),
            })
    }

    fn state(&self, i: usize) -> State {
        let rb = &self.sim.world.bodies[self.sim.bodies[i]];
        let w = |v: rapier3d::prelude::Vector| [v.x, v.y, v.z].map(f64::from);
        State {
            t: self.steps as f64 * self.dt(),
            x: w(rb.translation()),
            v: w(rb.linvel()),
        }
    }

    fn step(&mut self) {
        self.sim.world.step();
        self.steps += 1;
    }

    /// Steps to the end, handing `f` body `i`'s state after every step (and before the first);
    /// `f` returns false to stop early.
    fn follow(&mut self, i: usize, mut f: impl FnMut(State) -> bool) {
        if !f(self.state(i)) {
            return;
        }
        while self.steps < self.max_steps() {
            self.step();
            if !f(self.state(i)) {
                return;
            }
        }
    }

    fn not_observed(&self, quantity: &'static str, what: &'static str) -> AnalyticError {
        AnalyticError::NotObserved {
            scene: self.name,
            quantity,
            what,
        }
    }
}

fn sphere_radius(run: &Run<'_>, i: usize) -> Result<f64, AnalyticError> {
    match run.scene.bodies[i].shape {
        mwb_core::scene::Shape::Sphere { radius } => Ok(radius),
        _ => Err(AnalyticError::Shape {
            scene: run.name,
            what: format!("body {:?} is not a sphere", run.scene.bodies[i].name),
        }),
    }
}

fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The gravity direction's opposite (up).
fn up(run: &Run<'_>) -> [f64; 3] {
    let g = run.g();
    run.scene.settings.gravity.map(|x| -x / g)
}

/// Range and apex of a ball in free flight.
///
/// Tolerance: rapier integrates free flight by symplectic Euler per substep h = dt / substeps
/// (its `num_solver_iterations` are TGS substeps, and free bodies are integrated in them too),
/// which puts a body `g·h·t/2` below the parabola at time `t` (`y_n = y0 + v0 t − g t²/2 −
/// g h t/2`). The apex carries that bias at the apex time, the range at the flight time times
/// the horizontal speed over the vertical one; the frame sampling of the apex adds at most
/// `g dt²/8`. And f32: every substep adds `v·h` to an f32 position and rounds it by up to half
/// an ulp, `|x|·2⁻²⁴`, so `N` substeps may drift `N·|x|·2⁻²⁴` (5 mm over the 11 000 substeps of
/// the reference preset's flight; 0.3 mm at standard). The tolerance is 1.5× the substep bias
/// plus the sampling plus that f32 bound. At standard the measured apex error is the bias to
/// 1 %, so a simulator that stopped substepping free bodies fails.
fn projectile(run: &mut Run<'_>) -> Result<Vec<AnalyticCase>, AnalyticError> {
    let i = run.body("ball")?;
    let start = run.state(i);
    let u = up(run);
    let g = run.g();
    let v_up = dot(start.v, u);
    let horizontal = |x: [f64; 3]| {
        let h = [0, 1, 2].map(|k| x[k] - dot(x, u) * u[k]);
        norm(h)
    };
    let v_h = horizontal(start.v);
    let h0 = dot(start.x, u);
    let mut apex = f64::NEG_INFINITY;
    let mut range = None;
    let mut prev = start;
    run.follow(i, |s| {
        let h = dot(s.x, u);
        apex = apex.max(h - h0);
        if s.t > 0.0 && dot(s.v, u) < 0.0 && h < h0 {
            // Back through the launch height: interpolate between the two frames.
            let hp = dot(prev.x, u);
            let f = (hp - h0) / (hp - h);
            let d0 = horizontal([0, 1, 2].map(|k| prev.x[k] - start.x[k]));
            let d1 = horizontal([0, 1, 2].map(|k| s.x[k] - start.x[k]));
            range = Some(d0 + f * (d1 - d0));
            return false;
        }
        prev = s;
        true
    });
    let range = range.ok_or_else(|| run.not_observed("range", "never came back to h0"))?;
    let t_apex = v_up / g;
    let t_flight = 2.0 * t_apex;
    let dt = run.dt();
    let h = run.substep();
    let bias = |t: f64| g * h * t / 2.0;
    // Half an ulp of the largest coordinate reached, per substep flown.
    let f32_drift = |t: f64, x: f64| (t / h).ceil() * x * f64::powi(2.0, -24);
    let reach = norm(start.x) + range.abs() + v_up * v_up / (2.0 * g);
    Ok(vec![
        AnalyticCase::new(
            "projectile",
            "apex",
            "m",
            v_up * v_up / (2.0 * g),
            apex,
            1.5 * bias(t_apex) + g * dt * dt / 8.0 + f32_drift(t_apex, reach),
        ),
        AnalyticCase::new(
            "projectile",
            "range",
            "m",
            2.0 * v_h * v_up / g,
            range,
            1.5 * bias(t_flight) * v_h / v_up + f32_drift(t_flight, reach),
        ),
    ])
}

/// Stop distance of a box sliding on the ground.
///
/// Tolerance: 2 % (the margin our own LCP stepper's test holds, forward.rs) plus the
/// discretisation of the deceleration, `v0·dt/2` (the first step decelerates for a whole step;
/// a box that stops mid-step is seen at the step's end).
fn sliding(run: &mut Run<'_>) -> Result<Vec<AnalyticCase>, AnalyticError> {
    let i = run.body("box")?;
    let start = run.state(i);
    let v0 = norm(start.v);
    let mu = friction(run, i);
    let g = run.g();
    let mut end = start;
    let mut stopped = false;
    run.follow(i, |s| {
        end = s;
        stopped = s.t > 0.0 && norm(s.v) < 1e-3;
        !stopped
    });
    if !stopped {
        return Err(run.not_observed("stop distance", "the box never stopped"));
    }
    let d = norm([0, 1, 2].map(|k| end.x[k] - start.x[k]));
    let expected = v0 * v0 / (2.0 * mu * g);
    Ok(vec![AnalyticCase::new(
        "sliding",
        "stop distance",
        "m",
        expected,
        d,
        0.02 * expected + v0 * run.dt() / 2.0,
    )])
}

/// The friction rapier uses between body `i` and the first static (the average of the two
/// materials': rapier's default combine rule).
fn friction(run: &Run<'_>, i: usize) -> f64 {
    let s = run.scene;
    let body = s.materials[s.bodies[i].material].friction;
    match s.statics.first() {
        Some(st) => 0.5 * (body + s.materials[st.material].friction),
        None => body,
    }
}

fn restitution(run: &Run<'_>, i: usize) -> f64 {
    let s = run.scene;
    let body = s.materials[s.bodies[i].material].restitution;
    match s.statics.first() {
        Some(st) => 0.5 * (body + s.materials[st.material].restitution),
        None => body,
    }
}

/// The first three apexes of a dropped ball: e^{2k} h.
///
/// Tolerance: 3 % of each apex (the margin our own LCP stepper's test holds for the same
/// closed form, forward.rs) plus the frame sampling of an apex, `g dt²/8`. Rapier's contacts are
/// soft (a spring-damper bias on top of the velocity solve) and it applies restitution on the
/// velocity of the substep where the contact is first active, so its rebounds are not exactly
/// e·v; the measured errors are in docs/fidelity.md.
fn bounce(run: &mut Run<'_>) -> Result<Vec<AnalyticCase>, AnalyticError> {
    const QUANTITY: [&str; 3] = ["apex 1", "apex 2", "apex 3"];
    let i = run.body("ball")?;
    let r = sphere_radius(run, i)?;
    let u = up(run);
    let e = restitution(run, i);
    let start = run.state(i);
    let h = dot(start.x, u) - r;
    let mut apexes = Vec::new();
    let mut prev = start;
    run.follow(i, |s| {
        if dot(prev.v, u) > 0.0 && dot(s.v, u) <= 0.0 {
            apexes.push(dot(prev.x, u).max(dot(s.x, u)) - r);
        }
        prev = s;
        apexes.len() < QUANTITY.len()
    });
    let dt = run.dt();
    let g = run.g();
    let mut cases = Vec::new();
    for (k, quantity) in QUANTITY.into_iter().enumerate() {
        let measured = *apexes
            .get(k)
            .ok_or_else(|| run.not_observed(quantity, "fewer bounces than three"))?;
        let expected = e.powi(2 * (k as i32 + 1)) * h;
        cases.push(AnalyticCase::new(
            "bounce",
            quantity,
            "m",
            expected,
            measured,
            0.03 * expected + g * dt * dt / 8.0,
        ));
    }
    Ok(cases)
}

/// Rest height of a box on the ground after `end_time`: the penetration.
///
/// Tolerance: 1 mm, the standard codec bound on stored positions (a penetration below it cannot
/// be told from the recording's own error).
fn rest(run: &mut Run<'_>) -> Result<Vec<AnalyticCase>, AnalyticError> {
    let i = run.body("box")?;
    let u = up(run);
    let start = run.state(i);
    let mut end = start;
    run.follow(i, |s| {
        end = s;
        true
    });
    Ok(vec![AnalyticCase::new(
        "rest",
        "rest height",
        "m",
        dot(start.x, u),
        dot(end.x, u),
        1e-3,
    )])
}

/// Acceleration down a 30° incline, from the velocity between 0.25 s (contact settled) and the
/// end.
///
/// Tolerance: 2 % of `a` (rapier's friction is solved per manifold — its default "simplified"
/// model, one Coulomb constraint per 4 contacts plus a twist — and its contacts are soft, so a
/// sliding box sits slightly in the slope; 2 % is what we ask of our own stepper's sliding).
fn incline(run: &mut Run<'_>) -> Result<Vec<AnalyticCase>, AnalyticError> {
    let i = run.body("box")?;
    let slope = run
        .scene
        .statics
        .iter()
        .find(|s| s.name == "incline")
        .ok_or_else(|| AnalyticError::Shape {
            scene: run.name,
            what: "no static \"incline\"".into(),
        })?;
    // The slab's local x axis, turned by its rotation: the direction up the slope.
    let [qx, qy, qz, qw] = slope.rotation;
    let dir = [
        1.0 - 2.0 * (qy * qy + qz * qz),
        2.0 * (qx * qy + qz * qw),
        2.0 * (qx * qz - qy * qw),
    ];
    let u = up(run);
    let sin = dot(dir, u);
    let theta = sin.clamp(-1.0, 1.0).asin().abs();
    let mu = 0.5
        * (run.scene.materials[run.scene.bodies[i].material].friction
            + run.scene.materials[slope.material].friction);
    let g = run.g();
    let t0 = 0.25;
    let mut first: Option<State> = None;
    let mut last = run.state(i);
    run.follow(i, |s| {
        if first.is_none() && s.t >= t0 - 1e-9 {
            first = Some(s);
        }
        last = s;
        true
    });
    let first = first.ok_or_else(|| run.not_observed("acceleration", "ended before 0.25 s"))?;
    if last.t <= first.t {
        return Err(run.not_observed("acceleration", "ended before 0.25 s"));
    }
    // Down the slope is −dir.
    let a = -(dot(last.v, dir) - dot(first.v, dir)) / (last.t - first.t);
    let expected = g * (theta.sin() - mu * theta.cos());
    Ok(vec![AnalyticCase::new(
        "incline",
        "acceleration",
        "m/s²",
        expected,
        a,
        0.02 * expected,
    )])
}

/// Speed of a ball set sliding without spin, once it rolls: 5 v0 / 7.
///
/// Tolerance: 1 % (once rolling, nothing in the closed form changes it; what is left is the
/// solver's friction converging within the substep and f32).
fn rolling(run: &mut Run<'_>) -> Result<Vec<AnalyticCase>, AnalyticError> {
    let i = run.body("ball")?;
    let start = run.state(i);
    let u = up(run);
    let horizontal = |v: [f64; 3]| norm([0, 1, 2].map(|k| v[k] - dot(v, u) * u[k]));
    let v0 = horizontal(start.v);
    let mut end = start;
    run.follow(i, |s| {
        end = s;
        true
    });
    Ok(vec![AnalyticCase::new(
        "rolling",
        "rolling speed",
        "m/s",
        5.0 * v0 / 7.0,
        horizontal(end.v),
        0.01 * 5.0 * v0 / 7.0,
    )])
}

/// Period of a compound pendulum (a ball of radius r at L from a revolute hinge to the world),
/// from the times of its downward passages through the vertical (interpolated between frames).
///
/// Closed form: `T0 = 2π √((L² + 2/5 r²) / (g L))` (the ball turns with the arm), times
/// `1 + θ0²/16` for the amplitude θ0 (the next term, 11θ0⁴/3072, is 1e-7 at 5°).
/// Tolerance: 0.5 % of T (a period is measured between interpolated crossings, whose timing
/// error is a small fraction of a frame; the joint is solved as a very stiff spring, 1 MHz).
fn pendulum(run: &mut Run<'_>) -> Result<Vec<AnalyticCase>, AnalyticError> {
    let i = run.body("bob")?;
    let r = sphere_radius(run, i)?;
    let joint = run
        .scene
        .joints
        .first()
        .ok_or_else(|| AnalyticError::Shape {
            scene: run.name,
            what: "no joint".into(),
        })?;
    let hinge = joint.anchor1;
    let start = run.state(i);
    let u = up(run);
    let arm = [0, 1, 2].map(|k| start.x[k] - hinge[k]);
    let l = norm(arm);
    let theta0 = (-dot(arm, u) / l).clamp(-1.0, 1.0).acos();
    // The horizontal direction the bob swings along.
    let side = {
        let h = [0, 1, 2].map(|k| arm[k] - dot(arm, u) * u[k]);
        let n = norm(h);
        if n == 0.0 {
            return Err(AnalyticError::Shape {
                scene: run.name,
                what: "the bob starts at rest below the hinge".into(),
            });
        }
        h.map(|x| x / n)
    };
    let g = run.g();
    let mut crossings = Vec::new();
    let mut prev = start;
    run.follow(i, |s| {
        let a = dot([0, 1, 2].map(|k| prev.x[k] - hinge[k]), side);
        let b = dot([0, 1, 2].map(|k| s.x[k] - hinge[k]), side);
        // Passing the vertical in the starting side's negative direction.
        if a > 0.0 && b <= 0.0 {
            crossings.push(prev.t + (s.t - prev.t) * a / (a - b));
        }
        prev = s;
        true
    });
    let (Some(first), Some(last)) = (crossings.first(), crossings.last()) else {
        return Err(run.not_observed("period", "never passed the vertical"));
    };
    if crossings.len() < 2 {
        return Err(run.not_observed("period", "fewer than two passages"));
    }
    let measured = (last - first) / (crossings.len() - 1) as f64;
    let t0 = 2.0 * PI * ((l * l + 0.4 * r * r) / (g * l)).sqrt();
    let expected = t0 * (1.0 + theta0 * theta0 / 16.0);
    Ok(vec![AnalyticCase::new(
        "pendulum",
        "period",
        "s",
        expected,
        measured,
        0.005 * expected,
    )])
}

/// A standing stack over `end_time` (60 s): how far its top box sank (`sag`) and the largest
/// sideways displacement of any box (`lateral drift`). The closed form is 0 for both.
///
/// Tolerance: 1 mm each, the standard codec bound on stored positions. Rapier's contacts are
/// soft springs (30 Hz between two dynamic bodies, 60 Hz against a fixed one; ζ = 10), so a
/// contact under load sits inside by an amount that grows with the load: the boxes near the
/// bottom carry the most, and the stack's sags add up. Sleeping then freezes what is left.
fn stack(run: &mut Run<'_>) -> Result<Vec<AnalyticCase>, AnalyticError> {
    let n = run.scene.bodies.len();
    let u = up(run);
    let start: Vec<State> = (0..n).map(|i| run.state(i)).collect();
    let top = (0..n)
        .max_by(|&a, &b| dot(start[a].x, u).total_cmp(&dot(start[b].x, u)))
        .ok_or_else(|| AnalyticError::Shape {
            scene: run.name,
            what: "no bodies".into(),
        })?;
    while run.steps < run.max_steps() {
        run.step();
    }
    let end: Vec<State> = (0..n).map(|i| run.state(i)).collect();
    let sag = dot(start[top].x, u) - dot(end[top].x, u);
    let lateral = (0..n)
        .map(|i| {
            let d = [0, 1, 2].map(|k| end[i].x[k] - start[i].x[k]);
            norm([0, 1, 2].map(|k| d[k] - dot(d, u) * u[k]))
        })
        .fold(0.0, f64::max);
    Ok(vec![
        AnalyticCase::new("stack", "sag", "m", 0.0, sag, 1e-3),
        AnalyticCase::new("stack", "lateral drift", "m", 0.0, lateral, 1e-3),
    ])
}
