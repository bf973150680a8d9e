//! `mwb bench stepper`: our LCP stepper (`mwb-reverse`, stepping forward) and rapier (the
//! samplers' engine) on the same simple scenes, each against its analytic answer (issue 5).
//!
//! Both engines read the very same scene (the ordinary TOML format): rapier through the
//! sampler's own `run_world_observed` with perturbations off, ours through
//! `mwb_reverse::scene::world_from_scene`, stepped with the scene's `dt`. Both sides of every
//! contact get the same material, so the engines' different combine rules (rapier: average;
//! ours: √(μ₁μ₂) for friction, average for restitution) give the same coefficients.
//!
//! * `box_rest_height`: a 0.4 m box dropped from 1 m comes to rest; its centre should be 0.2 m
//!   above the plane (penetration shows as a lower value).
//! * `ball_bounce_apex`: a ball (r = 0.1 m) dropped with its bottom 1 m above the plane, e = 0.5:
//!   the first rebound's apex (bottom) should reach e²·h = 0.25 m.
//! * `box_slide_distance`: a box resting on the plane pushed at 3 m/s, μ = 0.5: it should stop
//!   after v²/(2μg) = 0.917 m.
//! * `ball_roll_speed`: a ball launched at 2 m/s without spin, μ = 0.5: friction makes it roll
//!   at 5/7 of the launch speed (solid sphere) after 2v/(7μg) = 0.12 s; measured at 1 s. Our
//!   round bodies carry rolling resistance (rows 5.15–5.18), rapier's do not; both are
//!   reported as they are.

use crate::output::{Summary, number};
use anyhow::{Context, Result, bail};
use mwb_core::scene::SceneTemplate;
use mwb_sampler::{PayloadEncoding, RunOptions, run_world_observed};
use std::fmt::Write as _;
use std::ops::ControlFlow;

/// Arguments of `mwb bench stepper`.
#[derive(Debug, Clone, clap::Args)]
pub struct StepperArgs {
    /// Print the result as one JSON line.
    #[arg(long)]
    pub json: bool,
}

/// Runs `mwb bench stepper`.
pub async fn run(args: StepperArgs) -> Result<()> {
    let b = tokio::task::spawn_blocking(measure).await??;
    crate::output::print(&b, args.json)
}

/// One scene, one measured quantity.
#[derive(Debug, Clone, serde::Serialize)]
pub struct StepperCase {
    pub case: &'static str,
    pub unit: &'static str,
    pub analytic: f64,
    pub ours: f64,
    pub rapier: f64,
    /// `ours − analytic` and `rapier − analytic`.
    pub ours_err: f64,
    pub rapier_err: f64,
    pub dt: f64,
}

/// The bench's one JSON line.
#[derive(Debug, Clone, serde::Serialize)]
pub struct StepperBench {
    pub cases: Vec<StepperCase>,
}

impl Summary for StepperBench {
    fn table(&self) -> String {
        let mut t = format!(
            "{:<20} {:<4} {:>9} {:>9} {:>9} {:>11} {:>11}\n",
            "CASE", "UNIT", "ANALYTIC", "OURS", "RAPIER", "OURS ERR", "RAPIER ERR"
        );
        for c in &self.cases {
            let _ = writeln!(
                t,
                "{:<20} {:<4} {:>9} {:>9} {:>9} {:>11} {:>11}",
                c.case,
                c.unit,
                number(c.analytic),
                number(c.ours),
                number(c.rapier),
                number(c.ours_err),
                number(c.rapier_err)
            );
        }
        t
    }
}

const G: f64 = 9.81;

fn scene(settings: &str, body: &str, material: &str) -> String {
    format!(
        r#"name = "stepper-bench"
[settings]
{settings}
[[material]]
name = "m"
{material}
[[static]]
name = "ground"
shape = "plane"
normal = [0, 1, 0]
material = "m"
[[body]]
name = "b"
material = "m"
{body}
"#
    )
}

/// rapier's positions, ours, and dt.
type Trajectories = (Vec<[f64; 3]>, Vec<[f64; 3]>, f64);

/// Positions (centre of mass) of body 0 at every frame: rapier, and ours. Same `dt`, same
/// number of frames (rapier's run may end early once everything rests: its last pose holds).
fn trajectories(text: &str) -> Result<Trajectories> {
    let template = SceneTemplate::parse(text, "stepper-bench.toml")?;
    let seed = 1;
    let scene = template.instantiate(seed);
    let dt = scene.settings.dt;
    let steps = (scene.settings.end_time / dt).round() as usize;
    let mut rapier: Vec<[f64; 3]> = Vec::with_capacity(steps + 1);
    let opts = RunOptions {
        perturb: false,
        record: true,
        encoding: PayloadEncoding::QuantisedFrames,
        ..RunOptions::default()
    };
    run_world_observed(
        &template,
        seed,
        opts,
        &mut |_| ControlFlow::Continue(()),
        &mut |tracks| {
            if let Some(t) = tracks.first() {
                rapier.extend_from_slice(&t.positions);
            }
        },
    )
    .context("rapier run")?;
    let Some(&last) = rapier.last() else {
        bail!("rapier recorded no frames");
    };
    rapier.resize(steps + 1, last);

    let mut world = mwb_reverse::scene::world_from_scene(&scene).context("our stepper's world")?;
    let mut ours = Vec::with_capacity(steps + 1);
    let pos = |w: &mwb_reverse::World| {
        let p = w.bodies[0].position;
        [p.x, p.y, p.z]
    };
    ours.push(pos(&world));
    for _ in 0..steps {
        world.step_forward(dt);
        ours.push(pos(&world));
    }
    Ok((rapier, ours, dt))
}

fn case(
    name: &'static str,
    unit: &'static str,
    analytic: f64,
    text: &str,
    measure: impl Fn(&[[f64; 3]], f64) -> f64,
) -> Result<StepperCase> {
    let (rapier, ours, dt) = trajectories(text).with_context(|| name.to_owned())?;
    let (r, o) = (measure(&rapier, dt), measure(&ours, dt));
    Ok(StepperCase {
        case: name,
        unit,
        analytic,
        ours: o,
        rapier: r,
        ours_err: o - analytic,
        rapier_err: r - analytic,
        dt,
    })
}

/// The first rebound's highest point after the first impact (the frame where the height
/// stops falling), of `y − offset`.
fn first_apex(track: &[[f64; 3]], offset: f64) -> f64 {
    let ys: Vec<f64> = track.iter().map(|p| p[1]).collect();
    // First impact: the lowest point of the initial fall.
    let Some(bottom) = (1..ys.len()).find(|&i| ys[i] > ys[i - 1]) else {
        return f64::NAN;
    };
    // Then the apex: the highest point before falling again.
    let apex = (bottom + 1..ys.len())
        .find(|&i| ys[i] < ys[i - 1])
        .map_or(ys.len() - 1, |i| i - 1);
    ys[apex] - offset
}

/// Runs every case on both engines.
pub fn measure() -> Result<StepperBench> {
    let settings = |end: f64| format!("end_time = {end}");
    let dense = "friction = 0.5\nrestitution = 0.0\ndensity = 1000";
    let cases = vec![
        case(
            "box_rest_height",
            "m",
            0.2,
            &scene(
                &settings(2.0),
                "shape = \"box\"\nsize = [0.4, 0.4, 0.4]\nposition = [0, 1.0, 0]",
                dense,
            ),
            |t, _| t.last().map_or(f64::NAN, |p| p[1]),
        )?,
        case(
            "ball_bounce_apex",
            "m",
            0.25,
            &scene(
                &settings(1.5),
                "shape = \"sphere\"\nradius = 0.1\nposition = [0, 1.1, 0]",
                "friction = 0.5\nrestitution = 0.5\ndensity = 1000",
            ),
            |t, _| first_apex(t, 0.1),
        )?,
        case(
            "box_slide_distance",
            "m",
            3.0 * 3.0 / (2.0 * 0.5 * G),
            &scene(
                &settings(1.5),
                "shape = \"box\"\nsize = [0.2, 0.2, 0.2]\nposition = [0, 0.1, 0]\nlinvel = [3, 0, 0]",
                dense,
            ),
            |t, _| match (t.first(), t.last()) {
                (Some(a), Some(b)) => b[0] - a[0],
                _ => f64::NAN,
            },
        )?,
        case(
            "ball_roll_speed",
            "m/s",
            2.0 * 5.0 / 7.0,
            &scene(
                &settings(1.1),
                "shape = \"sphere\"\nradius = 0.1\nposition = [0, 0.1, 0]\nlinvel = [2, 0, 0]",
                dense,
            ),
            |t, dt| {
                // Mean speed over 0.05 s around t = 1 s.
                let i = (1.0 / dt).round() as usize;
                let h = ((0.025 / dt).round() as usize).max(1);
                match (t.get(i.saturating_sub(h)), t.get(i + h)) {
                    (Some(a), Some(b)) => (b[0] - a[0]) / (2 * h) as f64 / dt,
                    _ => f64::NAN,
                }
            },
        )?,
    ];
    Ok(StepperBench { cases })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn apex_of_a_bounce() {
        // Falls to 0, rises to 0.3, falls again.
        let ys = [1.0, 0.5, 0.0, 0.2, 0.3, 0.25, 0.1];
        let t: Vec<[f64; 3]> = ys.iter().map(|&y| [0.0, y, 0.0]).collect();
        assert!((first_apex(&t, 0.0) - 0.3).abs() < 1e-12);
        assert!((first_apex(&t, 0.1) - 0.2).abs() < 1e-12);
        // Never bounces: NaN, not a made-up number.
        let t: Vec<[f64; 3]> = [1.0, 0.5, 0.0].iter().map(|&y| [0.0, y, 0.0]).collect();
        assert!(first_apex(&t, 0.0).is_nan());
    }
}
