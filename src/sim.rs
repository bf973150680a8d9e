//! `--sim`: the simulation preset of a job's scene (issue 19). The preset travels *in the scene
//! text* (`[settings] sim = "…"`), so a job, its worlds' regeneration and every refinement of
//! them use the same one; `auto` is resolved here, before the job exists, by a short
//! calibration ([`mwb_sampler::fidelity::calibrate`]), and the text records what it chose.

use anyhow::{Context, Result, bail};
use mwb_core::scene::{SceneTemplate, SimPreset, edit_text::set_sim_preset};
use mwb_sampler::fidelity::{Calibration, calibrate};
use mwb_sampler::limits::{Finding, Severity, check_template};

use crate::output::number;

/// Worlds per preset in `auto`'s calibration (and twice as many at the reference).
pub const CALIBRATION_WORLDS: usize = 24;

/// What the simulator cannot do faithfully in the scene ([`mwb_sampler::limits::check_template`]).
pub fn findings(template: &SceneTemplate) -> Vec<Finding> {
    check_template(template)
}

/// One finding as a line ([`Finding::line`]).
pub fn finding_line(file: &str, f: &Finding) -> String {
    f.line(file)
}

/// [`resolve`], then the limit checks: warnings go to stderr, a refusal is an error naming
/// every refused body, field and limit. For job submission.
pub fn resolve_checked(file: &str, text: &str, preset: Option<SimPreset>) -> Result<String> {
    let text = resolve(file, text, preset)?;
    let template = SceneTemplate::parse(&text, file)?;
    let found = findings(&template);
    for f in found.iter().filter(|f| f.severity == Severity::Warn) {
        eprintln!("{}", finding_line(file, f));
    }
    let refused: Vec<String> = found
        .iter()
        .filter(|f| f.severity == Severity::Refuse)
        .map(|f| finding_line(file, f))
        .collect();
    if !refused.is_empty() {
        bail!(
            "the simulator cannot do this scene faithfully:\n{}",
            refused.join("\n")
        );
    }
    Ok(text)
}

/// The scene text a job carries: `preset` written into it when given, and a preset of `auto`
/// (given, or the scene's own) replaced by the calibration's choice, with a comment saying so.
/// The calibration's table goes to stderr.
pub fn resolve(file: &str, text: &str, preset: Option<SimPreset>) -> Result<String> {
    let wanted = match preset {
        Some(p) => p,
        None => SceneTemplate::parse(text, file)?.settings().sim,
    };
    if wanted != SimPreset::Auto {
        return match preset {
            Some(p) => Ok(set_sim_preset(text, file, p, None)?),
            None => Ok(text.to_owned()),
        };
    }
    // Calibrate on the scene as written, under each preset in turn.
    let template = SceneTemplate::parse(text, file)?;
    eprintln!(
        "sim auto: calibrating {file} ({CALIBRATION_WORLDS} worlds per preset, {} at the reference)…",
        2 * CALIBRATION_WORLDS
    );
    let cal = calibrate(&template, CALIBRATION_WORLDS)
        .with_context(|| format!("{file}: sim auto calibration"))?;
    eprint!("{}", table(&cal));
    let note = format!(
        "chosen by sim = \"auto\": tolerance {} m over {} worlds",
        number(cal.tolerance),
        cal.worlds
    );
    Ok(set_sim_preset(text, file, cal.chosen, Some(&note))?)
}

/// The calibration as people read it.
pub fn table(cal: &Calibration) -> String {
    let mut out = String::new();
    for r in &cal.results {
        let c = &r.rest_position;
        out.push_str(&format!(
            "  {:<9} rest positions {} m from the reference [{} … {}] (other reference worlds: {} m), \
             penetration {} m, tunnelled in {} world(s){}\n",
            r.preset.name(),
            number(c.value),
            number(c.lo),
            number(c.hi),
            number(c.floor),
            number(r.extremes.max_penetration),
            r.extremes.tunnelled_worlds,
            if r.within { "  ✔ within" } else { "  ✘ outside" },
        ));
    }
    out.push_str(&format!(
        "sim auto: {} (tolerance {} m) — {}\n",
        cal.chosen,
        number(cal.tolerance),
        cal.plan
    ));
    out
}
