//! `mwb bench reverse`: our LCP stepper forward against backward (the backward-steps paper),
//! the plausible fraction of every shipped reverse scene and the 3037-ball lorem world, measured
//! by `mwb_reverse::bench`; this module prints its numbers.

use std::collections::BTreeMap;

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
    /// Worlds sampled per shipped reverse scene for `plausible_fraction` (0: none).
    #[arg(long, default_value_t = 20)]
    pub scene_worlds: usize,
    /// Worlds per big shipped scene (balls, > 500 bodies).
    #[arg(long, default_value_t = 20)]
    pub big_scene_worlds: usize,
    /// Skip the 3037-ball lorem world.
    #[arg(long)]
    pub no_lorem: bool,
    /// Sample only this shipped reverse scene for `plausible_fraction` (repeat for several;
    /// default: every one).
    #[arg(long = "scene", value_name = "NAME")]
    pub scenes: Vec<String>,
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
    o.scene_worlds = args.scene_worlds;
    o.big_scene_worlds = args.big_scene_worlds;
    if args.no_lorem {
        o.lorem_scene = None;
    }
    o.scenes = only_scenes(o.scenes, &args.scenes)?;
    let b = tokio::task::spawn_blocking(move || mwb_reverse::bench(&o)).await??;
    crate::output::print(&ReverseLine::from(b), args.json)
}

/// `scenes` narrowed to the names in `only` (all of them when `only` is empty); a name that is
/// not a shipped reverse scene is an error naming the ones there are.
fn only_scenes(scenes: Vec<(String, String)>, only: &[String]) -> Result<Vec<(String, String)>> {
    if only.is_empty() {
        return Ok(scenes);
    }
    if let Some(unknown) = only.iter().find(|n| !scenes.iter().any(|(s, _)| s == *n)) {
        let known: Vec<&str> = scenes.iter().map(|(s, _)| s.as_str()).collect();
        anyhow::bail!(
            "--scene {unknown}: not a shipped reverse scene (there are: {})",
            known.join(", ")
        );
    }
    Ok(scenes
        .into_iter()
        .filter(|(s, _)| only.contains(s))
        .collect())
}

/// The bench's line: [`ReverseBench`]'s fields (documented there), in the alphabetical order
/// the line has always had, so that scripts and docs/performance.md read the same line.
/// Per-scene numbers are objects keyed by scene name; `lorem_*` are null when skipped.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ReverseLine {
    pub angular_speed_peak_p50: f64,
    pub angular_speed_peak_p95: f64,
    pub backward_step_us: f64,
    pub balls: usize,
    pub balls_energy_growth: f64,
    pub balls_learn_seconds: f64,
    pub balls_seconds: f64,
    pub balls_steps: usize,
    pub bodies: usize,
    pub energy_growth_p50: f64,
    pub energy_growth_p95: f64,
    /// Per scene, the 95th percentile of its worlds' energy growth (m).
    pub energy_growth_p95_by_scene: BTreeMap<String, f64>,
    pub forward_step_us: f64,
    pub lorem_balls: Option<usize>,
    /// Played forward, bounces from 1 m/s or faster, and those that keep ≥ 90 % of the speed
    /// (elastic, with balls of restitution 0.6 on a 0.5 floor), and the balls with one.
    pub lorem_bounces: Option<usize>,
    pub lorem_cells_correct: Option<f64>,
    pub lorem_elastic_balls: Option<usize>,
    pub lorem_elastic_bounces: Option<usize>,
    pub lorem_energy_growth: Option<f64>,
    /// 5th percentile and median of the fraction of its falling speed a ball's first bounce
    /// keeps, played forward (the material pair keeps 0.55; the last rung of a backward ladder
    /// keeps less).
    pub lorem_first_bounce_keep_p5: Option<f64>,
    pub lorem_first_bounce_keep_p50: Option<f64>,
    pub lorem_excess_m: Option<f64>,
    pub lorem_implausible_balls: Option<usize>,
    pub lorem_left_bins: Option<f64>,
    pub lorem_plausible: Option<bool>,
    pub lorem_seconds: Option<f64>,
    pub lorem_steps: Option<usize>,
    /// Per scene, the median plausibility excess of its worlds (m; ≤ 0: plausible).
    pub plausible_excess_p50: BTreeMap<String, f64>,
    /// Per scene, the fraction of its sampled worlds that are plausible.
    pub plausible_fraction: BTreeMap<String, f64>,
    /// Per scene, its implausible worlds by the clause their worst body breaks
    /// (docs/reverse.md#plausibility): `faster_than_fall`, `too_high`, `penetration`.
    pub implausible_by_clause: BTreeMap<String, BTreeMap<String, usize>>,
    /// Per scene, how many worlds were sampled.
    pub plausible_worlds: BTreeMap<String, usize>,
    /// Per scene, the fraction of its bodies (over all worlds) that end at least 5 cm from
    /// their given position: how much the backward worlds do.
    pub moved_fraction: BTreeMap<String, f64>,
    pub ratio: f64,
    pub roundtrip_departed_fraction: f64,
    pub roundtrip_max_rel_err: f64,
    pub roundtrip_p50_rel_err: f64,
}

impl From<ReverseBench> for ReverseLine {
    fn from(b: ReverseBench) -> Self {
        let by_scene = |f: fn(&mwb_reverse::ScenePlausibility) -> f64| {
            b.scenes.iter().map(|(n, s)| (n.clone(), f(s))).collect()
        };
        let lorem = b.lorem.as_ref();
        Self {
            angular_speed_peak_p50: b.angular_speed_peak_p50,
            angular_speed_peak_p95: b.angular_speed_peak_p95,
            backward_step_us: b.backward_step_us,
            balls: b.balls,
            balls_energy_growth: b.balls_energy_growth,
            balls_learn_seconds: b.balls_learn_seconds,
            balls_seconds: b.balls_seconds,
            balls_steps: b.balls_steps,
            bodies: b.bodies,
            energy_growth_p50: b.energy_growth_p50,
            energy_growth_p95: b.energy_growth_p95,
            energy_growth_p95_by_scene: by_scene(|s| s.energy_growth_p95),
            forward_step_us: b.forward_step_us,
            lorem_balls: lorem.map(|l| l.balls),
            lorem_bounces: lorem.map(|l| l.bounces.bounces),
            lorem_elastic_bounces: lorem.map(|l| l.bounces.elastic),
            lorem_elastic_balls: lorem.map(|l| l.bounces.elastic_bodies),
            lorem_cells_correct: lorem.map(|l| l.cells_correct),
            lorem_energy_growth: lorem.map(|l| l.energy_growth),
            lorem_first_bounce_keep_p5: lorem.map(|l| l.first_bounce_keep.0),
            lorem_first_bounce_keep_p50: lorem.map(|l| l.first_bounce_keep.1),
            lorem_excess_m: lorem.map(|l| l.excess_m),
            lorem_implausible_balls: lorem.map(|l| l.implausible_balls),
            lorem_left_bins: lorem.map(|l| l.left_bins),
            lorem_plausible: lorem.map(|l| l.plausible),
            lorem_seconds: lorem.map(|l| l.seconds),
            lorem_steps: lorem.map(|l| l.steps),
            moved_fraction: by_scene(|s| s.moved_fraction),
            plausible_excess_p50: by_scene(|s| s.excess_p50),
            plausible_fraction: by_scene(|s| s.plausible_fraction),
            implausible_by_clause: b
                .scenes
                .iter()
                .map(|(n, s)| {
                    let [fall, high, sank] = s.implausible_by_clause;
                    let counts = [
                        ("faster_than_fall", fall),
                        ("too_high", high),
                        ("penetration", sank),
                    ];
                    (
                        n.clone(),
                        counts.into_iter().map(|(k, v)| (k.to_owned(), v)).collect(),
                    )
                })
                .collect(),
            plausible_worlds: b
                .scenes
                .iter()
                .map(|(n, s)| (n.clone(), s.worlds))
                .collect(),
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

#[cfg(test)]
mod tests {
    use super::*;

    /// `--scene` keeps the named scenes in their order, all of them when none is named, and
    /// refuses a name that is not shipped, naming the ones that are.
    #[test]
    fn scene_filter_keeps_the_named_and_refuses_the_unknown() {
        let all = mwb_reverse::BenchOptions::default().scenes;
        assert!(all.len() >= 2);
        let names = |v: &[(String, String)]| v.iter().map(|(n, _)| n.clone()).collect::<Vec<_>>();
        assert_eq!(
            names(&only_scenes(all.clone(), &[]).unwrap_or_default()),
            names(&all)
        );
        let pick = vec![all[1].0.clone()];
        assert_eq!(
            names(&only_scenes(all.clone(), &pick).unwrap_or_default()),
            pick
        );
        let err = only_scenes(all.clone(), &["nope".to_owned()])
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(
            err.contains("--scene nope") && err.contains(&all[0].0),
            "{err}"
        );
    }
}
