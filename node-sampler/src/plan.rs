//! What the simulator will do for a scene, and what it leaves out because the scene does not need
//! it (issue 19: "model only what a scene requires", made visible). Pure: from the scene alone,
//! so the plan printed by `mwb scene`, recorded in a job and carried by every world
//! (`WorldDone.sim`) is the one the samplers build.
//!
//! The preset ([`SimPreset`], `core`) sets substeps, iterations, the CCD policy and sleeping;
//! this module adds the decisions that follow from the scene's own bodies:
//!
//! * **CCD** only on bodies that can tunnel under the `auto` policy ([`ccd_bodies`]);
//! * **gyroscopic terms** off on bodies whose inertia is the same about every axis (spheres,
//!   cubes): for them `ω × Iω` is zero, so the term costs time and changes nothing;
//! * the solver's **length unit**: rapier's tolerances (5 mm allowed penetration, 2 cm contact
//!   margin, the speed cap) are absolute; a scene of millimetre or kilometre bodies gets them
//!   scaled to its size (the nearest power of ten of its median body), everyday scenes keep 1;
//! * the **speed cap**: rapier clamps every body at 400 m/s by default; a scene whose bodies can
//!   go faster gets a cap twice its bound, so nothing is clamped silently.

use mwb_core::scene::{CcdPolicy, Scene, Shape, SimPreset};

use crate::world::{ccd_bodies, speed_bound};

/// rapier's contact margin (m, at length unit 1: 4× its 5 mm allowed penetration).
pub const DEFAULT_PREDICTION: f64 = 0.02;
/// The largest margin the plan derives (m, at length unit 1): a wider one makes contacts
/// between bodies that are far apart, which costs solver time and buys nothing.
pub const MAX_PREDICTION: f64 = 0.1;

/// rapier's default sleep threshold (m/s, at length unit 1).
pub const SLEEP_SPEED: f64 = 0.05;

/// rapier's default speed cap (m/s, at length unit 1).
pub const DEFAULT_MAX_SPEED: f64 = 400.0;

/// The simulation plan of a scene.
#[derive(Debug, Clone, PartialEq)]
pub struct SimPlan {
    pub preset: SimPreset,
    /// Substeps per frame (rapier's `num_solver_iterations`).
    pub substeps: u32,
    /// Solver iterations per substep.
    pub iterations: u32,
    /// Stabilisation iterations per substep.
    pub stabilization: u32,
    pub ccd_policy: CcdPolicy,
    /// Per body: continuous collision detection on.
    pub ccd: Vec<bool>,
    /// Per body: gyroscopic terms on.
    pub gyroscopic: Vec<bool>,
    pub sleep: bool,
    /// Speed (m/s) under which a body may fall asleep: rapier's 0.05 m/s, which it scales by
    /// the length unit; for a unit above 1 it is kept at 0.05 m/s (at 100, 5 m/s froze a box
    /// let go from rest in mid-air before it was half a second into its fall).
    pub sleep_speed: f64,
    /// Contact margin (m).
    pub prediction_distance: f64,
    /// The solver's length scale (m).
    pub length_unit: f64,
    /// Speed cap (m/s).
    pub max_speed: f64,
    /// The scene's bound on any body's speed (m/s), from its energy (see [`speed_bound`]).
    pub speed_bound: f64,
    /// Whether the scene has joints (the joint solver runs only then).
    pub joints: bool,
}

/// Whether a body's inertia is the same about every axis, so that gyroscopic terms vanish:
/// spheres, cubes, and compounds of nothing else centred at one point are not tried (a
/// compound's inertia is known only once built).
pub fn isotropic(shape: &Shape) -> bool {
    match shape {
        Shape::Sphere { .. } => true,
        Shape::Box { half_extents: h } => h[0] == h[1] && h[1] == h[2],
        _ => false,
    }
}

/// The power of ten nearest a length (m).
fn decade(x: f64) -> f64 {
    10f64.powf(x.log10().round())
}

impl SimPlan {
    /// The plan for `scene` (an instance: its bodies' sizes and speeds are decided).
    pub fn of(scene: &Scene) -> Self {
        let s = &scene.settings;
        let n = scene.bodies.len();
        let ccd = match s.ccd {
            CcdPolicy::Auto => ccd_bodies(scene),
            CcdPolicy::All => vec![true; n],
            CcdPolicy::Off => vec![false; n],
        };
        let length_unit = s.length_unit.unwrap_or_else(|| {
            let mut sizes: Vec<f64> = scene
                .bodies
                .iter()
                .map(|b| 2.0 * b.shape.bounding_radius())
                .filter(|x| x.is_finite() && *x > 0.0)
                .collect();
            sizes.sort_by(f64::total_cmp);
            match sizes.get(sizes.len() / 2) {
                // Everyday sizes (5 cm … 20 m) keep rapier's tuning, and their worlds their bytes.
                Some(&median) if !(0.05..=20.0).contains(&median) => decade(median),
                _ => 1.0,
            }
        });
        let bound = speed_bound(scene);
        let max_speed = s.max_speed.unwrap_or_else(|| {
            let cap = DEFAULT_MAX_SPEED * length_unit;
            if bound.is_finite() && 2.0 * bound > cap {
                2.0 * bound
            } else {
                cap
            }
        });
        Self {
            preset: s.sim,
            substeps: s.solver_iterations.max(1),
            iterations: s.pgs_iterations.max(1),
            stabilization: s.stabilization_iterations.max(1),
            ccd_policy: s.ccd,
            ccd,
            gyroscopic: scene.bodies.iter().map(|b| !isotropic(&b.shape)).collect(),
            sleep: s.sleep,
            sleep_speed: SLEEP_SPEED * length_unit.min(1.0),
            prediction_distance: s.prediction_distance.unwrap_or_else(|| {
                // rapier finds contacts once per step, at the start: a body that covers more
                // than the margin in a step meets the ground or another body already inside it.
                // Tumble's boxes (32 worlds): 4.3 cm deep at final with 2 cm, 2.1 cm with its
                // 10 cm; standard went from 6 to 5 cm for 20 % more time, so only the accuracy
                // presets pay for it (`mwb bench fidelity`).
                // Never under rapier's 2 cm: a body's travel in a step does not shrink with
                // its size (a perturbed 1 mm box at a 20 µm margin ended below the ground in
                // 42 of 167 frames, extremes matrix).
                let base = DEFAULT_PREDICTION * length_unit.max(1.0);
                if matches!(s.sim, SimPreset::Final | SimPreset::Reference) && bound.is_finite() {
                    (bound * s.dt).clamp(base, MAX_PREDICTION * length_unit.max(1.0))
                } else {
                    base
                }
            }),
            length_unit,
            max_speed,
            speed_bound: bound,
            joints: !scene.joints.is_empty(),
        }
    }

    /// One line for people and for `WorldDone.sim`, e.g. "standard: 4 substeps × 1 iteration,
    /// CCD on 2 of 10 bodies (the others cannot tunnel), gyroscopic terms off on 6 round bodies,
    /// sleeping on".
    pub fn describe(&self) -> String {
        let n = self.ccd.len();
        let ccd_on = self.ccd.iter().filter(|c| **c).count();
        let mut parts = vec![format!(
            "{}: {} substep{} x {} iteration{}",
            self.preset,
            self.substeps,
            if self.substeps == 1 { "" } else { "s" },
            self.iterations,
            if self.iterations == 1 { "" } else { "s" },
        )];
        parts.push(match (self.ccd_policy, ccd_on) {
            (CcdPolicy::Off, _) => "CCD off".to_owned(),
            (_, 1) if n == 1 => "CCD on its one body".to_owned(),
            (_, on) if on == n => format!("CCD on all {n} bodies"),
            (_, 0) if n == 1 => "CCD off (its one body cannot tunnel)".to_owned(),
            (_, 0) => format!("CCD off (none of {n} bodies can tunnel)"),
            (_, on) => format!("CCD on {on} of {n} bodies (the others cannot tunnel)"),
        });
        let round = self.gyroscopic.iter().filter(|g| !**g).count();
        if round > 0 {
            parts.push(format!(
                "gyroscopic terms off on {round} round bod{}",
                if round == 1 { "y" } else { "ies" }
            ));
        }
        if !self.joints {
            parts.push("no joint solver".to_owned());
        }
        if (self.prediction_distance - DEFAULT_PREDICTION * self.length_unit.max(1.0)).abs() > 1e-12
        {
            parts.push(format!(
                "contact margin {:.1} cm (its fastest body's step)",
                100.0 * self.prediction_distance
            ));
        }
        parts.push(format!(
            "sleeping {}",
            if self.sleep { "on" } else { "off" }
        ));
        if self.length_unit != 1.0 {
            parts.push(format!("length unit {} m", self.length_unit));
        }
        if self.max_speed != DEFAULT_MAX_SPEED * self.length_unit {
            parts.push(format!("speed cap {:.0} m/s", self.max_speed));
        }
        parts.join(", ")
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

    const BALLS: &str = r#"
name = "t"
[[material]]
name = "m"
[[static]]
name = "floor"
shape = "plane"
normal = [0, 1, 0]
material = "m"
[[body]]
name = "ball"
shape = "sphere"
radius = 0.1
material = "m"
position = [0, 0.3, 0]
[[body]]
name = "brick"
shape = "box"
size = [0.2, 0.1, 0.4]
material = "m"
position = [1, 0.3, 0]
"#;

    #[test]
    fn presets_set_substeps_and_ccd() {
        let standard = SimPlan::of(&scene(BALLS));
        assert_eq!(standard.preset, SimPreset::Standard);
        assert_eq!((standard.substeps, standard.iterations), (4, 1));
        assert_eq!(standard.ccd, vec![false, false]);
        let final_ = SimPlan::of(&scene(&BALLS.replacen(
            "name = \"t\"\n",
            "name = \"t\"\n[settings]\nsim = \"final\"\n",
            1,
        )));
        assert_eq!((final_.substeps, final_.iterations), (8, 2));
        assert_eq!(final_.ccd, vec![true, true]);
        // A key written in the scene wins over its preset.
        let custom = SimPlan::of(&scene(&BALLS.replacen(
            "name = \"t\"\n",
            "name = \"t\"\n[settings]\nsim = \"draft\"\nsolver_iterations = 3\nccd = \"all\"\n",
            1,
        )));
        assert_eq!(custom.preset, SimPreset::Draft);
        assert_eq!((custom.substeps, custom.iterations), (3, 1));
        assert_eq!(custom.ccd, vec![true, true]);
    }

    #[test]
    fn gyroscopic_terms_only_where_inertia_is_not_round() {
        let plan = SimPlan::of(&scene(BALLS));
        assert_eq!(plan.gyroscopic, vec![false, true]);
        let line = plan.describe();
        assert!(
            line.starts_with("standard: 4 substeps x 1 iteration"),
            "{line}"
        );
        assert!(
            line.contains("gyroscopic terms off on 1 round body"),
            "{line}"
        );
        assert!(
            line.contains("CCD off (none of 2 bodies can tunnel)"),
            "{line}"
        );
    }

    #[test]
    fn length_unit_and_speed_cap_follow_the_scene() {
        assert_eq!(SimPlan::of(&scene(BALLS)).length_unit, 1.0);
        let tiny = BALLS
            .replace("radius = 0.1", "radius = 0.0005")
            .replace("size = [0.2, 0.1, 0.4]", "size = [0.001, 0.001, 0.001]");
        let plan = SimPlan::of(&scene(&tiny));
        assert_eq!(plan.length_unit, 0.001);
        assert!(plan.describe().contains("length unit 0.001 m"));
        // 1000 m/s needs a cap above rapier's 400.
        let fast = BALLS.replacen(
            "position = [0, 0.3, 0]",
            "position = [0, 0.3, 0]\nlinvel = [1000, 0, 0]",
            1,
        );
        let plan = SimPlan::of(&scene(&fast));
        assert!(plan.max_speed >= 2000.0, "{}", plan.max_speed);
        assert_eq!(plan.ccd, vec![true, true]);
        // Written values win.
        let set = BALLS.replacen(
            "name = \"t\"\n",
            "name = \"t\"\n[settings]\nlength_unit = 0.5\nmax_speed = 50\n",
            1,
        );
        let plan = SimPlan::of(&scene(&set));
        assert_eq!((plan.length_unit, plan.max_speed), (0.5, 50.0));
    }
}
