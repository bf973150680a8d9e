//! Back-pressure from the stores' memory cap: whether a worker should start another world.
//!
//! A store refuses a complete world that would take it past its memory cap, and stores never
//! drop worlds, so once a store is full every world computed for it is work thrown away. Worker
//! nodes read the stores' statistics (`stats/store/<node>`, every second) and pause — take no
//! new world — while some store is full: it refused a world for memory since its previous
//! report, or holds within [`FULL_FRACTION`] of its cap. A store that stops reporting (it left)
//! no longer holds anyone back after [`FORGET_AFTER`]. Conservative with shards: a full shard
//! pauses every worker, although worlds owned by the other shards would still be taken.
//!
//! Pure: reports and clocks in, a verdict out.

use mwb_proto::v1::NodeStats;
use std::collections::HashMap;
use std::time::{Duration, Instant};

/// A store holding this fraction of its cap or more counts as full.
pub const FULL_FRACTION: f64 = 0.98;
/// A store's report is forgotten after this long without a new one.
pub const FORGET_AFTER: Duration = Duration::from_secs(5);

#[derive(Debug, Clone)]
struct Report {
    at: Instant,
    refused_memory: u64,
    /// Why it is full, if it is.
    full: Option<String>,
}

/// The stores' room as their last reports tell it.
#[derive(Debug, Default, Clone)]
pub struct StoreRoom {
    stores: HashMap<String, Report>,
}

impl StoreRoom {
    /// Takes store `stats` (received at `now`).
    pub fn observe(&mut self, stats: &NodeStats, now: Instant) {
        let before = self.stores.get(&stats.node_id).map(|r| r.refused_memory);
        let cap = stats.memory_cap_bytes;
        let full = if before.is_some_and(|b| stats.refused_memory > b) {
            Some(format!(
                "store {} refused {} world(s) for memory (cap {} MiB)",
                stats.node_id,
                stats.refused_memory - before.unwrap_or(0),
                cap >> 20
            ))
        } else if cap > 0 && stats.memory_bytes as f64 >= FULL_FRACTION * cap as f64 {
            Some(format!(
                "store {} holds {} of its {} MiB",
                stats.node_id,
                stats.memory_bytes >> 20,
                cap >> 20
            ))
        } else {
            None
        };
        self.stores.insert(
            stats.node_id.clone(),
            Report {
                at: now,
                refused_memory: stats.refused_memory,
                full,
            },
        );
    }

    /// Why no new world should be started now (`None`: go on).
    pub fn full(&self, now: Instant) -> Option<&str> {
        self.stores
            .values()
            .filter(|r| now.saturating_duration_since(r.at) < FORGET_AFTER)
            .find_map(|r| r.full.as_deref())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stats(node: &str, memory: u64, cap: u64, refused: u64) -> NodeStats {
        NodeStats {
            node_id: node.into(),
            memory_bytes: memory,
            memory_cap_bytes: cap,
            refused_memory: refused,
            ..Default::default()
        }
    }

    #[test]
    fn a_store_near_its_cap_or_refusing_pauses_until_it_reports_room_or_leaves() {
        let t0 = Instant::now();
        let mut room = StoreRoom::default();
        assert_eq!(room.full(t0), None);
        room.observe(&stats("a", 10 << 20, 64 << 20, 3), t0);
        room.observe(&stats("b", 1 << 20, 64 << 20, 0), t0);
        // Refusals counted before we first heard of it are history.
        assert_eq!(room.full(t0), None);
        // A refusal since the last report.
        room.observe(&stats("a", 10 << 20, 64 << 20, 4), t0);
        assert!(
            room.full(t0)
                .is_some_and(|w| w.contains("store a refused 1"))
        );
        room.observe(&stats("a", 10 << 20, 64 << 20, 4), t0);
        assert_eq!(room.full(t0), None, "no new refusal, room left");
        // Within 2 % of the cap.
        room.observe(&stats("b", 63 << 20, 64 << 20, 0), t0);
        assert!(
            room.full(t0)
                .is_some_and(|w| w.contains("store b holds 63 of its 64 MiB"))
        );
        // A store that stopped reporting holds nobody back.
        assert_eq!(room.full(t0 + FORGET_AFTER), None);
        // No cap reported: never full by size.
        room.observe(&stats("c", u64::MAX, 0, 0), t0);
        room.observe(&stats("b", 0, 64 << 20, 0), t0);
        assert_eq!(room.full(t0), None);
    }
}
