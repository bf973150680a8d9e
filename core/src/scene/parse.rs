//! TOML → [`SceneTemplate`]: a walk over the span-annotated document of the toml crate that
//! checks every key and every number as it goes, so each refusal names the item, the field and
//! the line (DESIGN.md "Bad input and faults").
//!
//! We walk `toml::de::DeTable` by hand instead of deriving `Deserialize`: serde's errors know
//! neither which body they are in nor, for validation that happens after deserialising, where in
//! the file the offending value was.

use std::collections::{HashMap, HashSet};
use std::ops::Range;

use toml::de::{DeTable, DeValue};

use super::error::SceneError;
use super::generators::{Layout, MAX_INSTANCES};
use super::model::{BodyRef, CcdPolicy, Settings, SimPreset, Vec3};
use super::template::{
    BodyT, Dist, JointKindT, JointT, MaterialT, Num, NumVec3, PartT, RotationT, SceneTemplate,
    ShapeT,
};
// An item of the scene (`body "ball"`, `settings`, …) is a table of the shared reader.
use super::toml_span::{Source, Table as Item, Value as Val};

/// Largest magnitude of any number in a scene. Far beyond anything physical, and small enough
/// that squares and products downstream (inertia, bounding radii) stay finite.
pub const LIMIT: f64 = 1e12;

/// A `normal` distribution is cut (clamped) at mu ± this many sigma.
pub const NORMAL_CUT_SIGMAS: f64 = 4.0;

/// Smallest component magnitude that makes a sampled direction (plane normal, axis,
/// quaternion) certainly non-zero.
const MIN_DIRECTION: f64 = 1e-6;

/// The valid values of a numeric field.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Valid {
    /// Any finite number with |x| ≤ LIMIT.
    Any,
    /// Sizes and densities: > 0.
    Positive,
    /// Friction, damping, thresholds: ≥ 0.
    NonNegative,
    /// Restitution, α: in [0, 1].
    Unit,
}

impl Valid {
    fn contains(self, x: f64) -> bool {
        x.is_finite()
            && x.abs() <= LIMIT
            && match self {
                Valid::Any => true,
                Valid::Positive => x > 0.0,
                Valid::NonNegative => x >= 0.0,
                Valid::Unit => (0.0..=1.0).contains(&x),
            }
    }

    fn describe(self) -> &'static str {
        match self {
            Valid::Any => "a finite number of magnitude at most 1e12",
            Valid::Positive => "> 0",
            Valid::NonNegative => ">= 0",
            Valid::Unit => "in [0, 1]",
        }
    }
}

const SHAPES: &[&str] = &[
    "box", "sphere", "capsule", "cylinder", "convex", "plane", "trimesh", "compound",
];

fn shape_keys(shape: &str) -> &'static [&'static str] {
    match shape {
        "box" => &["size", "half_extents"],
        "sphere" => &["radius"],
        "capsule" | "cylinder" => &["radius", "height", "half_height"],
        "convex" => &["points"],
        "plane" => &["normal"],
        "trimesh" => &["vertices", "indices"],
        "compound" => &["part"],
        _ => &[],
    }
}

const ALL_SHAPE_KEYS: &[&str] = &[
    "size",
    "half_extents",
    "radius",
    "height",
    "half_height",
    "points",
    "normal",
    "vertices",
    "indices",
    "part",
];
/// Keys of one part of a compound (besides its shape's own keys).
const PART_KEYS: &[&str] = &[
    "shape",
    "material",
    "position",
    "rotation_deg",
    "axis_angle",
    "quat",
];
const STATIC_KEYS: &[&str] = &[
    "name",
    "shape",
    "material",
    "position",
    "rotation_deg",
    "axis_angle",
    "quat",
    "grid",
    "row",
    "stack",
];
const MOTION_KEYS: &[&str] = &["linvel", "angvel"];
const ROTATION_KEYS: &[&str] = &["rotation_deg", "axis_angle", "quat"];
const LAYOUT_KEYS: &[&str] = &["grid", "row", "stack"];
const SETTINGS_KEYS: &[&str] = &[
    "dt",
    "end_time",
    "gravity",
    "rest_linear",
    "rest_angular",
    "rest_hold",
    "solver_iterations",
    "alpha",
    "cos_exponent",
    "c_v",
    "c_omega",
    "segment_seconds",
    "linear_damping",
    "angular_damping",
    "sim",
    "pgs_iterations",
    "stabilization_iterations",
    "ccd",
    "prediction_distance",
    "sleep",
    "length_unit",
    "max_speed",
    "tolerance",
];

/// Levenshtein distance, for "did you mean" hints on typos.
fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut row: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut prev = row[0];
        row[0] = i + 1;
        for (j, cb) in b.iter().enumerate() {
            let cur = row[j + 1];
            row[j + 1] = (prev + usize::from(ca != *cb)).min(row[j] + 1).min(cur + 1);
            prev = cur;
        }
    }
    row[b.len()]
}

fn suggestion<'c>(word: &str, candidates: impl IntoIterator<Item = &'c str>) -> String {
    candidates
        .into_iter()
        .map(|c| (edit_distance(word, c), c))
        .filter(|(d, c)| *d <= 2.max(c.len() / 3))
        .min()
        .map(|(_, c)| format!(" (did you mean \"{c}\"?)"))
        .unwrap_or_default()
}

impl<'a> Item<'a> {
    fn sub(&self, key: &str, val: &'a Val<'a>) -> Result<Item<'a>, SceneError> {
        match val.get_ref() {
            DeValue::Table(t) => Ok(Item {
                src: self.src,
                label: self.label.clone(),
                prefix: format!("{}{key}.", self.prefix),
                span: val.span(),
                table: t,
            }),
            other => Err(self.err(
                key,
                val.span(),
                format!("expected a table, found {}", other.type_str()),
            )),
        }
    }

    /// Unknown keys are errors (they are almost always typos). `misplaced` explains keys that
    /// are valid elsewhere but not here; the earliest offending key in the file is reported.
    fn check_keys(
        &self,
        allowed: &[&str],
        misplaced: &dyn Fn(&str) -> Option<String>,
    ) -> Result<(), SceneError> {
        if let Some((key, span)) = self.unknown_key(allowed) {
            let msg = misplaced(key).unwrap_or_else(|| {
                format!("unknown field{}", suggestion(key, allowed.iter().copied()))
            });
            return Err(self.err(key, span, msg));
        }
        Ok(())
    }

    fn required_string(
        &self,
        key: &str,
        what: &str,
    ) -> Result<(&'a str, Range<usize>), SceneError> {
        self.string(key)?.ok_or_else(|| self.missing(key, what))
    }

    /// A plain number (no distribution), e.g. in `[settings]` or a generator layout.
    fn plain(&self, key: &str, valid: Valid, default: Option<f64>) -> Result<f64, SceneError> {
        match self.get(key) {
            None => default.ok_or_else(|| self.missing(key, "")),
            Some(v) => {
                let n = self.num_value(key, v, valid, false)?;
                Ok(n.lo)
            }
        }
    }

    fn plain3(&self, key: &str, valid: Valid, default: Option<Vec3>) -> Result<Vec3, SceneError> {
        match self.get(key) {
            None => default.ok_or_else(|| self.missing(key, "")),
            Some(v) => {
                let n = self.vec_value::<3>(key, v, valid, false)?;
                Ok(n.map(|c| c.lo))
            }
        }
    }

    fn integer(
        &self,
        key: &str,
        min: u64,
        max: u64,
        default: Option<u64>,
    ) -> Result<u64, SceneError> {
        match self.get(key) {
            None => default.ok_or_else(|| self.missing(key, "")),
            Some(v) => self.integer_value(key, v, min, max),
        }
    }

    fn integer_value(
        &self,
        path: &str,
        v: &Val<'_>,
        min: u64,
        max: u64,
    ) -> Result<u64, SceneError> {
        let n = match v.get_ref() {
            DeValue::Integer(i) => i64::from_str_radix(i.as_str(), i.radix()).ok(),
            other => {
                return Err(self.err(
                    path,
                    v.span(),
                    format!("expected an integer, found {}", other.type_str()),
                ));
            }
        };
        match n.and_then(|n| u64::try_from(n).ok()) {
            Some(n) if (min..=max).contains(&n) => Ok(n),
            _ => Err(self.err(
                path,
                v.span(),
                format!("must be an integer in [{min}, {max}]"),
            )),
        }
    }

    /// A number or a distribution, valid for every possible sample.
    fn num(&self, key: &str, valid: Valid, default: Option<f64>) -> Result<Num, SceneError> {
        match self.get(key) {
            None => default.map(Num::fixed).ok_or_else(|| self.missing(key, "")),
            Some(v) => self.num_value(key, v, valid, true),
        }
    }

    fn num3(&self, key: &str, valid: Valid, default: Option<Vec3>) -> Result<NumVec3, SceneError> {
        match self.get(key) {
            None => default
                .map(|d| d.map(Num::fixed))
                .ok_or_else(|| self.missing(key, "")),
            Some(v) => self.vec_value::<3>(key, v, valid, true),
        }
    }

    fn vec_value<const N: usize>(
        &self,
        path: &str,
        v: &Val<'_>,
        valid: Valid,
        random: bool,
    ) -> Result<[Num; N], SceneError> {
        let DeValue::Array(items) = v.get_ref() else {
            return Err(self.err(
                path,
                v.span(),
                format!(
                    "expected an array of {N} numbers, found {}",
                    v.get_ref().type_str()
                ),
            ));
        };
        if items.len() != N {
            return Err(self.err(
                path,
                v.span(),
                format!("expected {N} numbers, found {}", items.len()),
            ));
        }
        let mut out = [Num::fixed(0.0); N];
        for (i, (slot, item)) in out.iter_mut().zip(items.iter()).enumerate() {
            *slot = self.num_value(&format!("{path}[{i}]"), item, valid, random)?;
        }
        Ok(out)
    }

    fn plain_number(&self, path: &str, v: &Val<'_>) -> Result<f64, SceneError> {
        let x = self.number(path, v)?;
        let x = x.ok_or_else(|| self.err(path, v.span(), "not a representable number"))?;
        if !x.is_finite() {
            return Err(self.err(path, v.span(), format!("must be finite, found {x}")));
        }
        Ok(x)
    }

    /// The heart of the distribution rules (docs/scene-format.md "Distributions"):
    /// * `uniform = [a, b]`: a ≤ b, both valid for the field;
    /// * `normal = [mu, sigma]`: sigma ≥ 0 and mu ± 4σ valid for the field;
    /// * every sample is clamped into its distribution's interval ([a, b] or mu ± 4σ), which
    ///   therefore lies inside the valid range: every world is a valid scene.
    fn num_value(
        &self,
        path: &str,
        v: &Val<'_>,
        valid: Valid,
        random: bool,
    ) -> Result<Num, SceneError> {
        let table = match v.get_ref() {
            DeValue::Table(t) => t,
            DeValue::Integer(_) | DeValue::Float(_) => {
                let x = self.plain_number(path, v)?;
                if !valid.contains(x) {
                    return Err(self.err(
                        path,
                        v.span(),
                        format!("must be {}, found {x}", valid.describe()),
                    ));
                }
                return Ok(Num::fixed(x));
            }
            other => {
                let also = if random { " or a distribution" } else { "" };
                return Err(self.err(
                    path,
                    v.span(),
                    format!("expected a number{also}, found {}", other.type_str()),
                ));
            }
        };
        if !random {
            return Err(self.err(
                path,
                v.span(),
                "must be a plain number (distributions are not allowed here)",
            ));
        }
        let shape_msg = "a distribution is `{ uniform = [a, b] }` or `{ normal = [mu, sigma] }`";
        let mut entries = table.iter();
        let (Some((k, params)), None) = (entries.next(), entries.next()) else {
            return Err(self.err(path, v.span(), shape_msg));
        };
        let kind = k.get_ref().as_ref();
        if kind != "uniform" && kind != "normal" {
            return Err(self.err(
                path,
                k.span(),
                format!(
                    "unknown distribution \"{kind}\"{}; {shape_msg}",
                    suggestion(kind, ["uniform", "normal"])
                ),
            ));
        }
        let pair = match params.get_ref() {
            DeValue::Array(a) if a.len() == 2 => a,
            _ => {
                return Err(self.err(
                    path,
                    params.span(),
                    format!("`{kind}` takes two numbers: {shape_msg}"),
                ));
            }
        };
        let p0 = self.plain_number(path, &pair[0])?;
        let p1 = self.plain_number(path, &pair[1])?;
        let range_err = |lo: f64, hi: f64, what: &str| {
            self.err(path, params.span(), format!("{kind} [{p0}, {p1}]: {what} [{lo}, {hi}] must be {} (samples are clamped to it)", valid.describe()))
        };
        if kind == "uniform" {
            if p0 > p1 {
                return Err(self.err(
                    path,
                    params.span(),
                    format!("uniform [{p0}, {p1}]: needs a <= b"),
                ));
            }
            if !valid.contains(p0) || !valid.contains(p1) {
                return Err(range_err(p0, p1, "the interval"));
            }
            Ok(Num {
                dist: Dist::Uniform(p0, p1),
                lo: p0,
                hi: p1,
            })
        } else {
            if p1 < 0.0 {
                return Err(self.err(
                    path,
                    params.span(),
                    format!("normal [{p0}, {p1}]: sigma must be >= 0"),
                ));
            }
            let lo = p0 - NORMAL_CUT_SIGMAS * p1;
            let hi = p0 + NORMAL_CUT_SIGMAS * p1;
            if !valid.contains(lo) || !valid.contains(hi) {
                return Err(range_err(lo, hi, "mu ± 4 sigma ="));
            }
            Ok(Num {
                dist: Dist::Normal(p0, p1),
                lo,
                hi,
            })
        }
    }

    /// A direction (plane normal, axis, quaternion) must be non-zero in every world: one
    /// component must be bounded away from zero, or, when all are plain numbers, the vector
    /// must have a non-negligible length.
    fn check_direction(&self, key: &str, v: &[Num]) -> Result<(), SceneError> {
        let certain = if v.iter().all(|n| !n.is_random()) {
            v.iter().map(|n| n.lo * n.lo).sum::<f64>().sqrt() >= MIN_DIRECTION
        } else {
            v.iter()
                .any(|n| n.lo >= MIN_DIRECTION || n.hi <= -MIN_DIRECTION)
        };
        if certain {
            Ok(())
        } else {
            let span = self.get(key).map_or(self.span.clone(), |v| v.span());
            Err(self.err(key, span, "must be a non-zero direction in every world (with distributions: one component must exclude 0)"))
        }
    }

    fn points(&self, key: &str) -> Result<Vec<Vec3>, SceneError> {
        let v = self
            .get(key)
            .ok_or_else(|| self.missing(key, "a list of [x, y, z] points"))?;
        let DeValue::Array(items) = v.get_ref() else {
            return Err(self.err(
                key,
                v.span(),
                format!(
                    "expected an array of [x, y, z] points, found {}",
                    v.get_ref().type_str()
                ),
            ));
        };
        items
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let n = self.vec_value::<3>(&format!("{key}[{i}]"), p, Valid::Any, false)?;
                Ok(n.map(|c| c.lo))
            })
            .collect()
    }
}

/// Names users give: non-empty, not `world` (the joint keyword), and without brackets, which are
/// reserved for generated names such as `block[3,1,2]` (so the two can never collide).
fn check_name(item: &Item<'_>, name: &str, span: Range<usize>) -> Result<(), SceneError> {
    if name.trim().is_empty() {
        return Err(item.err("name", span, "must not be empty"));
    }
    if name == "world" {
        return Err(item.err(
            "name",
            span,
            "\"world\" is reserved for joints to the world frame",
        ));
    }
    if name.contains(['[', ']']) || name.chars().any(char::is_control) {
        return Err(item.err("name", span, "must not contain '[', ']' or control characters (brackets are reserved for generated names)"));
    }
    Ok(())
}

/// The elements of an array of tables (`[[body]]`), with their spans.
fn tables<'a>(
    root: &Item<'a>,
    key: &str,
) -> Result<Vec<(&'a DeTable<'a>, Range<usize>)>, SceneError> {
    let Some(v) = root.get(key) else {
        return Ok(Vec::new());
    };
    let DeValue::Array(items) = v.get_ref() else {
        return Err(root.err(
            key,
            v.span(),
            format!(
                "expected an array of tables `[[{key}]]`, found {}",
                v.get_ref().type_str()
            ),
        ));
    };
    items
        .iter()
        .map(|e| match e.get_ref() {
            DeValue::Table(t) => Ok((t, e.span())),
            other => Err(root.err(
                key,
                e.span(),
                format!("expected a table, found {}", other.type_str()),
            )),
        })
        .collect()
}

pub(crate) fn parse(src: Source<'_>) -> Result<SceneTemplate, SceneError> {
    let doc = src.parse()?;
    let root = Item::new(src, "scene", 0..0, doc.get_ref());
    // `reverse`: the backward-run table of a final-state scene, read and validated by
    // mwb-reverse (`settings_toml`); every other reader (samplers, the store's rest thresholds,
    // `mwb scene`) ignores it.
    root.check_keys(&["name", "description", "settings", "material", "static", "body", "joint", "reverse"], &|k| {
        matches!(k, "materials" | "statics" | "bodies" | "joints").then(|| {
            "unknown table (tables are singular: [[material]], [[static]], [[body]], [[joint]])".to_owned()
        })
    })?;
    let (name, name_span) = root.required_string("name", "every scene needs `name = \"...\"`")?;
    if name.trim().is_empty() {
        return Err(root.err("name", name_span, "must not be empty"));
    }
    let description = root
        .string("description")?
        .map_or(String::new(), |(d, _)| d.to_owned());

    let settings = match root.get("settings") {
        None => Settings::default(),
        Some(v) => {
            let mut s = root.sub("settings", v)?;
            s.label = "settings".to_owned();
            s.prefix.clear();
            parse_settings(&s)?
        }
    };

    let mut materials = Vec::new();
    let mut material_index: HashMap<String, usize> = HashMap::new();
    for (i, (table, span)) in tables(&root, "material")?.into_iter().enumerate() {
        let mut item = Item::new(src, format!("material #{}", i + 1), span, table);
        let (name, name_span) = item.required_string("name", "every material needs a `name`")?;
        item.label = format!("material \"{name}\"");
        check_name(&item, name, name_span.clone())?;
        item.check_keys(&["name", "friction", "restitution", "density"], &|_| None)?;
        if material_index
            .insert(name.to_owned(), materials.len())
            .is_some()
        {
            return Err(item.err("name", name_span, format!("duplicate material \"{name}\"")));
        }
        materials.push(MaterialT {
            name: name.to_owned(),
            friction: item.num("friction", Valid::NonNegative, Some(0.5))?,
            restitution: item.num("restitution", Valid::Unit, Some(0.0))?,
            density: item.num("density", Valid::Positive, Some(1000.0))?,
        });
    }

    // Each body's and static's name with the byte offset where it was written: the line of a
    // duplicate's first use is worked out only when a duplicate is reported (a line per body
    // would make a big scene quadratic: issue 18).
    let mut names: HashMap<&str, usize> = HashMap::new();
    let mut instances: u64 = 0;
    let mut statics = Vec::new();
    for (i, (table, span)) in tables(&root, "static")?.into_iter().enumerate() {
        let item = Item::new(src, format!("static #{}", i + 1), span, table);
        statics.push(parse_body(
            item,
            false,
            &material_index,
            &mut names,
            &mut instances,
        )?);
    }
    let mut bodies = Vec::new();
    for (i, (table, span)) in tables(&root, "body")?.into_iter().enumerate() {
        let item = Item::new(src, format!("body #{}", i + 1), span, table);
        bodies.push(parse_body(
            item,
            true,
            &material_index,
            &mut names,
            &mut instances,
        )?);
    }

    let mut body_index: HashMap<&str, usize> = HashMap::new();
    for (index, p) in bodies
        .iter()
        .flat_map(|b: &BodyT| &b.placements)
        .enumerate()
    {
        body_index.insert(p.name.as_str(), index);
    }
    let static_names: HashSet<&str> = statics
        .iter()
        .flat_map(|b: &BodyT| &b.placements)
        .map(|p| p.name.as_str())
        .collect();
    let mut joints: Vec<JointT> = Vec::new();
    let mut joint_names: HashSet<&str> = HashSet::new();
    for (i, (table, span)) in tables(&root, "joint")?.into_iter().enumerate() {
        let mut item = Item::new(src, format!("joint #{}", i + 1), span, table);
        let (name, name_span) = item.required_string("name", "every joint needs a `name`")?;
        item.label = format!("joint \"{name}\"");
        check_name(&item, name, name_span.clone())?;
        if !joint_names.insert(name) {
            return Err(item.err("name", name_span, format!("duplicate joint \"{name}\"")));
        }
        joints.push(parse_joint(&item, name, &body_index, &static_names)?);
    }

    Ok(SceneTemplate {
        name: name.to_owned(),
        description,
        settings,
        materials,
        statics,
        bodies,
        joints,
    })
}

fn parse_settings(s: &Item<'_>) -> Result<Settings, SceneError> {
    s.check_keys(SETTINGS_KEYS, &|_| None)?;
    let d = Settings::default();
    let dt = s.plain("dt", Valid::Positive, Some(d.dt))?;
    if dt > 0.1 {
        return Err(s.err(
            "dt",
            span_of(s, "dt"),
            format!("must be at most 0.1 s, found {dt}"),
        ));
    }
    let end_time = s.plain("end_time", Valid::Positive, Some(d.end_time))?;
    if end_time < dt {
        return Err(s.err(
            "end_time",
            span_of(s, "end_time"),
            format!("must be at least one step (dt = {dt}), found {end_time}"),
        ));
    }
    if end_time / dt > 1e7 {
        return Err(s.err(
            "end_time",
            span_of(s, "end_time"),
            format!("end_time / dt = {:.0} steps; at most 1e7", end_time / dt),
        ));
    }
    let segment_seconds = s.plain("segment_seconds", Valid::Positive, Some(d.segment_seconds))?;
    if segment_seconds < dt {
        return Err(s.err(
            "segment_seconds",
            span_of(s, "segment_seconds"),
            format!("must be at least one step (dt = {dt})"),
        ));
    }
    // The preset first, then every key written in the scene over it.
    let sim = match s.string("sim")? {
        None => d.sim,
        Some((name, span)) => SimPreset::from_name(name).ok_or_else(|| {
            s.err(
                "sim",
                span,
                format!(
                    "unknown preset {name:?}: one of draft, standard, final, reference, auto{}",
                    suggestion(name, ["draft", "standard", "final", "reference", "auto"])
                ),
            )
        })?,
    };
    let p = sim.apply(&d);
    let iterations = |key: &str, default: u32| -> Result<u32, SceneError> {
        Ok(u32::try_from(s.integer(key, 1, 1000, Some(u64::from(default)))?).unwrap_or(default))
    };
    let ccd = match s.string("ccd")? {
        None => p.ccd,
        Some((name, span)) => CcdPolicy::from_name(name).ok_or_else(|| {
            s.err(
                "ccd",
                span,
                format!("unknown CCD policy {name:?}: one of auto, all, off"),
            )
        })?,
    };
    let sleep = match s.get("sleep") {
        None => p.sleep,
        Some(v) => match v.get_ref() {
            DeValue::Boolean(b) => *b,
            other => {
                return Err(s.err(
                    "sleep",
                    v.span(),
                    format!("expected true or false, found {}", other.type_str()),
                ));
            }
        },
    };
    let optional_positive = |key: &str| -> Result<Option<f64>, SceneError> {
        match s.get(key) {
            None => Ok(None),
            Some(_) => s.plain(key, Valid::Positive, None).map(Some),
        }
    };
    // The reference steps 8× per frame (`SimPreset::apply`).
    let dt = if sim == SimPreset::Reference {
        dt / f64::from(super::model::REFERENCE_STEPS_PER_FRAME)
    } else {
        dt
    };
    Ok(Settings {
        dt,
        end_time,
        gravity: s.plain3("gravity", Valid::Any, Some(d.gravity))?,
        rest_linear: s.plain("rest_linear", Valid::NonNegative, Some(d.rest_linear))?,
        rest_angular: s.plain("rest_angular", Valid::NonNegative, Some(d.rest_angular))?,
        rest_hold: s.plain("rest_hold", Valid::NonNegative, Some(d.rest_hold))?,
        solver_iterations: iterations("solver_iterations", p.solver_iterations)?,
        alpha: s.plain("alpha", Valid::Unit, Some(d.alpha))?,
        cos_exponent: s.plain("cos_exponent", Valid::NonNegative, Some(d.cos_exponent))?,
        c_v: s.plain("c_v", Valid::Positive, Some(d.c_v))?,
        c_omega: s.plain("c_omega", Valid::Positive, Some(d.c_omega))?,
        segment_seconds,
        linear_damping: s.plain("linear_damping", Valid::NonNegative, Some(d.linear_damping))?,
        angular_damping: s.plain(
            "angular_damping",
            Valid::NonNegative,
            Some(d.angular_damping),
        )?,
        sim,
        pgs_iterations: iterations("pgs_iterations", p.pgs_iterations)?,
        stabilization_iterations: iterations(
            "stabilization_iterations",
            p.stabilization_iterations,
        )?,
        ccd,
        prediction_distance: match s.get("prediction_distance") {
            None => None,
            Some(_) => Some(s.plain("prediction_distance", Valid::NonNegative, None)?),
        },
        sleep,
        length_unit: optional_positive("length_unit")?,
        max_speed: optional_positive("max_speed")?,
        tolerance: optional_positive("tolerance")?,
    })
}

fn span_of(item: &Item<'_>, key: &str) -> Range<usize> {
    item.get(key).map_or(item.span.clone(), |v| v.span())
}

/// A `[[body]]` (dynamic) or `[[static]]` entry, with its generator if it has one.
fn parse_body<'a>(
    mut item: Item<'a>,
    dynamic: bool,
    materials: &HashMap<String, usize>,
    names: &mut HashMap<&'a str, usize>,
    instances: &mut u64,
) -> Result<BodyT, SceneError> {
    let kind = if dynamic { "body" } else { "static" };
    let (name, name_span) =
        item.required_string("name", &format!("every {kind} needs a `name`"))?;
    // Label a generator's template by its instance pattern: an error there holds for all of them.
    let pattern = if item.get("grid").is_some() {
        "[i,j,k]"
    } else if item.get("row").is_some() {
        "[i]"
    } else if item.get("stack").is_some() {
        "[layer,i]"
    } else {
        ""
    };
    item.label = format!("{kind} \"{name}{pattern}\"");
    check_name(&item, name, name_span.clone())?;
    if let Some(&first) = names.get(name) {
        let first = item.src.line_of(first);
        return Err(item.err(
            "name",
            name_span,
            format!("duplicate name \"{name}\" (first used on line {first})"),
        ));
    }
    names.insert(name, name_span.start);

    let (shape_name, shape_span) =
        item.required_string("shape", &format!("one of {}", SHAPES.join(", ")))?;
    if shape_name == "mesh" {
        // This parser reads no files: mesh shapes are replaced by inline geometry before a scene
        // gets here (mwb-mesh's resolve step, which every command's scene loading runs).
        return Err(item.err(
            "shape",
            shape_span,
            "a mesh is read from its file when the scene is loaded (mwb_mesh::resolve, run by \
             every mwb command); this text was not resolved",
        ));
    }
    if !SHAPES.contains(&shape_name) {
        return Err(item.err(
            "shape",
            shape_span,
            format!(
                "unknown shape \"{shape_name}\"; expected one of {}{}",
                SHAPES.join(", "),
                suggestion(shape_name, SHAPES.iter().copied())
            ),
        ));
    }
    if dynamic && matches!(shape_name, "plane" | "trimesh") {
        return Err(item.err(
            "shape",
            shape_span,
            format!("shape \"{shape_name}\" can only be static (declare it as [[static]])"),
        ));
    }
    let own_keys = shape_keys(shape_name);
    let mut allowed: Vec<&str> = STATIC_KEYS.iter().chain(own_keys).copied().collect();
    if dynamic {
        allowed.extend(MOTION_KEYS);
    }
    item.check_keys(&allowed, &|k| {
        if ALL_SHAPE_KEYS.contains(&k) {
            Some(if shape_name == "compound" {
                format!("a compound's shapes are written in its parts ([[{kind}.part]] tables), not on the {kind}")
            } else {
                format!(
                    "does not apply to shape \"{shape_name}\" (it takes {})",
                    own_keys.join(", ")
                )
            })
        } else if !dynamic && MOTION_KEYS.contains(&k) {
            Some("statics do not move; velocities apply to [[body]] only".to_owned())
        } else {
            None
        }
    })?;

    let (shape, material) = if shape_name == "compound" {
        let parts = parse_parts(&item, kind, dynamic, materials)?;
        // The body's material is the default of its parts; it may be left out when every part
        // names its own (the body then reports its first part's).
        let own = parts
            .iter()
            .map(|(_, m)| *m)
            .collect::<Option<Vec<usize>>>();
        let material = match (item.get("material"), own.as_deref()) {
            (None, Some([first, ..])) => *first,
            _ => body_material(
                &item,
                materials,
                " (the material of every part that names none)",
            )?,
        };
        let parts = parts
            .into_iter()
            .map(|(p, m)| PartT {
                material: m.unwrap_or(material),
                ..p
            })
            .collect();
        (ShapeT::Compound { parts }, material)
    } else {
        let shape = parse_shape(&item, shape_name)?;
        (shape, body_material(&item, materials, "")?)
    };

    let position = item.num3("position", Valid::Any, Some([0.0; 3]))?;
    let rotation = parse_rotation(&item)?;
    let zero = Some([0.0; 3]);
    let (linvel, angvel) = if dynamic {
        (
            item.num3("linvel", Valid::Any, zero)?,
            item.num3("angvel", Valid::Any, zero)?,
        )
    } else {
        ([Num::fixed(0.0); 3], [Num::fixed(0.0); 3])
    };

    let (layout, layout_key) = parse_layout(&item)?;
    *instances = instances.saturating_add(layout.count());
    if *instances > MAX_INSTANCES {
        let (field, span) = match layout_key {
            Some(k) => (k, span_of(&item, k)),
            None => ("name", name_span),
        };
        return Err(item.err(
            field,
            span,
            format!("the scene would expand to more than {MAX_INSTANCES} bodies and statics"),
        ));
    }
    let placements = layout.placements(name);
    Ok(BodyT {
        shape,
        material,
        position,
        rotation,
        linvel,
        angvel,
        placements,
    })
}

/// The `material` of a body, static or part: the index of a `[[material]]` by name. `what_for`
/// is added to the message when it is missing.
fn body_material(
    item: &Item<'_>,
    materials: &HashMap<String, usize>,
    what_for: &str,
) -> Result<usize, SceneError> {
    let (name, span) =
        item.required_string("material", &format!("the name of a [[material]]{what_for}"))?;
    material_index(item, materials, name, span)
}

fn material_index(
    item: &Item<'_>,
    materials: &HashMap<String, usize>,
    name: &str,
    span: Range<usize>,
) -> Result<usize, SceneError> {
    materials.get(name).copied().ok_or_else(|| {
        item.err(
            "material",
            span,
            format!(
                "unknown material \"{name}\"{}",
                suggestion(name, materials.keys().map(String::as_str))
            ),
        )
    })
}

/// The parts of a compound `item` (`[[body.part]]` tables, or an inline `part = [{ … }, …]`),
/// each with its own material if it names one. Every refusal names the part: `part[1].radius`.
/// A part is written like a body's shape (`shape` and its keys), placed by `position` and one
/// of the rotation keys in the body's frame; it may not be a compound, a plane, or (in a
/// dynamic body) a triangle mesh.
fn parse_parts(
    item: &Item<'_>,
    kind: &str,
    dynamic: bool,
    materials: &HashMap<String, usize>,
) -> Result<Vec<(PartT, Option<usize>)>, SceneError> {
    let tables = format!("[[{kind}.part]]");
    let v = item.get("part").ok_or_else(|| {
        item.missing(
            "part",
            &format!("a compound needs its shapes, each in a {tables} table"),
        )
    })?;
    let DeValue::Array(items) = v.get_ref() else {
        return Err(item.err(
            "part",
            v.span(),
            format!(
                "expected an array of tables {tables}, found {}",
                v.get_ref().type_str()
            ),
        ));
    };
    if items.is_empty() {
        return Err(item.err("part", v.span(), "a compound needs at least one part"));
    }
    let mut out = Vec::with_capacity(items.len());
    for (i, pv) in items.iter().enumerate() {
        let path = format!("part[{i}]");
        let DeValue::Table(table) = pv.get_ref() else {
            return Err(item.err(
                &path,
                pv.span(),
                format!("expected a table, found {}", pv.get_ref().type_str()),
            ));
        };
        let part = Item {
            src: item.src,
            label: item.label.clone(),
            prefix: format!("{}{path}.", item.prefix),
            span: pv.span(),
            table,
        };
        let solids = "box, sphere, capsule, cylinder, convex";
        let (shape_name, shape_span) = part.required_string(
            "shape",
            &format!("one of {solids}{}", if dynamic { "" } else { ", trimesh" }),
        )?;
        let refusal = match shape_name {
            "compound" => Some(
                "a part cannot be a compound (compounds do not nest): list its shapes as parts of this one".to_owned(),
            ),
            "plane" => Some(
                "a plane cannot be a part (it is an infinite half-space): declare it as its own [[static]]".to_owned(),
            ),
            "trimesh" if dynamic => Some(format!(
                "shape \"trimesh\" can only be static: a dynamic body's parts are solids ({solids}); \
                 declare the mesh as [[static]]"
            )),
            s if !SHAPES.contains(&s) => Some(format!(
                "unknown shape \"{s}\"; expected one of {solids}{}{}",
                if dynamic { "" } else { ", trimesh" },
                suggestion(s, SHAPES.iter().copied())
            )),
            _ => None,
        };
        if let Some(msg) = refusal {
            return Err(part.err("shape", shape_span, msg));
        }
        let own_keys = shape_keys(shape_name);
        let allowed: Vec<&str> = PART_KEYS.iter().chain(own_keys).copied().collect();
        part.check_keys(&allowed, &|k| {
            if ALL_SHAPE_KEYS.contains(&k) {
                Some(format!(
                    "does not apply to shape \"{shape_name}\" (it takes {})",
                    own_keys.join(", ")
                ))
            } else if MOTION_KEYS.contains(&k) {
                Some(format!("velocities belong to the {kind}, not to one of its parts"))
            } else if LAYOUT_KEYS.contains(&k) {
                Some(format!(
                    "a part cannot be a generator: put `{k}` on the {kind} to repeat the whole compound"
                ))
            } else {
                None
            }
        })?;
        let shape = parse_shape(&part, shape_name)?;
        let material = match part.string("material")? {
            Some((name, span)) => Some(material_index(&part, materials, name, span)?),
            None => None,
        };
        let position = part.num3("position", Valid::Any, Some([0.0; 3]))?;
        let rotation = parse_rotation(&part)?;
        out.push((
            PartT {
                shape,
                position,
                rotation,
                material: 0, // resolved by the caller once the body's material is known
            },
            material,
        ));
    }
    Ok(out)
}

/// Exactly one of `a` (half) or `b` (full); returns the value and whether it was the full one.
fn half_or_full<T>(
    item: &Item<'_>,
    half: &str,
    full: &str,
    parse: impl Fn(&str) -> Result<T, SceneError>,
) -> Result<(T, bool), SceneError> {
    match (item.get(half), item.get(full)) {
        (Some(_), Some(v)) => Err(item.err(
            full,
            v.span(),
            format!("give either `{half}` or `{full}`, not both"),
        )),
        (Some(_), None) => Ok((parse(half)?, false)),
        (None, Some(_)) => Ok((parse(full)?, true)),
        (None, None) => Err(item.missing(full, &format!("give `{full}` or `{half}`"))),
    }
}

fn parse_shape(item: &Item<'_>, shape: &str) -> Result<ShapeT, SceneError> {
    Ok(match shape {
        "box" => {
            let (extents, full) = half_or_full(item, "half_extents", "size", |k| {
                item.num3(k, Valid::Positive, None)
            })?;
            ShapeT::Box { extents, full }
        }
        "sphere" => ShapeT::Sphere {
            radius: item.num("radius", Valid::Positive, None)?,
        },
        "capsule" | "cylinder" => {
            let (height, full) = half_or_full(item, "half_height", "height", |k| {
                item.num(k, Valid::Positive, None)
            })?;
            let radius = item.num("radius", Valid::Positive, None)?;
            if shape == "capsule" {
                ShapeT::Capsule {
                    height,
                    radius,
                    full,
                }
            } else {
                ShapeT::Cylinder {
                    height,
                    radius,
                    full,
                }
            }
        }
        "convex" => {
            let points = item.points("points")?;
            let span = span_of(item, "points");
            if points.len() < 4 {
                return Err(item.err(
                    "points",
                    span,
                    format!(
                        "a convex hull needs at least 4 points, found {}",
                        points.len()
                    ),
                ));
            }
            if !has_volume(&points) {
                return Err(item.err(
                    "points",
                    span,
                    "degenerate convex hull: the points are coplanar (no volume)",
                ));
            }
            ShapeT::ConvexHull { points }
        }
        "plane" => {
            let normal = item.num3("normal", Valid::Any, Some([0.0, 1.0, 0.0]))?;
            item.check_direction("normal", &normal)?;
            ShapeT::Plane { normal }
        }
        _ => {
            // "trimesh" (the caller only passes known shapes).
            let vertices = item.points("vertices")?;
            if vertices.len() < 3 {
                return Err(item.err(
                    "vertices",
                    span_of(item, "vertices"),
                    format!(
                        "a triangle mesh needs at least 3 vertices, found {}",
                        vertices.len()
                    ),
                ));
            }
            let indices = parse_indices(item, vertices.len())?;
            ShapeT::TriMesh { vertices, indices }
        }
    })
}

fn parse_indices(item: &Item<'_>, n_vertices: usize) -> Result<Vec<[u32; 3]>, SceneError> {
    let v = item
        .get("indices")
        .ok_or_else(|| item.missing("indices", "a list of [a, b, c] vertex-index triangles"))?;
    let DeValue::Array(tris) = v.get_ref() else {
        return Err(item.err(
            "indices",
            v.span(),
            format!(
                "expected an array of [a, b, c] triangles, found {}",
                v.get_ref().type_str()
            ),
        ));
    };
    if tris.is_empty() {
        return Err(item.err(
            "indices",
            v.span(),
            "a triangle mesh needs at least one triangle",
        ));
    }
    let max = u64::try_from(n_vertices)
        .unwrap_or(u64::MAX)
        .saturating_sub(1)
        .min(u64::from(u32::MAX));
    let mut out = Vec::with_capacity(tris.len());
    for (t, tri) in tris.iter().enumerate() {
        let path = format!("indices[{t}]");
        let corners = match tri.get_ref() {
            DeValue::Array(c) if c.len() == 3 => c,
            _ => {
                return Err(item.err(
                    &path,
                    tri.span(),
                    "expected a triangle [a, b, c] of vertex indices",
                ));
            }
        };
        let mut abc = [0u32; 3];
        for (slot, c) in abc.iter_mut().zip(corners.iter()) {
            let idx = match c.get_ref() {
                DeValue::Integer(i) => i64::from_str_radix(i.as_str(), i.radix()).ok(),
                _ => None,
            };
            *slot = match idx.and_then(|i| u64::try_from(i).ok()) {
                Some(i) if i <= max => u32::try_from(i).unwrap_or(u32::MAX),
                Some(i) => {
                    return Err(item.err(
                        &path,
                        c.span(),
                        format!(
                            "vertex index {i} out of range (the mesh has {n_vertices} vertices)"
                        ),
                    ));
                }
                None => {
                    return Err(item.err(
                        &path,
                        c.span(),
                        "expected a vertex index (an integer >= 0)",
                    ));
                }
            };
        }
        if abc[0] == abc[1] || abc[1] == abc[2] || abc[0] == abc[2] {
            return Err(item.err(
                &path,
                tri.span(),
                "degenerate triangle: a vertex index repeats",
            ));
        }
        out.push(abc);
    }
    Ok(out)
}

/// Whether the points span a volume: some tetrahedron of them has a volume that is not
/// negligible relative to the points' extent.
fn has_volume(points: &[Vec3]) -> bool {
    let sub = |a: Vec3, b: Vec3| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let dot = |a: Vec3, b: Vec3| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let cross = |a: Vec3, b: Vec3| {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    };
    let p0 = points[0];
    let farthest = |score: &dyn Fn(Vec3) -> f64| {
        points
            .iter()
            .copied()
            .map(|p| (score(p), p))
            .fold((0.0, p0), |a, b| if b.0 > a.0 { b } else { a })
    };
    let (d1, p1) = farthest(&|p| dot(sub(p, p0), sub(p, p0)));
    if d1 <= 0.0 {
        return false;
    }
    let e1 = sub(p1, p0);
    let (_, p2) = farthest(&|p| {
        let c = cross(e1, sub(p, p0));
        dot(c, c)
    });
    let n = cross(e1, sub(p2, p0));
    let (vol, _) = farthest(&|p| dot(n, sub(p, p0)).abs());
    // |n|·height ≥ 1e-9 · extent³ : a hull thinner than a billionth of its size is a plane.
    let extent = d1.sqrt();
    vol > 1e-9 * extent * extent * extent
}

fn parse_rotation(item: &Item<'_>) -> Result<RotationT, SceneError> {
    let given: Vec<&str> = ROTATION_KEYS
        .iter()
        .copied()
        .filter(|k| item.get(k).is_some())
        .collect();
    if let [_, second, ..] = given.as_slice() {
        return Err(item.err(
            second,
            span_of(item, second),
            format!(
                "give only one of {}",
                ROTATION_KEYS
                    .iter()
                    .map(|k| format!("`{k}`"))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        ));
    }
    Ok(match given.first().copied() {
        None => RotationT::Identity,
        Some("rotation_deg") => {
            RotationT::EulerXyzDeg(item.num3("rotation_deg", Valid::Any, None)?)
        }
        Some("quat") => {
            let v = item.get("quat").ok_or_else(|| item.missing("quat", ""))?;
            let q = item.vec_value::<4>("quat", v, Valid::Any, true)?;
            item.check_direction("quat", &q)?;
            RotationT::Quat(q)
        }
        Some(_) => {
            let v = item
                .get("axis_angle")
                .ok_or_else(|| item.missing("axis_angle", ""))?;
            let sub = item.sub("axis_angle", v)?;
            sub.check_keys(&["axis", "deg"], &|k| {
                (k == "angle" || k == "rad")
                    .then(|| "the angle is given in degrees as `deg`".to_owned())
            })?;
            let axis = sub.num3("axis", Valid::Any, None)?;
            sub.check_direction("axis", &axis)?;
            RotationT::AxisAngleDeg {
                axis,
                deg: sub.num("deg", Valid::Any, None)?,
            }
        }
    })
}

fn parse_layout(item: &Item<'_>) -> Result<(Layout, Option<&'static str>), SceneError> {
    let given: Vec<&'static str> = LAYOUT_KEYS
        .iter()
        .copied()
        .filter(|k| item.get(k).is_some())
        .collect();
    if let [_, second, ..] = given.as_slice() {
        return Err(item.err(
            second,
            span_of(item, second),
            "give only one generator: `grid`, `row` or `stack`",
        ));
    }
    let Some(key) = given.first().copied() else {
        return Ok((Layout::Single, None));
    };
    let v = item.get(key).ok_or_else(|| item.missing(key, ""))?;
    let g = item.sub(key, v)?;
    let max = MAX_INSTANCES;
    let as_u32 = |n: u64| u32::try_from(n).unwrap_or(u32::MAX);
    let layout = match key {
        "grid" => {
            g.check_keys(&["count", "spacing"], &|_| None)?;
            let c = g
                .get("count")
                .ok_or_else(|| g.missing("count", "[nx, ny, nz]"))?;
            let DeValue::Array(cs) = c.get_ref() else {
                return Err(g.err("count", c.span(), "expected [nx, ny, nz]"));
            };
            if cs.len() != 3 {
                return Err(g.err(
                    "count",
                    c.span(),
                    format!("expected 3 counts [nx, ny, nz], found {}", cs.len()),
                ));
            }
            let mut count = [0u32; 3];
            for (i, (slot, n)) in count.iter_mut().zip(cs.iter()).enumerate() {
                *slot = as_u32(g.integer_value(&format!("count[{i}]"), n, 1, max)?);
            }
            Layout::Grid {
                count,
                spacing: g.plain3("spacing", Valid::Any, None)?,
            }
        }
        "row" => {
            g.check_keys(&["count", "spacing"], &|_| None)?;
            Layout::Row {
                count: as_u32(g.integer("count", 1, max, None)?),
                spacing: g.plain3("spacing", Valid::Any, None)?,
            }
        }
        _ => {
            g.check_keys(
                &["layers", "per_layer", "spacing", "layer_height", "turn_deg"],
                &|_| None,
            )?;
            Layout::Stack {
                layers: as_u32(g.integer("layers", 1, max, None)?),
                per_layer: as_u32(g.integer("per_layer", 1, max, Some(1))?),
                spacing: g.plain("spacing", Valid::Any, Some(0.0))?,
                layer_height: g.plain("layer_height", Valid::Any, None)?,
                turn_deg: g.plain("turn_deg", Valid::Any, Some(90.0))?,
            }
        }
    };
    Ok((layout, Some(key)))
}

fn parse_joint(
    item: &Item<'_>,
    name: &str,
    bodies: &HashMap<&str, usize>,
    statics: &HashSet<&str>,
) -> Result<JointT, SceneError> {
    item.check_keys(
        &[
            "name", "kind", "body1", "body2", "anchor1", "anchor2", "axis",
        ],
        &|_| None,
    )?;
    const KINDS: [&str; 3] = ["revolute", "spherical", "fixed"];
    let (kind_name, kind_span) =
        item.required_string("kind", "one of revolute, spherical, fixed")?;
    let body_ref = |key: &str| -> Result<(BodyRef, Range<usize>), SceneError> {
        let (b, span) = item.required_string(key, "a body name or \"world\"")?;
        if b == "world" {
            return Ok((BodyRef::World, span));
        }
        match bodies.get(b) {
            Some(i) => Ok((BodyRef::Body(*i), span)),
            None if statics.contains(b) => Err(item.err(
                key,
                span,
                format!("\"{b}\" is a static body; attach to \"world\" instead"),
            )),
            None => Err(item.err(
                key,
                span,
                format!(
                    "unknown body \"{b}\"{}",
                    suggestion(b, bodies.keys().copied())
                ),
            )),
        }
    };
    let (body1, _) = body_ref("body1")?;
    let (body2, span2) = body_ref("body2")?;
    if body1 == body2 {
        return Err(item.err(
            "body2",
            span2,
            "a joint needs two different bodies (or one body and \"world\")",
        ));
    }
    let kind = match kind_name {
        "revolute" => {
            let axis = item.num3("axis", Valid::Any, None).map_err(|e| {
                if item.get("axis").is_none() {
                    item.missing("axis", "a revolute joint needs a hinge `axis`")
                } else {
                    e
                }
            })?;
            item.check_direction("axis", &axis)?;
            JointKindT::Revolute { axis }
        }
        "spherical" | "fixed" => {
            if let Some(v) = item.get("axis") {
                return Err(item.err("axis", v.span(), "`axis` applies to revolute joints only"));
            }
            if kind_name == "fixed" {
                JointKindT::Fixed
            } else {
                JointKindT::Spherical
            }
        }
        other => {
            return Err(item.err(
                "kind",
                kind_span,
                format!(
                    "unknown joint kind \"{other}\"; expected one of {}{}",
                    KINDS.join(", "),
                    suggestion(other, KINDS)
                ),
            ));
        }
    };
    Ok(JointT {
        name: name.to_owned(),
        kind,
        body1,
        body2,
        anchor1: item.num3("anchor1", Valid::Any, Some([0.0; 3]))?,
        anchor2: item.num3("anchor2", Valid::Any, Some([0.0; 3]))?,
    })
}
