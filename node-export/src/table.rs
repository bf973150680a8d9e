//! Motion as rows for scripts: one row per (world, frame, body), frame-major (every body of
//! frame 0, then frame 1, …), with the decoded pose exactly as the codec gave it (numbers are
//! printed so that they parse back to the same `f64`).
//!
//! CSV (RFC 4180; a header line, names quoted when they need it):
//!
//! ```text
//! world,seed,frame,time,body,name,px,py,pz,qx,qy,qz,qw
//! 3,7,0,0,0,crate,-1.5,1,0,0,0.3826834323650898,0,0.9238795325112867
//! ```
//!
//! `world` is empty for a world simulated from its seed alone (it has no store index).
//! Quaternions are `[x, y, z, w]`; positions metres, right-handed, y up; time seconds.
//!
//! JSON: one document, `{"format": "mwb-export motion 1", "worlds": [{"world", "seed",
//! "scene", "frame_dt", "frame_count", "bodies": [{"index", "name"}], "rows": [{"frame",
//! "time", "body", "name", "position", "rotation"}]}]}`.

use crate::{ExportError, ExportWorld};
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;

/// The `format` field of the JSON document.
pub const JSON_FORMAT: &str = "mwb-export motion 1";
/// The CSV header line.
pub const CSV_HEADER: &str = "world,seed,frame,time,body,name,px,py,pz,qx,qy,qz,qw";

/// One body in one frame of one world.
#[derive(Debug, Clone, PartialEq)]
pub struct Row {
    pub world: Option<u32>,
    pub seed: u64,
    pub frame: u32,
    pub time: f64,
    pub body: u32,
    pub name: String,
    pub position: [f64; 3],
    pub rotation: [f64; 4],
}

/// Every row of the worlds, in order.
pub fn rows(worlds: &[ExportWorld<'_>]) -> Result<Vec<Row>, ExportError> {
    let mut out = Vec::new();
    for w in worlds {
        w.check()?;
        for k in 0..w.motion.frame_count() {
            for (i, body) in w.scene.bodies.iter().enumerate() {
                out.push(Row {
                    world: w.index,
                    seed: w.seed,
                    frame: k as u32,
                    time: k as f64 * w.motion.frame_dt,
                    body: i as u32,
                    name: body.name.clone(),
                    position: w.motion.tracks[i].positions[k],
                    rotation: w.motion.tracks[i].rotations[k],
                });
            }
        }
    }
    Ok(out)
}

/// The worlds as CSV text.
pub fn write_csv(worlds: &[ExportWorld<'_>]) -> Result<Vec<u8>, ExportError> {
    let mut s = String::from(CSV_HEADER);
    s.push('\n');
    for r in rows(worlds)? {
        if let Some(w) = r.world {
            let _ = write!(s, "{w}");
        }
        let _ = write!(
            s,
            ",{},{},{},{},{}",
            r.seed,
            r.frame,
            r.time,
            r.body,
            csv_field(&r.name)
        );
        for x in r.position.iter().chain(&r.rotation) {
            let _ = write!(s, ",{x}");
        }
        s.push('\n');
    }
    Ok(s.into_bytes())
}

fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_owned()
    }
}

/// Splits one CSV line into fields (quoted fields may hold commas and doubled quotes).
fn csv_split(line: &str) -> Result<Vec<String>, String> {
    let mut fields = Vec::new();
    let mut cur = String::new();
    let mut chars = line.chars().peekable();
    let mut quoted = false;
    while let Some(c) = chars.next() {
        match (quoted, c) {
            (true, '"') if chars.peek() == Some(&'"') => {
                cur.push('"');
                chars.next();
            }
            (true, '"') => quoted = false,
            (true, c) => cur.push(c),
            (false, '"') if cur.is_empty() => quoted = true,
            (false, ',') => fields.push(std::mem::take(&mut cur)),
            (false, c) => cur.push(c),
        }
    }
    if quoted {
        return Err("unterminated quoted field".into());
    }
    fields.push(cur);
    Ok(fields)
}

/// Reads rows back from [`write_csv`]'s text. Errors name the line (1-based) and the column.
pub fn read_csv(bytes: &[u8]) -> Result<Vec<Row>, ExportError> {
    let text = std::str::from_utf8(bytes).map_err(|e| ExportError::Csv {
        line: 1,
        reason: format!("not UTF-8: {e}"),
    })?;
    let mut lines = text.lines().enumerate();
    match lines.next() {
        Some((_, h)) if h == CSV_HEADER => {}
        _ => {
            return Err(ExportError::Csv {
                line: 1,
                reason: format!("the header must be {CSV_HEADER:?}"),
            });
        }
    }
    let names: Vec<&str> = CSV_HEADER.split(',').collect();
    let mut out = Vec::new();
    for (n, line) in lines {
        let line_no = n + 1;
        let err = |reason: String| ExportError::Csv {
            line: line_no,
            reason,
        };
        let f = csv_split(line).map_err(err)?;
        if f.len() != names.len() {
            return Err(err(format!("{} fields, expected {}", f.len(), names.len())));
        }
        fn num<T: std::str::FromStr>(f: &[String], names: &[&str], i: usize) -> Result<T, String> {
            f[i].parse::<T>()
                .map_err(|_| format!("{}: {:?} is not a number", names[i], f[i]))
        }
        let parse = || -> Result<Row, String> {
            Ok(Row {
                world: if f[0].is_empty() {
                    None
                } else {
                    Some(num(&f, &names, 0)?)
                },
                seed: num(&f, &names, 1)?,
                frame: num(&f, &names, 2)?,
                time: num(&f, &names, 3)?,
                body: num(&f, &names, 4)?,
                name: f[5].clone(),
                position: [
                    num(&f, &names, 6)?,
                    num(&f, &names, 7)?,
                    num(&f, &names, 8)?,
                ],
                rotation: [
                    num(&f, &names, 9)?,
                    num(&f, &names, 10)?,
                    num(&f, &names, 11)?,
                    num(&f, &names, 12)?,
                ],
            })
        };
        out.push(parse().map_err(err)?);
    }
    Ok(out)
}

#[derive(Serialize, Deserialize)]
struct Document {
    format: String,
    worlds: Vec<JsonWorld>,
}

#[derive(Serialize, Deserialize)]
struct JsonWorld {
    world: Option<u32>,
    seed: u64,
    scene: String,
    frame_dt: f64,
    frame_count: u32,
    bodies: Vec<JsonBody>,
    rows: Vec<JsonRow>,
}

#[derive(Serialize, Deserialize)]
struct JsonBody {
    index: u32,
    name: String,
}

#[derive(Serialize, Deserialize)]
struct JsonRow {
    frame: u32,
    time: f64,
    body: u32,
    name: String,
    position: [f64; 3],
    rotation: [f64; 4],
}

/// The worlds as one JSON document.
pub fn write_json(worlds: &[ExportWorld<'_>]) -> Result<Vec<u8>, ExportError> {
    let mut doc = Document {
        format: JSON_FORMAT.to_owned(),
        worlds: Vec::new(),
    };
    for w in worlds {
        doc.worlds.push(JsonWorld {
            world: w.index,
            seed: w.seed,
            scene: w.scene.name.clone(),
            frame_dt: w.motion.frame_dt,
            frame_count: w.motion.frame_count() as u32,
            bodies: w
                .scene
                .bodies
                .iter()
                .enumerate()
                .map(|(i, b)| JsonBody {
                    index: i as u32,
                    name: b.name.clone(),
                })
                .collect(),
            rows: rows(std::slice::from_ref(w))?
                .into_iter()
                .map(|r| JsonRow {
                    frame: r.frame,
                    time: r.time,
                    body: r.body,
                    name: r.name,
                    position: r.position,
                    rotation: r.rotation,
                })
                .collect(),
        });
    }
    let mut out = serde_json::to_vec(&doc)?;
    out.push(b'\n');
    Ok(out)
}

/// Reads rows back from [`write_json`]'s document.
pub fn read_json(bytes: &[u8]) -> Result<Vec<Row>, ExportError> {
    let doc: Document = serde_json::from_slice(bytes)?;
    if doc.format != JSON_FORMAT {
        return Err(ExportError::Csv {
            line: 1,
            reason: format!("format {:?}, expected {JSON_FORMAT:?}", doc.format),
        });
    }
    Ok(doc
        .worlds
        .into_iter()
        .flat_map(|w| {
            let (world, seed) = (w.world, w.seed);
            w.rows.into_iter().map(move |r| Row {
                world,
                seed,
                frame: r.frame,
                time: r.time,
                body: r.body,
                name: r.name,
                position: r.position,
                rotation: r.rotation,
            })
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn csv_fields_with_commas_and_quotes_survive() {
        let name = "a, \"quoted\" name";
        let f = csv_split(&format!("1,{},x", csv_field(name))).unwrap();
        assert_eq!(f, vec!["1".to_owned(), name.to_owned(), "x".to_owned()]);
        assert!(csv_split("\"open").is_err());
    }

    #[test]
    fn a_bad_csv_line_is_named() {
        let text = format!("{CSV_HEADER}\n,1,0,0,0,a,1,2,3,0,0,0,1\n,1,0,0,0,a,1,x,3,0,0,0,1\n");
        let e = read_csv(text.as_bytes()).unwrap_err().to_string();
        assert!(e.contains("line 3") && e.contains("py"), "{e}");
        let e = read_csv(b"frame,body\n").unwrap_err().to_string();
        assert!(e.contains("line 1"), "{e}");
    }
}
