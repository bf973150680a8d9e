//! Reading a scene file's span-annotated TOML so that every refusal says where: byte spans
//! become `file:line`, and errors are [`SceneError`]s naming the file, the line, the item and the
//! field.
//!
//! [`SceneTemplate::parse`](super::SceneTemplate::parse) reads the scene with these, and so does
//! any crate that reads a table of its own from the same text (mwb-reverse's `[reverse]` table),
//! so that both report alike and a `file:line` means the same everywhere. A file's bytes become
//! its text through [`decode_utf8`], which says where a file that is not UTF-8 goes wrong.
//!
//! ```
//! use mwb_core::scene::toml_span::{Source, Table};
//!
//! let src = Source { text: "[extra]\nlevel = \"high\"\n", file: "a.toml" };
//! let doc = src.parse()?;
//! let value = doc.get_ref().get("extra").expect("written above");
//! let toml::de::DeValue::Table(t) = value.get_ref() else { unreachable!() };
//! let extra = Table::new(src, "[extra]", value.span(), t);
//! let (level, span) = extra.string("level")?.expect("written above");
//! let err = extra.err("level", span, format!("unknown level \"{level}\""));
//! assert_eq!(err.to_string(), "a.toml:2: [extra]: field `level`: unknown level \"high\"");
//! # Ok::<(), mwb_core::scene::SceneError>(())
//! ```

use std::ops::Range;

use toml::Spanned;
use toml::de::{DeTable, DeValue};

use super::error::SceneError;

/// A value of the document, with the byte span it was written at.
pub type Value<'a> = Spanned<DeValue<'a>>;

/// The text being parsed, for turning byte offsets into lines and building errors.
#[derive(Debug, Clone, Copy)]
pub struct Source<'a> {
    /// The whole file.
    pub text: &'a str,
    /// Its name, as errors show it.
    pub file: &'a str,
}

impl<'a> Source<'a> {
    /// 1-based line of a byte offset (offsets past the end count as the last line).
    ///
    /// This counts the newlines before `offset`, in time linear in `offset`: it is meant for the
    /// one error a parse reports. Nothing on the way to an accepted scene may ask for a line
    /// (keep byte offsets and turn them into lines when the error is built), or validation
    /// becomes quadratic in the size of the file (issue 18: 100 000 bodies took 220 s).
    pub fn line_of(&self, offset: usize) -> usize {
        line_of(self.text.as_bytes(), offset)
    }

    /// An error at the line of `span`'s start (no line without a span).
    pub fn error(
        &self,
        span: Option<Range<usize>>,
        item: Option<String>,
        field: Option<String>,
        message: impl Into<String>,
    ) -> SceneError {
        SceneError {
            file: self.file.to_owned(),
            line: span.map(|s| self.line_of(s.start)),
            item,
            field,
            message: message.into(),
        }
    }

    /// A syntax error reported by the toml crate, with its span turned into a line.
    pub fn toml_error(&self, err: &toml::de::Error) -> SceneError {
        // The toml crate's message may span several lines (it quotes the source when it knows
        // it); we keep the first, since file:line already says where.
        let message = err
            .message()
            .lines()
            .next()
            .unwrap_or("invalid TOML")
            .trim()
            .to_owned();
        self.error(err.span(), None, None, format!("invalid TOML: {message}"))
    }

    /// The span-annotated document; a syntax error as [`Self::toml_error`].
    pub fn parse(&self) -> Result<Spanned<DeTable<'a>>, SceneError> {
        DeTable::parse(self.text).map_err(|e| self.toml_error(&e))
    }
}

/// One table of the document (an item, or a sub-table of one) and how to blame it.
#[derive(Debug, Clone)]
pub struct Table<'a> {
    /// The text it was read from.
    pub src: Source<'a>,
    /// The item errors name: `body "ball"`, `settings`, `[reverse]`, ….
    pub label: String,
    /// Field-path prefix of a sub-table (`grid.`), empty for an item.
    pub prefix: String,
    /// Where the table was written; errors about a missing field point here.
    pub span: Range<usize>,
    /// Its keys and values.
    pub table: &'a DeTable<'a>,
}

impl<'a> Table<'a> {
    /// An item (no field-path prefix).
    pub fn new(
        src: Source<'a>,
        label: impl Into<String>,
        span: Range<usize>,
        table: &'a DeTable<'a>,
    ) -> Self {
        Self {
            src,
            label: label.into(),
            prefix: String::new(),
            span,
            table,
        }
    }

    /// An error about `field` (a key of this table, or an index path such as `points[3]`),
    /// at the line of `span`.
    pub fn err(&self, field: &str, span: Range<usize>, msg: impl Into<String>) -> SceneError {
        self.src.error(
            Some(span),
            Some(self.label.clone()),
            Some(format!("{}{field}", self.prefix)),
            msg,
        )
    }

    /// An error about a field that is missing: blamed on the table's own line, as
    /// `missing: {msg}` (`missing (required)` for an empty `msg`).
    pub fn missing(&self, field: &str, msg: &str) -> SceneError {
        let (sep, msg) = if msg.is_empty() {
            (" ", "(required)")
        } else {
            (": ", msg)
        };
        self.err(field, self.span.clone(), format!("missing{sep}{msg}"))
    }

    /// The value of `key`, if written.
    pub fn get(&self, key: &str) -> Option<&'a Value<'a>> {
        self.table.get(key)
    }

    /// The key not in `allowed` that comes first in the file, with its span: the one to report
    /// (the caller words the message, e.g. with a "did you mean").
    pub fn unknown_key(&self, allowed: &[&str]) -> Option<(&'a str, Range<usize>)> {
        self.table
            .iter()
            .filter(|(k, _)| !allowed.contains(&k.get_ref().as_ref()))
            .min_by_key(|(k, _)| k.span().start)
            .map(|(k, _)| (k.get_ref().as_ref(), k.span()))
    }

    /// The string value of `key` and where it was written, if the key is there.
    pub fn string(&self, key: &str) -> Result<Option<(&'a str, Range<usize>)>, SceneError> {
        match self.get(key) {
            None => Ok(None),
            Some(v) => match v.get_ref() {
                DeValue::String(s) => Ok(Some((s.as_ref(), v.span()))),
                other => Err(self.err(
                    key,
                    v.span(),
                    format!("expected a string, found {}", other.type_str()),
                )),
            },
        }
    }

    /// A TOML integer or float as `f64`, unchecked (it may be infinite or NaN); `None` for an
    /// integer that does not fit in `i64` or digits that do not parse. `path` names the field in
    /// the error for a value that is not a number.
    pub fn number(&self, path: &str, v: &Value<'_>) -> Result<Option<f64>, SceneError> {
        match v.get_ref() {
            DeValue::Integer(i) => Ok(i64::from_str_radix(i.as_str(), i.radix())
                .ok()
                .map(|n| n as f64)),
            DeValue::Float(f) => Ok(f.as_str().parse::<f64>().ok()),
            other => Err(self.err(
                path,
                v.span(),
                format!("expected a number, found {}", other.type_str()),
            )),
        }
    }
}

/// 1-based line of a byte offset in `bytes` (offsets past the end count as the last line).
fn line_of(bytes: &[u8], offset: usize) -> usize {
    let end = offset.min(bytes.len());
    bytes[..end].iter().filter(|b| **b == b'\n').count() + 1
}

/// The text of a scene file read as bytes: the bytes themselves if they are UTF-8, else an error
/// naming the file, the line, the column and the byte offset of the first byte that is not.
///
/// Read scene files with `std::fs::read` and this rather than `std::fs::read_to_string`, whose
/// error says only "stream did not contain valid UTF-8".
///
/// ```
/// use mwb_core::scene::decode_utf8;
///
/// let text = decode_utf8("a.toml", b"name = \"caf\xc3\xa9\"\n".to_vec())?;
/// assert_eq!(text, "name = \"café\"\n");
///
/// // Latin-1 "é" (0xE9) on line 2, after `d = "`.
/// let err = decode_utf8("a.toml", b"name = \"x\"\nd = \"\xe9\"\n".to_vec())
///     .expect_err("0xE9 alone is not UTF-8");
/// assert_eq!(err.line, Some(2));
/// assert_eq!(
///     err.to_string(),
///     "a.toml:2: not UTF-8: byte 0xe9 at column 6 (byte offset 16 of the file); \
///      scene files must be saved as UTF-8"
/// );
/// # Ok::<(), mwb_core::scene::SceneError>(())
/// ```
pub fn decode_utf8(file: &str, bytes: Vec<u8>) -> Result<String, SceneError> {
    String::from_utf8(bytes).map_err(|e| not_utf8(file, e.as_bytes(), e.utf8_error()))
}

/// The error of [`decode_utf8`] for `bytes`, which fail to decode as `err` says.
fn not_utf8(file: &str, bytes: &[u8], err: std::str::Utf8Error) -> SceneError {
    let offset = err.valid_up_to();
    let before = &bytes[..offset];
    let line_start = before
        .iter()
        .rposition(|b| *b == b'\n')
        .map_or(0, |i| i + 1);
    // `before` is valid UTF-8 (so borrowed, not copied): columns count characters, as editors do.
    let column = String::from_utf8_lossy(&before[line_start..])
        .chars()
        .count()
        + 1;
    let byte = bytes.get(offset).copied().unwrap_or_default();
    let cut = if err.error_len().is_none() {
        ", which starts a character the file ends in the middle of"
    } else {
        ""
    };
    let hint = if bytes.starts_with(&[0xff, 0xfe]) || bytes.starts_with(&[0xfe, 0xff]) {
        "the file looks like UTF-16; scene files must be saved as UTF-8"
    } else {
        "scene files must be saved as UTF-8"
    };
    SceneError {
        file: file.to_owned(),
        line: Some(line_of(bytes, offset)),
        item: None,
        field: None,
        message: format!(
            "not UTF-8: byte 0x{byte:02x} at column {column} (byte offset {offset} of the file){cut}; {hint}"
        ),
    }
}
