//! The optional `[reverse]` table of a reverse scene: how the scene's state is used (the last
//! frame of a backward run, or the intermediate frame of a mixed run, §5.4.4), the energy
//! budget, and per-body user hints (Figure 5.10), mapped onto [`UserHint`] / [`HintMotion`].
//!
//! ```toml
//! [reverse]
//! mode = "mixed"        # "backward" (default): the state is the LAST frame, the run goes back
//!                       # [settings] end_time; "mixed": the state is an intermediate frame,
//! forward_time = 1.5    # reached after end_time s of backward run and left for forward_time s
//! energy_budget = 0.1   # 0–1 of the plausibility allowance (default 0): energy a body may
//!                       # gain beyond what a fall or its lift-off explains; more leaves rest
//!                       # more often, less is plausible more often (run::Heuristics)
//!
//! [[reverse.hint]]
//! body = "M0"               # a [[body]] name (generator instances: "name[i,j,k]")
//! motion = "slide"          # "free" (the contact chain decides; default), "slide", "bounce", "stay"
//! direction = [1, 0, 0]     # slide only, required: played forward the body arrives moving along
//!                           # it (its length is ignored, the speed is sampled; needs a component
//!                           # perpendicular to gravity)
//! release_before_end = 0.5  # s (default 0): it leaves its resting contacts only earlier than this
//!                           # before the given state; played forward, it has settled by then
//! ```
//!
//! Hints act in the backward run (for a mixed world: the part before the given state), and only
//! on a body while it touches something (a body in flight has nothing to leave).
//!
//! The core scene parser passes over the `reverse` key, so the same text goes to both parsers
//! and every `file:line` stays true; the table may also be written inline
//! (`reverse = { mode = "mixed", … }`). Every refusal is a [`SceneError`] naming the file, the
//! line, the item and the field.
//!
//! ```
//! use mwb_reverse::settings_toml::{RunMode, parse_reverse_scene};
//! use mwb_reverse::scene::builtin;
//!
//! let text = format!(
//!     "{}\n[reverse]\nmode = \"mixed\"\nforward_time = 0.5\n\n[[reverse.hint]]\nbody = \"M0\"\nmotion = \"stay\"\n",
//!     builtin::WORD
//! );
//! let (template, table) = parse_reverse_scene(&text, "word.toml")?;
//! assert_eq!(template.body_count(), 16);
//! assert_eq!(table.mode, RunMode::Mixed { forward_time: 0.5 });
//! assert_eq!(table.hints.len(), 1);
//!
//! let bad = text.replace("body = \"M0\"", "body = \"M99\"");
//! let err = parse_reverse_scene(&bad, "word.toml").unwrap_err();
//! assert_eq!(err.field.as_deref(), Some("body"));
//! # Ok::<(), mwb_core::scene::SceneError>(())
//! ```

use std::collections::BTreeMap;
use std::collections::HashMap;
use std::ops::Range;

use mwb_core::scene::toml_span::{Source, Table, Value};
use mwb_core::scene::{SceneError, SceneTemplate};
use nalgebra::Vector3;
use toml::de::DeValue;

use crate::run::{HintMotion, UserHint};

/// The top-level key of the table.
pub const TABLE: &str = "reverse";

/// How a reverse job uses the scene's state.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum RunMode {
    /// The state is the last frame: `[settings] end_time` seconds of backward run lead to it.
    #[default]
    Backward,
    /// The state is an intermediate frame (§5.4.4): `end_time` seconds backward lead into it,
    /// `forward_time` seconds of forward steps lead out of it.
    Mixed {
        /// Seconds simulated forward from the given state.
        forward_time: f64,
    },
}

/// The `[reverse]` table, its hints resolved to body indices.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ReverseTable {
    /// Backward or mixed.
    pub mode: RunMode,
    /// User hints by body index (scene body order), for [`crate::ReverseSettings::hints`].
    pub hints: BTreeMap<usize, UserHint>,
    /// `energy_budget`: the energy budget heuristic's fraction of the plausibility allowance
    /// ([`crate::run::Heuristics::energy_budget`]), in [0, 1]; `None`: the default
    /// ([`crate::run::DEFAULT_ENERGY_BUDGET`]). More lets bodies gain height they cannot
    /// explain, and so leave rest more (lorem's balls leave their bins), at plausibility's cost.
    pub energy_budget: Option<f64>,
}

const TABLE_KEYS: &[&str] = &["mode", "forward_time", "energy_budget", "hint"];
const HINT_KEYS: &[&str] = &["body", "motion", "direction", "release_before_end"];
const MOTIONS: &str = "\"free\", \"slide\", \"bounce\" or \"stay\"";

/// A vector and where it was written.
type SpannedVec3 = (Vector3<f64>, Range<usize>);

/// Unknown keys are errors; `explain` words the message for a key it knows is misplaced.
fn check_keys(
    part: &Table<'_>,
    allowed: &[&str],
    explain: &dyn Fn(&str) -> Option<&'static str>,
) -> Result<(), SceneError> {
    match part.unknown_key(allowed) {
        None => Ok(()),
        Some((key, span)) => {
            let msg = explain(key).map_or_else(
                || format!("unknown field; expected one of {}", allowed.join(", ")),
                str::to_owned,
            );
            Err(part.err(key, span, msg))
        }
    }
}

fn number_value(part: &Table<'_>, field: &str, v: &Value<'_>) -> Result<f64, SceneError> {
    match part.number(field, v)? {
        Some(x) if x.is_finite() && x.abs() <= mwb_core::scene::LIMIT => Ok(x),
        _ => Err(part.err(
            field,
            v.span(),
            "must be a finite number of magnitude at most 1e12",
        )),
    }
}

fn number(part: &Table<'_>, key: &str) -> Result<Option<(f64, Range<usize>)>, SceneError> {
    part.get(key)
        .map(|v| Ok((number_value(part, key, v)?, v.span())))
        .transpose()
}

fn vec3(part: &Table<'_>, key: &str) -> Result<Option<SpannedVec3>, SceneError> {
    let Some(v) = part.get(key) else {
        return Ok(None);
    };
    let DeValue::Array(items) = v.get_ref() else {
        return Err(part.err(
            key,
            v.span(),
            format!(
                "expected an array of 3 numbers, found {}",
                v.get_ref().type_str()
            ),
        ));
    };
    if items.len() != 3 {
        return Err(part.err(
            key,
            v.span(),
            format!("expected 3 numbers [x, y, z], found {}", items.len()),
        ));
    }
    let mut out = Vector3::zeros();
    for (i, item) in items.iter().enumerate() {
        out[i] = number_value(part, &format!("{key}[{i}]"), item)?;
    }
    Ok(Some((out, v.span())))
}

/// A hint as written, before its body name is resolved.
struct RawHint<'a> {
    part: Table<'a>,
    body: (&'a str, Range<usize>),
    motion: HintMotion,
    direction: Option<Range<usize>>,
    release: Option<(f64, Range<usize>)>,
}

fn motion_of(part: Table<'_>) -> Result<RawHint<'_>, SceneError> {
    check_keys(&part, HINT_KEYS, &|k| match k {
        "speed" => Some(
            "a hint has no speed: a slide's speed is sampled (Sampling::slide_speed), only its \
             direction is given",
        ),
        "start" | "release" | "release_time" | "time" => Some(
            "unknown field; the release time is `release_before_end` (seconds before the given \
             state)",
        ),
        _ => None,
    })?;
    let body = part
        .string("body")?
        .ok_or_else(|| part.missing("body", "every hint names a [[body]]"))?;
    let motion_name = part.string("motion")?;
    let direction = vec3(&part, "direction")?;
    let motion = match motion_name.as_ref().map(|(m, _)| *m).unwrap_or("free") {
        "free" => HintMotion::Free,
        "bounce" => HintMotion::Bounce,
        "stay" => HintMotion::Stay,
        "slide" => match &direction {
            Some((d, _)) => HintMotion::Slide(*d),
            None => {
                return Err(part.missing(
                    "direction",
                    "a slide hint needs the direction the body arrives along, e.g. [1, 0, 0]",
                ));
            }
        },
        other => {
            let span = motion_name.map(|(_, s)| s).unwrap_or(part.span.clone());
            return Err(part.err(
                "motion",
                span,
                format!("unknown motion \"{other}\"; expected {MOTIONS}"),
            ));
        }
    };
    if let (Some((_, span)), false) = (&direction, matches!(motion, HintMotion::Slide(_))) {
        return Err(part.err(
            "direction",
            span.clone(),
            "only a slide hint (motion = \"slide\") takes a direction",
        ));
    }
    let release = number(&part, "release_before_end")?;
    Ok(RawHint {
        body,
        motion,
        direction: direction.map(|(_, s)| s),
        release,
        part,
    })
}

/// The `[reverse]` table as written: mode, forward time and unresolved hints.
struct RawTable<'a> {
    mode: RunMode,
    energy_budget: Option<f64>,
    hints: Vec<RawHint<'a>>,
}

fn raw_table<'a>(src: Source<'a>, v: &'a Value<'a>) -> Result<RawTable<'a>, SceneError> {
    let item = "[reverse]";
    let DeValue::Table(table) = v.get_ref() else {
        return Err(src.error(
            Some(v.span()),
            Some(item.to_owned()),
            None,
            format!(
                "`reverse` must be a table, found {}",
                v.get_ref().type_str()
            ),
        ));
    };
    let part = Table::new(src, item, v.span(), table);
    check_keys(&part, TABLE_KEYS, &|k| {
        (k == "hints").then_some("unknown field (hints are [[reverse.hint]] tables)")
    })?;
    let forward = number(&part, "forward_time")?;
    let mode = match part.string("mode")? {
        None | Some(("backward", _)) => {
            if let Some((_, span)) = forward {
                return Err(part.err(
                    "forward_time",
                    span,
                    "only a mixed run (mode = \"mixed\") goes forward",
                ));
            }
            RunMode::Backward
        }
        Some(("mixed", _)) => match forward {
            Some((t, _)) if t > 0.0 => RunMode::Mixed { forward_time: t },
            Some((t, span)) => {
                return Err(part.err("forward_time", span, format!("must be > 0, found {t}")));
            }
            None => {
                return Err(part.missing(
                    "forward_time",
                    "a mixed run needs the seconds to run forward from the given state",
                ));
            }
        },
        Some((other, span)) => {
            return Err(part.err(
                "mode",
                span,
                format!("unknown mode \"{other}\"; expected \"backward\" or \"mixed\""),
            ));
        }
    };
    let energy_budget = match number(&part, "energy_budget")? {
        None => None,
        Some((b, _)) if (0.0..=1.0).contains(&b) => Some(b),
        Some((b, span)) => {
            return Err(part.err(
                "energy_budget",
                span,
                format!(
                    "must be in [0, 1] (a fraction of the {} m plausibility allowance), found {b}",
                    crate::plausible::PLAUSIBILITY_ALLOWANCE_M
                ),
            ));
        }
    };
    let mut hints = Vec::new();
    if let Some(h) = part.get("hint") {
        let DeValue::Array(items) = h.get_ref() else {
            return Err(part.err(
                "hint",
                h.span(),
                format!(
                    "expected [[reverse.hint]] tables, found {}",
                    h.get_ref().type_str()
                ),
            ));
        };
        for (i, e) in items.iter().enumerate() {
            let DeValue::Table(t) = e.get_ref() else {
                return Err(part.err(
                    "hint",
                    e.span(),
                    format!(
                        "expected a [[reverse.hint]] table, found {}",
                        e.get_ref().type_str()
                    ),
                ));
            };
            let hint = Table::new(src, format!("[[reverse.hint]] #{}", i + 1), e.span(), t);
            hints.push(motion_of(hint)?);
        }
    }
    Ok(RawTable {
        mode,
        energy_budget,
        hints,
    })
}

/// Parses a reverse scene: the ordinary scene (`docs/scene-format.md`) plus the optional
/// `[reverse]` table of the [module docs](self). `file` names the scene in errors.
pub fn parse_reverse_scene(
    text: &str,
    file: &str,
) -> Result<(SceneTemplate, ReverseTable), SceneError> {
    let src = Source { text, file };
    let doc = src.parse()?;
    let Some(value) = doc.get_ref().get(TABLE) else {
        return Ok((SceneTemplate::parse(text, file)?, ReverseTable::default()));
    };
    let raw = raw_table(src, value)?;
    // The core scene parser passes over the `reverse` key.
    let template = SceneTemplate::parse(text, file)?;
    let table = resolve(&template, raw)?;
    Ok((template, table))
}

/// Resolves hint body names to indices and checks the values against the scene.
fn resolve(template: &SceneTemplate, raw: RawTable<'_>) -> Result<ReverseTable, SceneError> {
    let index: HashMap<&str, usize> = template
        .body_names()
        .enumerate()
        .map(|(i, n)| (n, i))
        .collect();
    let s = template.settings();
    let g = Vector3::new(s.gravity[0], s.gravity[1], s.gravity[2]);
    // As the run does: "up" is against gravity, z without gravity.
    let up = (-g).try_normalize(1e-12).unwrap_or(Vector3::z());
    let mut hints = BTreeMap::new();
    for h in raw.hints {
        let p = &h.part;
        let (name, name_span) = h.body;
        let Some(&b) = index.get(name) else {
            let mut names: Vec<&str> = template.body_names().take(8).collect();
            if template.body_count() > names.len() {
                names.push("…");
            }
            return Err(p.err(
                "body",
                name_span,
                format!("unknown body \"{name}\" (bodies: {})", names.join(", ")),
            ));
        };
        if let (HintMotion::Slide(d), Some(span)) = (h.motion, &h.direction) {
            let tangential = d - up * up.dot(&d);
            if !(d.norm() > 0.0 && tangential.norm() > 1e-6 * d.norm()) {
                return Err(p.err(
                    "direction",
                    span.clone(),
                    "needs a component perpendicular to gravity: a body slides along the ground",
                ));
            }
        }
        let release_before_end = match h.release {
            None => 0.0,
            Some((t, span)) => {
                if !(0.0..=s.end_time).contains(&t) {
                    return Err(p.err(
                        "release_before_end",
                        span,
                        format!(
                            "must be in [0, [settings] end_time = {}] seconds, found {t}",
                            s.end_time
                        ),
                    ));
                }
                t
            }
        };
        let hint = UserHint {
            motion: h.motion,
            release_before_end,
        };
        if hints.insert(b, hint).is_some() {
            return Err(p.err("body", name_span, format!("body \"{name}\" has two hints")));
        }
    }
    Ok(ReverseTable {
        mode: raw.mode,
        hints,
        energy_budget: raw.energy_budget,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The word scene (bodies "M0" … "B15", y up, end_time 3 s) plus `table`: after it, or
    /// before it for a root key (`reverse = …`), which would land in the last body otherwise.
    fn word_with(table: &str) -> String {
        let word = crate::scene::builtin::WORD;
        if table.starts_with("reverse =") {
            format!("{table}\n{word}")
        } else {
            format!("{word}\n{table}")
        }
    }

    fn parse(table: &str) -> Result<ReverseTable, SceneError> {
        parse_reverse_scene(&word_with(table), "word.toml").map(|(_, t)| t)
    }

    #[test]
    fn no_table_is_a_plain_backward_run() {
        let (template, table) = parse_reverse_scene(crate::scene::builtin::WORD, "word.toml")
            .unwrap_or_else(|e| {
                panic!("{e}");
            });
        assert_eq!(template.body_count(), 16);
        assert_eq!(table, ReverseTable::default());
        assert_eq!(table.mode, RunMode::Backward);
    }

    #[test]
    fn a_full_table_maps_onto_user_hints() {
        let table = parse(
            r#"
[reverse]
mode = "mixed"
forward_time = 1.5
energy_budget = 0.25

[[reverse.hint]]
body = "M0"
motion = "slide"
direction = [1, 0.5, 0]   # the vertical part is the run's to drop
release_before_end = 0.5

[[reverse.hint]]
body = "W5"
motion = "bounce"

[[reverse.hint]]
body = "B15"
motion = "stay"

[[reverse.hint]]
body = "M1"
release_before_end = 1
"#,
        )
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(table.mode, RunMode::Mixed { forward_time: 1.5 });
        assert_eq!(table.energy_budget, Some(0.25));
        let want = [
            (0, HintMotion::Slide(Vector3::new(1.0, 0.5, 0.0)), 0.5),
            (1, HintMotion::Free, 1.0),
            (5, HintMotion::Bounce, 0.0),
            (15, HintMotion::Stay, 0.0),
        ];
        assert_eq!(table.hints.len(), want.len());
        for (b, motion, release_before_end) in want {
            assert_eq!(
                table.hints.get(&b),
                Some(&UserHint {
                    motion,
                    release_before_end
                }),
                "body {b}"
            );
        }
        // Explicit backward mode, and a hint table written before its parent.
        let t = parse(
            "[[reverse.hint]]\nbody = \"M0\"\nmotion = \"stay\"\n[reverse]\nmode = \"backward\"\n",
        )
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(t.mode, RunMode::Backward);
        assert_eq!(t.hints.len(), 1);
        assert_eq!(t.energy_budget, None, "the default budget unless written");
    }

    #[test]
    fn an_inline_table_reads_as_the_same_table() {
        let tables = [
            "[reverse]\nmode = \"mixed\"\nforward_time = 1\n[[reverse.hint]]\nbody = \"M0\"\nmotion = \"stay\"\n",
            "reverse = { mode = \"mixed\", forward_time = 1, hint = [{ body = \"M0\", motion = \"stay\" }] }",
        ];
        let [block, inline] = tables.map(|t| parse(t).unwrap_or_else(|e| panic!("{t}: {e}")));
        assert_eq!(block, inline);
        assert_eq!(block.hints.len(), 1);
    }

    #[test]
    fn scene_errors_keep_their_line_numbers() {
        // An error below the table is reported at its true line.
        let text = word_with(
            "[reverse]\nmode = \"mixed\"\nforward_time = 1\n\n[[body]]\nname = \"late\"\nshape = \"box\"\nsize = [1, 1, 1]\nmaterial = \"wod\"\n",
        );
        let line = text
            .lines()
            .position(|l| l.contains("\"wod\""))
            .map(|l| l + 1);
        let e = parse_reverse_scene(&text, "word.toml")
            .err()
            .unwrap_or_else(|| panic!("accepted"));
        assert_eq!(e.line, line, "{e}");
        assert_eq!(e.field.as_deref(), Some("material"), "{e}");
    }

    #[test]
    fn every_bad_value_is_refused_naming_its_field() {
        let hint = |body: &str| format!("[reverse]\n[[reverse.hint]]\nbody = \"M0\"\n{body}\n");
        let cases: Vec<(&str, String, &str, &str)> = vec![
            (
                "mode",
                "[reverse]\nmode = \"sideways\"".into(),
                "mode",
                "unknown mode",
            ),
            (
                "mode type",
                "[reverse]\nmode = 1".into(),
                "mode",
                "expected a string",
            ),
            (
                "mixed without forward_time",
                "[reverse]\nmode = \"mixed\"".into(),
                "forward_time",
                "missing",
            ),
            (
                "forward_time 0",
                "[reverse]\nmode = \"mixed\"\nforward_time = 0".into(),
                "forward_time",
                "> 0",
            ),
            (
                "forward_time NaN",
                "[reverse]\nmode = \"mixed\"\nforward_time = nan".into(),
                "forward_time",
                "finite",
            ),
            (
                "forward_time text",
                "[reverse]\nmode = \"mixed\"\nforward_time = \"1\"".into(),
                "forward_time",
                "expected a number",
            ),
            (
                "forward_time in backward",
                "[reverse]\nforward_time = 1".into(),
                "forward_time",
                "only a mixed run",
            ),
            (
                "energy_budget negative",
                "[reverse]\nenergy_budget = -0.1".into(),
                "energy_budget",
                "must be in [0, 1]",
            ),
            (
                "energy_budget above the allowance",
                "[reverse]\nenergy_budget = 2".into(),
                "energy_budget",
                "must be in [0, 1]",
            ),
            (
                "energy_budget text",
                "[reverse]\nenergy_budget = \"some\"".into(),
                "energy_budget",
                "expected a number",
            ),
            (
                "unknown key",
                "[reverse]\nmood = \"mixed\"".into(),
                "mood",
                "unknown field",
            ),
            (
                "hints plural",
                "[reverse]\nhints = []".into(),
                "hints",
                "[[reverse.hint]]",
            ),
            (
                "hint not tables",
                "[reverse]\nhint = 3".into(),
                "hint",
                "expected [[reverse.hint]]",
            ),
            (
                "no body",
                "[reverse]\n[[reverse.hint]]\nmotion = \"stay\"".into(),
                "body",
                "missing",
            ),
            (
                "body type",
                "[reverse]\n[[reverse.hint]]\nbody = 0".into(),
                "body",
                "expected a string",
            ),
            (
                "unknown body",
                "[reverse]\n[[reverse.hint]]\nbody = \"Q7\"".into(),
                "body",
                "unknown body \"Q7\"",
            ),
            (
                "two hints",
                format!("{}[[reverse.hint]]\nbody = \"M0\"\n", hint("")),
                "body",
                "two hints",
            ),
            (
                "motion",
                hint("motion = \"fly\""),
                "motion",
                "unknown motion \"fly\"",
            ),
            (
                "slide without direction",
                hint("motion = \"slide\""),
                "direction",
                "missing",
            ),
            (
                "direction on stay",
                hint("motion = \"stay\"\ndirection = [1, 0, 0]"),
                "direction",
                "only a slide",
            ),
            (
                "direction length",
                hint("motion = \"slide\"\ndirection = [1, 0]"),
                "direction",
                "3 numbers",
            ),
            (
                "direction entry",
                hint("motion = \"slide\"\ndirection = [1, \"x\", 0]"),
                "direction[1]",
                "expected a number",
            ),
            (
                "direction vertical",
                hint("motion = \"slide\"\ndirection = [0, -2, 0]"),
                "direction",
                "perpendicular to gravity",
            ),
            (
                "direction zero",
                hint("motion = \"slide\"\ndirection = [0, 0, 0]"),
                "direction",
                "perpendicular",
            ),
            (
                "speed",
                hint("motion = \"slide\"\ndirection = [1, 0, 0]\nspeed = 2"),
                "speed",
                "sampled",
            ),
            ("start", hint("start = 0.5"), "start", "release_before_end"),
            (
                "release negative",
                hint("release_before_end = -1"),
                "release_before_end",
                "[0,",
            ),
            (
                "release past the run",
                hint("release_before_end = 3.5"),
                "release_before_end",
                "end_time",
            ),
            (
                "not a table",
                "reverse = \"mixed\"".into(),
                "",
                "must be a table",
            ),
        ];
        for (what, table, field, message) in cases {
            let e = match parse(&table) {
                Ok(t) => panic!("{what}: accepted as {t:?}"),
                Err(e) => e,
            };
            let text = e.to_string();
            assert_eq!(e.field.as_deref().unwrap_or(""), field, "{what}: {text}");
            assert!(text.contains(message), "{what}: {text}");
            assert!(text.starts_with("word.toml:"), "{what}: {text}");
            assert!(e.line.is_some(), "{what}: {text}");
        }
    }
}
