//! Broad phase: which shape pairs are close enough for the narrow phase to look at.
//!
//! Sweep and prune (the "careful tuning of the broad-phase collision handling" §5.4.1 says the
//! 3037-ball example lacked): the finite bounding boxes are sorted by their lower end along the
//! axis on which their centres spread most, then swept once, keeping the boxes whose interval is
//! still open. A box whose extent is not finite (a half-space) is tested against every body
//! instead of being swept, so one ground plane does not keep itself in every sweep window. The
//! cost is `O(n log n + k)` for `n` boxes and `k` pairs whose intervals overlap on the sweep axis,
//! instead of the `O(n²)` of testing all pairs ([`all_pairs`], kept as the reference the tests
//! compare against).

use parry3d::bounding_volume::{Aabb, BoundingVolume};

use crate::contact::Partner;

/// Boxes larger than this (m) on any axis are treated as unbounded (half-spaces, huge meshes).
pub const UNBOUNDED_EXTENT: f32 = 1.0e6;

/// One candidate pair: a dynamic body and its partner (a body with a larger index, or a static).
pub type CandidatePair = (usize, Partner);

fn is_unbounded(aabb: &Aabb) -> bool {
    let e = aabb.extents();
    !(e.x.is_finite() && e.y.is_finite() && e.z.is_finite())
        || e.x > UNBOUNDED_EXTENT
        || e.y > UNBOUNDED_EXTENT
        || e.z > UNBOUNDED_EXTENT
}

/// The order the narrow phase has always visited pairs in: by body, statics before bodies,
/// each ascending. Keeping it makes contact order (and so every LCP) independent of the broad
/// phase.
fn narrow_phase_order(pair: &CandidatePair) -> (usize, u8, usize) {
    match pair.1 {
        Partner::Static(s) => (pair.0, 0, s),
        Partner::Body(b) => (pair.0, 1, b),
    }
}

/// Every pair of overlapping boxes between enabled bodies (`bodies[i]` is `None` for a disabled
/// body) and between a body and a static, by sweep and prune. Body pairs come as `(i, Body(j))`
/// with `i < j`. Sorted in the narrow phase's order.
pub fn sweep_and_prune(bodies: &[Option<Aabb>], statics: &[Aabb]) -> Vec<CandidatePair> {
    // Entries: (aabb, is_static, index); unbounded statics are handled separately.
    let mut swept: Vec<(Aabb, bool, usize)> = Vec::with_capacity(bodies.len() + statics.len());
    let mut unbounded_statics = Vec::new();
    let mut unbounded_bodies = Vec::new();
    for (i, aabb) in bodies.iter().enumerate() {
        if let Some(a) = aabb {
            if is_unbounded(a) {
                unbounded_bodies.push(i);
            } else {
                swept.push((*a, false, i));
            }
        }
    }
    for (s, a) in statics.iter().enumerate() {
        if is_unbounded(a) {
            unbounded_statics.push(s);
        } else {
            swept.push((*a, true, s));
        }
    }
    let axis = spread_axis(swept.iter().map(|e| &e.0));
    swept.sort_by(|x, y| {
        x.0.mins[axis]
            .total_cmp(&y.0.mins[axis])
            .then(x.1.cmp(&y.1))
            .then(x.2.cmp(&y.2))
    });
    let mut pairs = Vec::new();
    let mut open: Vec<usize> = Vec::new(); // indices into `swept`
    for (k, (aabb, is_static, idx)) in swept.iter().enumerate() {
        let lo = aabb.mins[axis];
        open.retain(|&o| swept[o].0.maxs[axis] >= lo);
        for &o in &open {
            let (other, other_static, oidx) = &swept[o];
            if *is_static && *other_static {
                continue;
            }
            if !aabb.intersects(other) {
                continue;
            }
            pairs.push(match (*is_static, *other_static) {
                (true, _) => (*oidx, Partner::Static(*idx)),
                (_, true) => (*idx, Partner::Static(*oidx)),
                _ => ((*idx).min(*oidx), Partner::Body((*idx).max(*oidx))),
            });
        }
        open.push(k);
    }
    // Unbounded shapes meet everything whose box they touch.
    for &s in &unbounded_statics {
        for (i, aabb) in bodies.iter().enumerate() {
            if let Some(a) = aabb
                && a.intersects(&statics[s])
            {
                pairs.push((i, Partner::Static(s)));
            }
        }
    }
    for &i in &unbounded_bodies {
        let Some(a) = &bodies[i] else { continue };
        for (s, st) in statics.iter().enumerate() {
            if !unbounded_statics.contains(&s) && a.intersects(st) {
                pairs.push((i, Partner::Static(s)));
            }
        }
        for (j, other) in bodies.iter().enumerate() {
            if let Some(b) = other
                && j != i
                && a.intersects(b)
                && (!unbounded_bodies.contains(&j) || i < j)
            {
                pairs.push((i.min(j), Partner::Body(i.max(j))));
            }
        }
    }
    pairs.sort_unstable_by_key(narrow_phase_order);
    pairs.dedup();
    pairs
}

/// The reference broad phase: every pair tested. `O(n²)`; for tests and tiny scenes.
pub fn all_pairs(bodies: &[Option<Aabb>], statics: &[Aabb]) -> Vec<CandidatePair> {
    let mut pairs = Vec::new();
    for (i, a) in bodies.iter().enumerate() {
        let Some(a) = a else { continue };
        for (s, st) in statics.iter().enumerate() {
            if a.intersects(st) {
                pairs.push((i, Partner::Static(s)));
            }
        }
        for (j, b) in bodies.iter().enumerate().skip(i + 1) {
            if let Some(b) = b
                && a.intersects(b)
            {
                pairs.push((i, Partner::Body(j)));
            }
        }
    }
    pairs
}

/// The axis (0, 1, 2) along which the box centres have the largest variance.
fn spread_axis<'a>(boxes: impl Iterator<Item = &'a Aabb>) -> usize {
    let (mut n, mut sum, mut sq) = (0.0f64, [0.0f64; 3], [0.0f64; 3]);
    for b in boxes {
        let c = b.center();
        for (k, v) in [c.x, c.y, c.z].into_iter().enumerate() {
            sum[k] += v as f64;
            sq[k] += (v as f64) * (v as f64);
        }
        n += 1.0;
    }
    if n == 0.0 {
        return 0;
    }
    let var = |k: usize| sq[k] / n - (sum[k] / n).powi(2);
    let mut best = 0;
    for k in 1..3 {
        if var(k) > var(best) {
            best = k;
        }
    }
    best
}
