//! Scenes: the human-editable TOML format (`docs/scene-format.md`), its validation, and the
//! concrete [`Scene`] a simulator consumes.
//!
//! ```
//! use mwb_core::scene::{SceneTemplate, builtin};
//!
//! let template = SceneTemplate::parse(builtin::TOWER, "scenes/tower.toml")?;
//! assert_eq!(template.body_count(), 193); // 192 blocks and the projectile
//! let world = template.instantiate(42); // the same seed always gives the same scene
//! assert_eq!(world, template.instantiate(42));
//! # Ok::<(), mwb_core::scene::SceneError>(())
//! ```

pub mod builtin;
pub mod edit_text;
mod error;
mod generators;
pub mod model;
mod parse;
mod template;
pub mod toml_span;

pub use error::SceneError;
pub use generators::MAX_INSTANCES;
pub use model::*;
pub use parse::{LIMIT, NORMAL_CUT_SIGMAS};
pub use template::SceneTemplate;
pub use toml_span::decode_utf8;

#[cfg(test)]
mod tests;
