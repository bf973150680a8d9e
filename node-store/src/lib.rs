//! The in-memory world store (DESIGN.md "Store and queries").
//!
//! * [`assembly`] — pure: segments + summaries → complete, CRC-verified, indexed worlds.
//! * [`node`] — the bus node around it.

pub mod assembly;
pub mod node;

pub use assembly::{Assembler, Outcome, Rejection, StoredWorld};
pub use node::{StoreConfig, StoreHandle, run_store};
