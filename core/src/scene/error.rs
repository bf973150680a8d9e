//! Errors of the scene format: every refusal names the file, the line, the item and the field
//! ([`super::toml_span`] builds them from byte spans).

use std::fmt;

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
