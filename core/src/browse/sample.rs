//! Which worlds a viewer holds when the stores hold more than it can draw.
//!
//! A store holds up to a million worlds; a viewer that drew every path would spend a second on
//! each frame and tens of gigabytes on their polylines. It holds the paths of at most a budget
//! of worlds instead, chosen by a hash of each world's global index that every node computes
//! alike ([`sample_hash`]):
//!
//! * **context**: every world whose hash is below a threshold ([`context_threshold`]) set from
//!   the number of worlds the stores hold, so that about half the budget is taken. A store
//!   applies the threshold itself when it answers `q/paths` (`PathsRequest.sample_below`), so
//!   the other worlds' paths never cross the bus. These draw the cloud every world makes
//!   (rejected ones dim).
//! * **survivors**: the `k` survivors with the smallest hashes ([`bottom_k`]), fetched by
//!   index: the other half, so that a narrow result (a few thousand survivors of a million) is
//!   drawn whole, and a wide one as a uniform sample.
//!
//! Both halves are uniform over the worlds (the hash mixes the index's bits; jobs, shards and
//! arrival order do not bias them), and both are stable, so that browsing does not churn:
//! as worlds arrive the threshold only falls, so the context only loses worlds; and when a
//! constraint narrows the survivors, every survivor in the sample that still survives stays in
//! it (fewer than `k` worlds of a set hash below a member of its bottom `k`, so fewer than `k`
//! of any subset holding it do) — narrowing fetches worlds but drops none that still survive.

/// The hash that orders worlds for sampling: a bijection of the 32-bit global index (the
/// finaliser of MurmurHash3), so that no two worlds tie and consecutive indices — one job's
/// worlds, one shard's — scatter over the whole range.
#[inline]
pub fn sample_hash(world: u32) -> u32 {
    let mut h = world;
    h ^= h >> 16;
    h = h.wrapping_mul(0x85eb_ca6b);
    h ^= h >> 13;
    h = h.wrapping_mul(0xc2b2_ae35);
    h ^= h >> 16;
    h
}

/// The inverse of [`sample_hash`].
fn unhash(mut h: u32) -> u32 {
    // Each step of the finaliser undone, last first: x ^= x >> s is its own inverse for
    // s ≥ 16, and is undone by two applications for s = 13; the multipliers by their inverses
    // modulo 2³².
    h ^= h >> 16;
    h = h.wrapping_mul(0x7ed1_b41d);
    h ^= (h >> 13) ^ (h >> 26);
    h = h.wrapping_mul(0xa5cb_9243);
    h ^= h >> 16;
    h
}

/// The context threshold for `target` worlds of `total`: `0` (every world, the value a
/// `PathsRequest` has when it asks for no sample) when `total ≤ target`, else the hash below
/// which a world falls with probability `target / total` (at least 1). It never rises as
/// `total` grows.
pub fn context_threshold(target: u64, total: u64) -> u32 {
    if total <= target {
        return 0;
    }
    // target < total, so the quotient is below 2³².
    let t = (u128::from(target) << 32) / u128::from(total);
    (t as u32).max(1)
}

/// Whether `world` belongs to the context under `threshold` ([`context_threshold`]).
#[inline]
pub fn in_context(world: u32, threshold: u32) -> bool {
    threshold == 0 || sample_hash(world) < threshold
}

/// The `k` worlds of `worlds` with the smallest [`sample_hash`] (all of them when there are
/// at most `k`), in ascending index order. Duplicates count once.
pub fn bottom_k(worlds: &[u32], k: usize) -> Vec<u32> {
    if k == 0 {
        return Vec::new();
    }
    let mut keyed: Vec<u32> = worlds.iter().map(|&w| sample_hash(w)).collect();
    // A survivor list is ascending, so has no repeats; anything else loses its repeats first
    // (the hash is a bijection: equal hashes are equal worlds).
    if !worlds.windows(2).all(|p| p[0] < p[1]) {
        keyed.sort_unstable();
        keyed.dedup();
    }
    if keyed.len() > k {
        // Linear: a million survivors take a few milliseconds.
        keyed.select_nth_unstable(k - 1);
        keyed.truncate(k);
    }
    keyed.sort_unstable();
    keyed.dedup();
    let mut out: Vec<u32> = keyed.into_iter().map(unhash).collect();
    out.sort_unstable();
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::{Stream, WorldRng};

    #[test]
    fn the_hash_is_a_bijection_that_scatters_neighbours() {
        // Distinct on a dense range (a bijection on u32 is distinct everywhere; this checks the
        // constants were not mistyped into a many-to-one map on small indices).
        let mut seen: Vec<u32> = (0..200_000).map(sample_hash).collect();
        seen.sort_unstable();
        seen.dedup();
        assert_eq!(seen.len(), 200_000);
        // Consecutive indices land all over the range: each quarter gets about a quarter.
        let mut quarters = [0u32; 4];
        for w in 0..100_000u32 {
            quarters[(sample_hash(w) >> 30) as usize] += 1;
        }
        for q in quarters {
            assert!((23_000..27_000).contains(&q), "{quarters:?}");
        }
    }

    #[test]
    fn unhash_inverts_the_hash() {
        let mut rng = WorldRng::new(7, Stream::Scene);
        for w in (0..10_000).chain((0..10_000).map(|_| rng.next_u64() as u32)) {
            assert_eq!(unhash(sample_hash(w)), w);
        }
        assert_eq!(unhash(sample_hash(u32::MAX)), u32::MAX);
    }

    #[test]
    fn the_context_takes_about_the_target_and_shrinks_as_worlds_arrive() {
        assert_eq!(context_threshold(10_000, 0), 0);
        assert_eq!(context_threshold(10_000, 10_000), 0);
        assert!(context_threshold(10_000, 10_001) > 0);
        assert_eq!(context_threshold(1, u64::MAX), 1);
        let mut last = u32::MAX;
        for total in [20_000u64, 50_000, 100_000, 400_000, 1_000_000] {
            let t = context_threshold(10_000, total);
            assert!(t < last, "the threshold only falls");
            last = t;
            let held = (0..total as u32).filter(|&w| in_context(w, t)).count();
            // Binomial(total, 10 000 / total): within ±4 %.
            assert!((9_600..10_400).contains(&held), "{total}: {held}");
        }
    }

    #[test]
    fn bottom_k_of_a_narrower_set_keeps_the_members_it_still_has() {
        let mut rng = WorldRng::new(23, Stream::Scene);
        for _ in 0..200 {
            let n = 1 + rng.next_u64() % 3_000;
            let k = (rng.next_u64() % 400) as usize;
            let all: Vec<u32> = (0..n)
                .map(|_| (rng.next_u64() % (1 << 20)) as u32)
                .collect();
            let wide = bottom_k(&all, k);
            let mut unique = all.clone();
            unique.sort_unstable();
            unique.dedup();
            assert_eq!(wide.len(), k.min(unique.len()));
            assert!(
                wide.windows(2).all(|p| p[0] < p[1]),
                "ascending, no repeats"
            );
            // Every member hashes below every non-member.
            let worst = wide.iter().map(|&w| sample_hash(w)).max();
            for w in &unique {
                if wide.binary_search(w).is_err() {
                    assert!(worst.is_none_or(|m| sample_hash(*w) > m));
                }
            }
            // A constraint keeps some of the worlds.
            let keep = rng.next_f64();
            let narrow_set: Vec<u32> = unique
                .iter()
                .copied()
                .filter(|_| rng.next_f64() < keep)
                .collect();
            let narrow = bottom_k(&narrow_set, k);
            for w in &wide {
                if narrow_set.binary_search(w).is_ok() {
                    assert!(
                        narrow.binary_search(w).is_ok(),
                        "{w} survives but was dropped"
                    );
                }
            }
        }
    }
}
