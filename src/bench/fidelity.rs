//! `mwb bench fidelity`: the speed↔accuracy trade of the simulation presets (issue 19), per
//! scene. The method is `mwb_sampler::fidelity`'s: `--worlds` worlds (seeds 0..N) at each
//! preset and at the reference (final's step ÷ 8, 4× its iterations), compared as
//! distributions — 1-Wasserstein distance per coordinate, averaged over bodies, with a 90 %
//! bootstrap interval — plus each set's worst penetration, free-flight energy drift and
//! tunnelling. Cost is thread CPU time per world (one core, perturbations on, no encoding).

use crate::output::{json_line, number};
use anyhow::{Context, Result, bail};
use mwb_core::scene::{SceneTemplate, SimPreset};
use mwb_sampler::fidelity::{
    Comparison, Quantity, WorldMeasure, compare, extremes, measure_world, scene_at, tolerance,
    within_tolerance,
};
use mwb_sampler::plan::SimPlan;
use std::path::Path;

/// Arguments of `mwb bench fidelity`.
#[derive(Debug, Clone, clap::Args)]
pub struct FidelityArgs {
    /// Scene files or shipped scene names [default: every shipped scene].
    #[arg(long = "scene")]
    pub scenes: Vec<String>,
    /// Presets to measure against the reference (comma-separated).
    #[arg(long, value_delimiter = ',', default_value = "draft,standard,final")]
    pub presets: Vec<String>,
    /// Worlds per (scene, preset); the reference runs as many.
    #[arg(long, default_value_t = 32)]
    pub worlds: u32,
    /// Bootstrap resamplings for the intervals.
    #[arg(long, default_value_t = 200)]
    pub bootstrap: usize,
    /// Also write a cost-versus-error plot (PNG) here, the Pareto front marked.
    #[arg(long)]
    pub plot: Option<std::path::PathBuf>,
    /// Skip the analytic suite (scenes/analytic: closed forms, one line per case and preset).
    #[arg(long)]
    pub no_analytic: bool,
    /// Print one JSON line per (scene, setting) instead of the table.
    #[arg(long)]
    pub json: bool,
}

/// One analytic case at one preset.
#[derive(Debug, Clone, serde::Serialize)]
pub struct AnalyticLine {
    pub scene: String,
    pub preset: String,
    pub quantity: String,
    pub unit: String,
    pub expected: f64,
    pub measured: f64,
    pub error: f64,
    pub tolerance: f64,
    pub pass: bool,
}

/// One (scene, setting) line.
#[derive(Debug, Clone, serde::Serialize)]
pub struct FidelityLine {
    pub scene: String,
    pub preset: String,
    /// Simulated time step (s): the frame interval ÷ substeps.
    pub dt: f64,
    pub frame_dt: f64,
    pub substeps: u32,
    pub iterations: u32,
    /// CCD policy and how many bodies of world 0 it puts CCD on.
    pub ccd: String,
    pub worlds: usize,
    pub core_s_per_world: f64,
    /// Reference's CPU per world ÷ this setting's.
    pub speedup_vs_reference: f64,
    /// Distance of the rest positions' distribution to the reference's of the same seeds (m),
    /// with its 90 % bootstrap interval (0 for the reference itself).
    pub rest_position_w1: f64,
    pub rest_position_w1_lo: f64,
    pub rest_position_w1_hi: f64,
    /// The same for the final orientation's angle (rad), the rest time (s) and the impact
    /// count (impacts counted between frames, so that the reference's 8 steps a frame count
    /// like one).
    pub rest_angle_w1: f64,
    pub rest_time_w1: f64,
    pub impacts_w1: f64,
    /// The reference's distance to as many reference worlds of other seeds: the study's
    /// resolution (m).
    pub noise_floor_m: f64,
    /// `rest_position_w1_lo − noise_floor_m`: how much further than other reference worlds,
    /// at the interval's lower end (≤ 0: indistinguishable at this many worlds).
    pub excess_lo_m: f64,
    pub max_penetration_m: f64,
    pub flight_energy_drift_m: f64,
    pub tunnelled_worlds: usize,
    pub non_finite_worlds: usize,
    /// The scene's tolerance (m) and whether this setting meets it (the `auto` rule).
    pub tolerance_m: f64,
    pub within_tolerance: bool,
    pub plan: String,
}

fn measure_set(
    template: &SceneTemplate,
    preset: SimPreset,
    first: u64,
    worlds: u32,
) -> Result<(Vec<WorldMeasure>, f64)> {
    let mut out = Vec::with_capacity(worlds as usize);
    let t0 = mwb_node::bus::cpu_time();
    for seed in first..first + u64::from(worlds) {
        out.push(
            measure_world(template, Some(preset), seed)
                .with_context(|| format!("{preset} world {seed}"))?,
        );
    }
    let cpu = mwb_node::bus::cpu_time() - t0;
    Ok((out, cpu / f64::from(worlds.max(1))))
}

/// Runs `mwb bench fidelity`.
pub fn run(args: FidelityArgs) -> Result<()> {
    let scenes = if args.scenes.is_empty() {
        mwb_core::scene::builtin::NAMES
            .iter()
            .map(|s| (*s).to_owned())
            .collect()
    } else {
        args.scenes.clone()
    };
    let presets: Vec<SimPreset> = args
        .presets
        .iter()
        .map(|p| match SimPreset::from_name(p) {
            Some(SimPreset::Auto) | None => {
                bail!("--presets: unknown preset {p:?} (draft, standard, final, reference)")
            }
            Some(p) => Ok(p),
        })
        .collect::<Result<_>>()?;
    if args.worlds < 2 {
        bail!("--worlds: at least 2 (the noise floor compares two halves)");
    }
    let mut curves = Vec::new();
    for name in &scenes {
        let (file, text) = crate::client::load_scene(name)?;
        let template = SceneTemplate::parse(&text, &file)?;
        let scene_name = template.name().to_owned();
        let (reference, ref_cpu) = measure_set(&template, SimPreset::Reference, 0, args.worlds)?;
        let (reference_b, _) = measure_set(
            &template,
            SimPreset::Reference,
            u64::from(args.worlds),
            args.worlds,
        )?;
        let tol = tolerance(&template.instantiate(0));
        let mut points = Vec::new();
        for &preset in presets.iter().chain([&SimPreset::Reference]) {
            let (set, cpu) = if preset == SimPreset::Reference {
                (reference.clone(), ref_cpu)
            } else {
                measure_set(&template, preset, 0, args.worlds)?
            };
            let est = |q: Quantity| -> Comparison {
                compare(&set, &reference, &reference_b, q, args.bootstrap, 1)
            };
            let pos = est(Quantity::RestPosition);
            let floor = pos.floor;
            let ext = extremes(&set);
            let scene0 = scene_at(&template, Some(preset), 0);
            let plan = SimPlan::of(&scene0);
            let line = FidelityLine {
                scene: scene_name.clone(),
                preset: preset.name().to_owned(),
                dt: scene0.settings.dt / f64::from(plan.substeps),
                frame_dt: scene_at(&template, Some(SimPreset::Standard), 0)
                    .settings
                    .dt,
                substeps: plan.substeps,
                iterations: plan.iterations,
                ccd: format!(
                    "{} ({} of {})",
                    plan.ccd_policy.name(),
                    plan.ccd.iter().filter(|c| **c).count(),
                    plan.ccd.len()
                ),
                worlds: set.len(),
                core_s_per_world: cpu,
                speedup_vs_reference: ref_cpu / cpu,
                rest_position_w1: pos.value,
                rest_position_w1_lo: pos.lo,
                rest_position_w1_hi: pos.hi,
                rest_angle_w1: est(Quantity::RestAngle).value,
                rest_time_w1: est(Quantity::RestTime).value,
                impacts_w1: est(Quantity::Impacts).value,
                noise_floor_m: floor,
                excess_lo_m: pos.excess_lo(),
                max_penetration_m: ext.max_penetration,
                flight_energy_drift_m: ext.flight_energy_drift,
                tunnelled_worlds: ext.tunnelled_worlds,
                non_finite_worlds: ext.non_finite_worlds,
                tolerance_m: tol,
                within_tolerance: within_tolerance(&pos, &ext, tol),
                plan: plan.describe(),
            };
            if args.json {
                json_line(&line)?;
            } else {
                crate::output::out(&format!(
                    "{:<16} {:<9} {:>3}x{:<2} {:>9} s/world {:>6}x  rest pos {} m [{} … {}] \
                     floor {}  angle {} rad  rest time {} s  impacts {}  pen {} m  drift {}  \
                     tunnelled {}/{}{}\n",
                    line.scene,
                    line.preset,
                    line.substeps,
                    line.iterations,
                    number(line.core_s_per_world),
                    number(line.speedup_vs_reference),
                    number(line.rest_position_w1),
                    number(line.rest_position_w1_lo),
                    number(line.rest_position_w1_hi),
                    number(line.noise_floor_m),
                    number(line.rest_angle_w1),
                    number(line.rest_time_w1),
                    number(line.impacts_w1),
                    number(line.max_penetration_m),
                    if line.flight_energy_drift_m.is_nan() {
                        "n/a (damped scene)".to_owned()
                    } else {
                        format!("{} m", number(line.flight_energy_drift_m))
                    },
                    line.tunnelled_worlds,
                    line.worlds,
                    if line.within_tolerance {
                        ""
                    } else {
                        "  (outside tolerance)"
                    },
                ))?;
            }
            // The reference is drawn at its floor: its distance to itself is 0 by construction,
            // and what it can resolve is the floor.
            let y = if preset == SimPreset::Reference {
                line.noise_floor_m
            } else {
                line.rest_position_w1
            };
            points.push((preset, line.core_s_per_world, y));
        }
        let floor = compare(
            &reference,
            &reference,
            &reference_b,
            Quantity::RestPosition,
            0,
            1,
        )
        .floor;
        curves.push((scene_name, points, floor));
    }
    if !args.no_analytic {
        for &preset in presets.iter().chain([&SimPreset::Reference]) {
            let cases = mwb_sampler::analytic::run_suite(preset)
                .with_context(|| format!("analytic suite at {preset}"))?;
            for c in cases {
                let line = AnalyticLine {
                    scene: format!("analytic/{}", c.name),
                    preset: preset.name().to_owned(),
                    quantity: c.quantity.to_owned(),
                    unit: c.unit.to_owned(),
                    expected: c.expected,
                    measured: c.measured,
                    error: c.error,
                    tolerance: c.tolerance,
                    pass: c.passes(),
                };
                if args.json {
                    json_line(&line)?;
                } else {
                    crate::output::out(&format!(
                        "{:<20} {:<9} {:<32} expected {} {}, measured {}, error {} (tolerance {}) {}\n",
                        line.scene,
                        line.preset,
                        line.quantity,
                        number(line.expected),
                        line.unit,
                        number(line.measured),
                        number(line.error),
                        number(line.tolerance),
                        if line.pass { "✔" } else { "✘" },
                    ))?;
                }
            }
        }
    }
    if let Some(path) = &args.plot {
        plot(path, &curves)?;
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}

/// The presets of a scene that no other is both cheaper and closer to the reference than
/// (the reference itself is the front's costly end), cheapest first.
pub fn pareto(points: &[(SimPreset, f64, f64)]) -> Vec<(SimPreset, f64, f64)> {
    let mut front: Vec<(SimPreset, f64, f64)> = points
        .iter()
        .copied()
        .filter(|&(_, c, e)| {
            !points
                .iter()
                .any(|&(_, c2, e2)| c2 <= c && e2 <= e && (c2 < c || e2 < e))
        })
        .collect();
    front.sort_by(|a, b| a.1.total_cmp(&b.1));
    front
}

type Curve = (String, Vec<(SimPreset, f64, f64)>, f64);

/// Cost (CPU s per world) against error (rest-position distance to the reference, m), log–log,
/// one colour per scene: every preset a dot (a cross when another preset is both cheaper and
/// closer), the Pareto front of the presets a line, the reference a triangle on its floor (the
/// dashed level: what other reference worlds give; below it a preset is indistinguishable).
fn plot(path: &Path, curves: &[Curve]) -> Result<()> {
    use plotters::prelude::*;
    let text = crate::bench::codec::register_font();
    let pts = curves
        .iter()
        .flat_map(|(_, p, f)| p.iter().map(|&(_, c, e)| (c, e)).chain([(f64::NAN, *f)]));
    let (mut x_lo, mut x_hi, mut y_lo, mut y_hi) = (f64::INFINITY, 0.0f64, f64::INFINITY, 0.0f64);
    for (c, e) in pts {
        if c.is_finite() && c > 0.0 {
            x_lo = x_lo.min(c);
            x_hi = x_hi.max(c);
        }
        if e.is_finite() && e > 0.0 {
            y_lo = y_lo.min(e);
            y_hi = y_hi.max(e);
        }
    }
    if !(x_lo.is_finite() && y_lo.is_finite()) {
        bail!("nothing to plot");
    }
    let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("plot {}: {e}", path.display());
    let root = BitMapBackend::new(path, (960, 640)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let mut builder = ChartBuilder::on(&root);
    builder.margin(20);
    if text {
        builder
            .caption(
                "Simulation presets: cost vs distance to the reference (rest positions)",
                ("sans-serif", 22),
            )
            .x_label_area_size(50)
            .y_label_area_size(70);
    }
    let mut chart = builder
        .build_cartesian_2d(
            (x_lo * 0.6..x_hi * 1.6).log_scale(),
            (y_lo * 0.6..y_hi * 1.6).log_scale(),
        )
        .map_err(|e| err(&e))?;
    let mut mesh = chart.configure_mesh();
    if text {
        mesh.x_desc("CPU seconds per world (one core)")
            .y_desc("rest-position distance to reference [m]")
            .x_label_formatter(&|v| format!("{v:.0e}"))
            .y_label_formatter(&|v| format!("{v:.0e}"));
    } else {
        mesh.x_labels(0).y_labels(0);
    }
    mesh.draw().map_err(|e| err(&e))?;
    let colours = [&BLUE, &RED, &GREEN, &MAGENTA, &CYAN, &BLACK];
    for (i, (scene, points, floor)) in curves.iter().enumerate() {
        let c = colours[i % colours.len()];
        // The front of the presets one samples with; the reference is where they are measured
        // from, drawn on its floor.
        let presets: Vec<(SimPreset, f64, f64)> = points
            .iter()
            .copied()
            .filter(|p| p.0 != SimPreset::Reference)
            .collect();
        let front = pareto(&presets);
        let line: Vec<(f64, f64)> = front.iter().map(|&(_, x, y)| (x, y)).collect();
        let series = chart
            .draw_series(LineSeries::new(line, c.stroke_width(2)))
            .map_err(|e| err(&e))?;
        if text {
            series.label(scene.clone()).legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2))
            });
        }
        if *floor > 0.0 {
            chart
                .draw_series(DashedLineSeries::new(
                    vec![(x_lo * 0.6, *floor), (x_hi * 1.6, *floor)],
                    4,
                    4,
                    c.stroke_width(1),
                ))
                .map_err(|e| err(&e))?;
        }
        for &(preset, x, y) in points {
            if !(x > 0.0 && y > 0.0) {
                continue;
            }
            let on_front = front.iter().any(|f| f.0 == preset);
            if preset == SimPreset::Reference {
                chart
                    .draw_series([TriangleMarker::new((x, y), 7, c.filled())])
                    .map_err(|e| err(&e))?;
            } else if on_front {
                chart
                    .draw_series([Circle::new((x, y), 5, c.filled())])
                    .map_err(|e| err(&e))?;
            } else {
                chart
                    .draw_series([Cross::new((x, y), 5, c.stroke_width(2))])
                    .map_err(|e| err(&e))?;
            }
            if text {
                chart
                    .draw_series([Text::new(
                        preset.name().to_owned(),
                        (x * 1.08, y * 1.08),
                        ("sans-serif", 13).into_font().color(c),
                    )])
                    .map_err(|e| err(&e))?;
            }
        }
    }
    if text {
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 14))
            .draw()
            .map_err(|e| err(&e))?;
    }
    root.present().map_err(|e| err(&e))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_front_drops_what_is_both_dearer_and_worse() {
        let pts = [
            (SimPreset::Draft, 1.0, 0.5),
            (SimPreset::Standard, 2.0, 0.6),
            (SimPreset::Final, 4.0, 0.1),
            (SimPreset::Reference, 30.0, 0.02),
        ];
        let front: Vec<SimPreset> = pareto(&pts).into_iter().map(|p| p.0).collect();
        assert_eq!(
            front,
            [SimPreset::Draft, SimPreset::Final, SimPreset::Reference]
        );
    }
}
