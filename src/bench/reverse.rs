//! `mwb bench reverse`: our LCP stepper forward against backward (the backward-steps paper),
//! measured by `mwb_reverse::bench`; this module prints its numbers.

use crate::output::{Summary, fields_table};
use anyhow::Result;
use mwb_reverse::ReverseBench;

/// Arguments of `mwb bench reverse`.
#[derive(Debug, Clone, clap::Args)]
pub struct ReverseArgs {
    /// Worlds sampled backward for the round-trip and energy numbers.
    #[arg(long, default_value_t = 16)]
    pub worlds: usize,
    /// Skip the big ball-array run.
    #[arg(long)]
    pub no_balls: bool,
    /// Print the result as one JSON line.
    #[arg(long)]
    pub json: bool,
}

/// Runs `mwb bench reverse`.
pub async fn run(args: ReverseArgs) -> Result<()> {
    let mut o = mwb_reverse::BenchOptions {
        worlds: args.worlds,
        ..Default::default()
    };
    if args.no_balls {
        o.balls_scene = None;
    }
    let b = tokio::task::spawn_blocking(move || mwb_reverse::bench(&o)).await??;
    crate::output::print(&ReverseLine::from(b), args.json)
}

/// The bench's line: [`ReverseBench`]'s fields (documented there), in the alphabetical order
/// the line has always had, so that scripts and docs/performance.md read the same line.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ReverseLine {
    pub angular_speed_peak_p50: f64,
    pub backward_step_us: f64,
    pub balls: usize,
    pub balls_energy_growth: f64,
    pub balls_learn_seconds: f64,
    pub balls_seconds: f64,
    pub balls_steps: usize,
    pub bodies: usize,
    pub energy_growth_p50: f64,
    pub forward_step_us: f64,
    pub ratio: f64,
    pub roundtrip_departed_fraction: f64,
    pub roundtrip_max_rel_err: f64,
    pub roundtrip_p50_rel_err: f64,
}

impl From<ReverseBench> for ReverseLine {
    fn from(b: ReverseBench) -> Self {
        Self {
            angular_speed_peak_p50: b.angular_speed_peak_p50,
            backward_step_us: b.backward_step_us,
            balls: b.balls,
            balls_energy_growth: b.balls_energy_growth,
            balls_learn_seconds: b.balls_learn_seconds,
            balls_seconds: b.balls_seconds,
            balls_steps: b.balls_steps,
            bodies: b.bodies,
            energy_growth_p50: b.energy_growth_p50,
            forward_step_us: b.forward_step_us,
            ratio: b.ratio,
            roundtrip_departed_fraction: b.roundtrip_departed_fraction,
            roundtrip_max_rel_err: b.roundtrip_max_rel_err,
            roundtrip_p50_rel_err: b.roundtrip_p50_rel_err,
        }
    }
}

impl Summary for ReverseLine {
    fn table(&self) -> String {
        fields_table(self)
    }
}
