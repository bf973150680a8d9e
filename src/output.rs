//! How a command prints its result: a table for people, or with `--json` one JSON line per
//! result for scripts. Summaries are structs deriving `Serialize`, so the JSON line and the
//! table name the same fields.
//!
//! Everything a command prints on stdout goes through [`out`], which returns the write's error
//! instead of panicking as `println!` does: piped into `head`, a command ends quietly when the
//! reader goes away ([`is_broken_pipe`]; `main` exits 0 then, as Unix tools do).

use anyhow::{Context, Result};
use serde::Serialize;
use std::fmt::Write as _;
use std::io::Write as _;

/// Writes `text` to stdout and flushes it. A reader that went away is an error like any other
/// ([`is_broken_pipe`] tells it apart).
pub fn out(text: &str) -> Result<()> {
    let mut stdout = std::io::stdout().lock();
    stdout
        .write_all(text.as_bytes())
        .and_then(|()| stdout.flush())
        .context("writing to stdout")
}

/// Whether `e` is, at bottom, a write to a pipe whose reader has gone (`mwb … | head`).
pub fn is_broken_pipe(e: &anyhow::Error) -> bool {
    e.chain().any(|cause| {
        cause
            .downcast_ref::<std::io::Error>()
            .is_some_and(|io| io.kind() == std::io::ErrorKind::BrokenPipe)
    })
}

/// A result a command prints.
pub trait Summary: Serialize {
    /// The human form, ending in a newline.
    fn table(&self) -> String;
}

/// Prints `v` as one JSON line.
pub fn json_line<T: Serialize + ?Sized>(v: &T) -> Result<()> {
    out(&format!("{}\n", serde_json::to_string(v)?))
}

/// Prints `v` as one JSON line (`json`) or as its table.
pub fn print<T: Summary>(v: &T, json: bool) -> Result<()> {
    if json { json_line(v) } else { out(&v.table()) }
}

/// A summary's JSON fields in the order its line has them, a name written twice listed twice.
pub fn fields<T: Serialize>(v: &T) -> Vec<(String, serde_json::Value)> {
    // Through the JSON text, so that the order is the struct's (serde_json's own map sorts).
    serde_json::to_string(v)
        .and_then(|text| serde_json::from_str::<Fields>(&text))
        .map(|f| f.0)
        .unwrap_or_default()
}

/// A flat summary as a table: one field per line, named as in its JSON line and in the order
/// the JSON line has them.
pub fn fields_table<T: Serialize>(v: &T) -> String {
    let fields = fields(v);
    let width = fields.iter().map(|(k, _)| k.len()).max().unwrap_or(0);
    let mut out = String::new();
    for (name, value) in &fields {
        let _ = writeln!(out, "{name:<width$}  {}", cell(value));
    }
    out
}

/// One value as a table cell: numbers to four significant digits (integers whole), strings
/// without quotes, absent (or not a number, which JSON writes as null) as `-`.
pub fn cell(v: &serde_json::Value) -> String {
    match v {
        serde_json::Value::Null => "-".to_owned(),
        serde_json::Value::String(s) => s.clone(),
        serde_json::Value::Number(n) if n.is_f64() => number(n.as_f64().unwrap_or(f64::NAN)),
        other => other.to_string(),
    }
}

/// `x` to four significant digits, never in exponent form.
pub fn number(x: f64) -> String {
    if x == 0.0 || !x.is_finite() {
        return x.to_string();
    }
    let magnitude = x.abs().log10().floor() as i32;
    let decimals = (3 - magnitude).clamp(0, 12) as usize;
    format!("{x:.decimals$}")
}

/// A JSON object's fields in the order of its text.
struct Fields(Vec<(String, serde_json::Value)>);

impl<'de> serde::Deserialize<'de> for Fields {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl<'de> serde::de::Visitor<'de> for Visitor {
            type Value = Fields;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a JSON object")
            }
            fn visit_map<A: serde::de::MapAccess<'de>>(
                self,
                mut map: A,
            ) -> Result<Fields, A::Error> {
                let mut fields = Vec::new();
                while let Some(entry) = map.next_entry()? {
                    fields.push(entry);
                }
                Ok(Fields(fields))
            }
        }
        d.deserialize_map(Visitor)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Serialize)]
    struct Line {
        scene: &'static str,
        worlds: u32,
        ratio: f64,
        tiny: f64,
        missing: Option<f64>,
        nan: f64,
    }

    #[test]
    fn fields_keep_the_struct_order_and_names() {
        let t = fields_table(&Line {
            scene: "scenes/tumble.toml",
            worlds: 50,
            ratio: 0.446_123,
            tiny: 0.000_999_08,
            missing: None,
            nan: f64::NAN,
        });
        assert_eq!(
            t,
            "scene    scenes/tumble.toml\nworlds   50\nratio    0.4461\ntiny     0.0009991\n\
             missing  -\nnan      -\n"
        );
    }

    #[test]
    fn a_broken_pipe_is_told_apart_from_other_errors() {
        let pipe = anyhow::Error::new(std::io::Error::from(std::io::ErrorKind::BrokenPipe))
            .context("writing to stdout");
        assert!(is_broken_pipe(&pipe));
        let other = anyhow::Error::new(std::io::Error::from(std::io::ErrorKind::NotFound));
        assert!(!is_broken_pipe(&other));
        assert!(!is_broken_pipe(&anyhow::anyhow!("no store holds world 9")));
    }

    #[test]
    fn numbers_have_four_significant_digits() {
        assert_eq!(number(135_012.7), "135013");
        assert_eq!(number(1.216_666), "1.217");
        assert_eq!(number(-22.5), "-22.50");
        assert_eq!(number(0.0), "0");
    }
}
