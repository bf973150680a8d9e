use super::*;
use crate::browse::{Camera, Frustum, Intrinsics, Polarity, ScreenRect, Viewport};
use proptest::prelude::*;
use std::collections::BTreeMap;

fn frustum_at(x: f64) -> Frustum {
    Camera {
        position: [x, 0.0, 10.0],
        rotation: [0.0, 0.0, 0.0, 1.0],
        intrinsics: Intrinsics::VerticalFov { fov_y_rad: 0.5 },
        viewport: Viewport {
            width: 100,
            height: 100,
        },
        near: 0.1,
        far: 100.0,
    }
    .frustum(&ScreenRect {
        x0: 45.0,
        y0: 45.0,
        x1: 55.0,
        y1: 55.0,
    })
    .expect("valid")
}

fn constraint(id: u64, polarity: Polarity) -> Constraint {
    Constraint {
        id: ConstraintId(id),
        polarity,
        frustum: frustum_at(id as f64 * 3.0),
        objects: vec![0],
        quantifier: Default::default(),
        window: None,
        scope: Default::default(),
    }
}

/// A table standing in for geometry: does world w's object pass through constraint c's
/// frustum? The evaluator applies the polarity like `Constraint::satisfied_given`.
struct Oracle {
    touches: BTreeMap<(u64, u32), bool>,
}

impl Oracle {
    fn new(seed: u64) -> Self {
        let mut touches = BTreeMap::new();
        let mut s = seed | 1;
        for c in 0..16u64 {
            for w in 0..300u32 {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                touches.insert((c, w), !s.is_multiple_of(3));
            }
        }
        Self { touches }
    }
    fn eval(&self, c: &Constraint, w: u32) -> bool {
        let touched = self.touches.get(&(c.id.0, w)).copied().unwrap_or(false);
        c.satisfied_given(touched)
    }
    /// Expected result from scratch.
    fn expected(&self, worlds: &WorldSet, live: &[Constraint]) -> WorldSet {
        worlds
            .iter()
            .filter(|&w| live.iter().all(|c| self.eval(c, w)))
            .collect()
    }
}

#[test]
fn positive_and_negative_combine_by_and() {
    let oracle = Oracle::new(1);
    let mut s = ConstraintSet::new();
    for w in 0..100 {
        s.on_new_world(w, |c, w| oracle.eval(c, w));
    }
    assert_eq!(s.result(), &WorldSet::full(100));
    let pos = constraint(1, Polarity::Positive);
    let neg = constraint(2, Polarity::Negative);
    s.add(pos.clone(), |c, w| oracle.eval(c, w))
        .expect("new id");
    s.add(neg.clone(), |c, w| oracle.eval(c, w))
        .expect("new id");
    assert_eq!(
        s.add(pos.clone(), |c, w| oracle.eval(c, w)),
        Err(BrowseError::DuplicateConstraint(1))
    );
    assert_eq!(
        s.result(),
        &oracle.expected(s.worlds(), &[pos.clone(), neg.clone()])
    );
    for w in 0..100 {
        let n = u32::from(oracle.eval(&pos, w)) + u32::from(oracle.eval(&neg, w));
        assert_eq!(s.satisfied_count(w), n);
    }
    assert_eq!(
        s.remove(ConstraintId(9)),
        Err(BrowseError::UnknownConstraint(9))
    );
}

#[test]
fn removal_and_undo_redo_never_reevaluate_geometry() {
    let oracle = Oracle::new(2);
    let mut s = ConstraintSet::new();
    for w in 0..200 {
        s.on_new_world(w, |c, w| oracle.eval(c, w));
    }
    let cs: Vec<Constraint> = (0..5)
        .map(|i| {
            constraint(
                i,
                if i % 2 == 0 {
                    Polarity::Positive
                } else {
                    Polarity::Negative
                },
            )
        })
        .collect();
    for c in &cs {
        s.add(c.clone(), |c, w| oracle.eval(c, w)).expect("new");
    }
    let never = |_: &Constraint, _: u32| -> bool { panic!("geometry re-evaluated") };
    s.remove(ConstraintId(2)).expect("live");
    let remaining: Vec<Constraint> = cs.iter().filter(|c| c.id.0 != 2).cloned().collect();
    assert_eq!(s.result(), &oracle.expected(s.worlds(), &remaining));
    assert!(s.undo(never));
    assert_eq!(
        s.constraints().map(|c| c.id.0).collect::<Vec<_>>(),
        vec![0, 1, 2, 3, 4],
        "undo puts the constraint back where it was"
    );
    assert!(s.undo(never), "undo the last add");
    assert!(s.redo(never));
    assert!(s.redo(never));
    assert_eq!(s.result(), &oracle.expected(s.worlds(), &remaining));
    assert!(!s.redo(never));
}

#[test]
fn parked_constraints_catch_up_on_worlds_that_arrived_meanwhile() {
    let oracle = Oracle::new(3);
    let mut s = ConstraintSet::new();
    for w in 0..50 {
        s.on_new_world(w, |c, w| oracle.eval(c, w));
    }
    let a = constraint(0, Polarity::Positive);
    let b = constraint(1, Polarity::Negative);
    s.add(a.clone(), |c, w| oracle.eval(c, w)).expect("new");
    s.add(b.clone(), |c, w| oracle.eval(c, w)).expect("new");
    s.remove(ConstraintId(0)).expect("live");
    for w in 50..120 {
        s.on_new_world(w, |c, w| oracle.eval(c, w));
    }
    let mut evaluated = Vec::new();
    assert!(s.undo(|c, w| {
        evaluated.push(w);
        oracle.eval(c, w)
    }));
    assert_eq!(evaluated, (50..120).collect::<Vec<_>>());
    assert_eq!(
        s.result(),
        &oracle.expected(s.worlds(), &[a.clone(), b.clone()])
    );
    // Forgetting a world clears it everywhere, also in parked constraints.
    s.forget_world(7);
    assert!(!s.result().contains(7) && !s.worlds().contains(7));
    assert!(s.undo(|_, _| panic!("nothing new")), "undo add b");
    assert!(s.undo(|_, _| panic!("nothing new")), "undo remove a");
    s.on_new_world(7, |c, w| oracle.eval(c, w));
    let mut evaluated = Vec::new();
    assert!(s.redo(|c, w| {
        evaluated.push(w);
        oracle.eval(c, w)
    }));
    assert_eq!(
        evaluated,
        vec![7],
        "only world 7 arrived while a was parked"
    );
    assert_eq!(s.result(), &oracle.expected(s.worlds(), &[a]));
    assert_eq!(s.constraints().count(), 1);
}

#[test]
fn pick_selects_the_nearest_frustum_on_the_ray() {
    let mut s = ConstraintSet::new();
    s.add(constraint(0, Polarity::Positive), |_, _| true)
        .expect("new");
    s.add(constraint(1, Polarity::Negative), |_, _| true)
        .expect("new");
    // Looking down −z from above the first camera: only constraint 0's frustum is on the ray.
    assert_eq!(
        s.pick([0.0, 0.0, 20.0], [0.0, 0.0, -1.0]),
        Some(ConstraintId(0))
    );
    assert_eq!(
        s.pick([3.0, 0.0, 20.0], [0.0, 0.0, -1.0]),
        Some(ConstraintId(1))
    );
    assert_eq!(s.pick([50.0, 0.0, 20.0], [0.0, 0.0, -1.0]), None);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 96, ..ProptestConfig::default() })]

    /// Removing any constraint (here: one in the middle) gives exactly the result of building the
    /// set from scratch without it, and so does any interleaving with new worlds.
    #[test]
    fn removing_any_constraint_equals_recomputing_from_scratch(
        seed in any::<u64>(),
        n in 2usize..8,
        remove_at in 0usize..8,
        worlds_before in 0u32..150,
        worlds_after in 0u32..150,
    ) {
        let oracle = Oracle::new(seed);
        let cs: Vec<Constraint> = (0..n as u64)
            .map(|i| constraint(i, if (seed >> i) & 1 == 0 { Polarity::Positive } else { Polarity::Negative }))
            .collect();
        let mut s = ConstraintSet::new();
        for w in 0..worlds_before {
            s.on_new_world(w, |c, w| oracle.eval(c, w));
        }
        for c in &cs {
            s.add(c.clone(), |c, w| oracle.eval(c, w)).expect("new");
        }
        for w in worlds_before..worlds_before + worlds_after {
            s.on_new_world(w, |c, w| oracle.eval(c, w));
        }
        let gone = cs[remove_at % n].id;
        s.remove(gone).expect("live");
        let remaining: Vec<Constraint> = cs.iter().filter(|c| c.id != gone).cloned().collect();

        let mut fresh = ConstraintSet::new();
        for w in 0..worlds_before + worlds_after {
            fresh.on_new_world(w, |c, w| oracle.eval(c, w));
        }
        for c in &remaining {
            fresh.add(c.clone(), |c, w| oracle.eval(c, w)).expect("new");
        }
        prop_assert_eq!(s.result(), fresh.result());
        prop_assert_eq!(s.result(), &oracle.expected(s.worlds(), &remaining));
        for w in 0..worlds_before + worlds_after {
            prop_assert_eq!(s.satisfied_count(w), fresh.satisfied_count(w));
        }
        // Undo brings back the exact previous result; redo removes it again.
        prop_assert!(s.undo(|c, w| oracle.eval(c, w)));
        prop_assert_eq!(s.result(), &oracle.expected(s.worlds(), &cs));
        prop_assert!(s.redo(|c, w| oracle.eval(c, w)));
        prop_assert_eq!(s.result(), fresh.result());
    }
}
