//! Errors of the scene format: every refusal names the file, the line, the item and the field.

use std::fmt;
use std::ops::Range;

/// Why a scene file was refused.
///
/// Displays as `file:line: item: field `name`: message`, leaving out the parts that do not apply,
/// e.g. `scenes/tower.toml:42: body "block": field `material`: unknown material "wod"`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub struct SceneError {
    /// The file name given to [`SceneTemplate::parse`](super::SceneTemplate::parse).
    pub file: String,
    /// 1-based line of the offending key or value, when known.
    pub line: Option<usize>,
    /// The item the error belongs to, as displayed: `body "ball"`, `static "ground"`,
    /// `material "wood"`, `joint "hinge"`, `settings`, `scene`. `None` for TOML syntax errors.
    pub item: Option<String>,
    /// The field within the item, with an index path where it helps: `position[2]`,
    /// `points[3]`, `grid.count`.
    pub field: Option<String>,
    /// What is wrong, and where possible what was expected.
    pub message: String,
}

impl fmt::Display for SceneError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.file)?;
        if let Some(line) = self.line {
            write!(f, ":{line}")?;
        }
        f.write_str(": ")?;
        if let Some(item) = &self.item {
            write!(f, "{item}: ")?;
        }
        if let Some(field) = &self.field {
            write!(f, "field `{field}`: ")?;
        }
        f.write_str(&self.message)
    }
}

/// The text being parsed, for turning byte offsets into line numbers.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Source<'a> {
    pub text: &'a str,
    pub file: &'a str,
}

impl Source<'_> {
    /// 1-based line of a byte offset (offsets past the end count as the last line).
    pub fn line_of(&self, offset: usize) -> usize {
        let end = offset.min(self.text.len());
        self.text.as_bytes()[..end]
            .iter()
            .filter(|b| **b == b'\n')
            .count()
            + 1
    }

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
}
