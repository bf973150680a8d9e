//! The in-memory world store (DESIGN.md "Store and queries").
//!
//! * [`assembly`] — pure: segments + summaries → complete, CRC-verified, indexed worlds.
//! * [`index`] — pure: a stored world → per-object paths (bit-packed on a 2⁻¹⁰ m grid, the
//!   store's only copy) with never-miss radii, and metrics.
//! * [`browse`] — pure: one shard's worlds and per-session constraint bitsets; answers
//!   node-query's requests.
//! * [`spatial`] — pure: per object index, a bounding-volume hierarchy over every world's path
//!   pieces (8 segments each, referring to the world's path), so a constraint visits only the
//!   parts of paths near it.
//! * [`slots`] — pure: the world table, in fixed-size chunks (no doubling, no copying).
//! * [`scenes`] — pure: every scene revision of the space (`scene/<rev>`), never overwritten.
//! * [`journal`] — the store's durable journal (MCAP files via `mwb-record`) and loading
//!   recordings into a store.
//! * [`node`] — the bus node around them.

pub mod assembly;
pub mod browse;
pub mod index;
pub mod journal;
pub mod node;
pub mod scenes;
pub mod slots;
pub mod spatial;

pub use assembly::{Assembler, Outcome, Rejection, StoredWorld};
pub use browse::{Shard, ShardBytes, ShardSpec};
pub use index::{IndexError, IndexedWorld, index_world, index_worlds};
pub use journal::{FileReport, Journal, JournalCounters, JournalError, StartReport};
pub use node::{
    DEFAULT_MEMORY_CAP_MIB, DEFAULT_VERIFY_INDEX_EVERY, StoreConfig, StoreError, StoreHandle,
    run_store,
};
pub use scenes::{Offered, SceneRefusal, SceneRevisions};
