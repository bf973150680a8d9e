//! A browsing session's constraints: one bitset per constraint, their AND as the result, and an
//! undo/redo stack (§4.4.2).
//!
//! §4.4.2 keeps, next to every constraint, a bitset whose bit i says whether world i satisfies
//! it. Intersecting bitsets is cheap, so removing *any* constraint (the most recent via undo, an
//! older one by clicking its frustum) only re-ANDs the remaining bitsets; no path is tested
//! against a frustum again.
//!
//! **Storage choice.** Every constraint stores the worlds that *satisfy* it, whatever its
//! polarity: for a negative constraint, the worlds that never pass through. The result is then
//! a plain AND, "constraints satisfied" is a plain count of set bits, and an unevaluated world
//! (bit 0) is never shown by mistake.

use super::BrowseError;
use super::bitset::WorldSet;
use super::constraint::{Constraint, ConstraintId};
use super::geom::Vec3;

#[derive(Debug, Clone)]
struct Live {
    constraint: Constraint,
    satisfied: WorldSet,
}

/// A constraint off the live list (removed, or undone) with the bits it had, and which worlds
/// those bits cover: worlds that arrive while it is parked are evaluated when it comes back.
#[derive(Debug, Clone)]
struct Parked {
    constraint: Constraint,
    satisfied: WorldSet,
    evaluated: WorldSet,
}

/// A change to the live list; applying one returns its inverse.
#[derive(Debug, Clone)]
enum Edit {
    Insert {
        parked: Box<Parked>,
        position: usize,
    },
    Remove(ConstraintId),
}

/// The constraints of one browsing session over the worlds it knows.
#[derive(Debug, Clone, Default)]
pub struct ConstraintSet {
    worlds: WorldSet,
    live: Vec<Live>,
    /// `worlds` ∩ every live constraint's satisfied bits.
    result: WorldSet,
    undo: Vec<Edit>,
    redo: Vec<Edit>,
}

impl ConstraintSet {
    pub fn new() -> Self {
        Self::default()
    }

    /// Every world the session knows.
    pub fn worlds(&self) -> &WorldSet {
        &self.worlds
    }

    /// Worlds satisfying every live constraint (all known worlds when there are none).
    pub fn result(&self) -> &WorldSet {
        &self.result
    }

    /// Live constraints, oldest first.
    pub fn constraints(&self) -> impl ExactSizeIterator<Item = &Constraint> {
        self.live.iter().map(|l| &l.constraint)
    }

    pub fn get(&self, id: ConstraintId) -> Option<&Constraint> {
        self.find(id).map(|i| &self.live[i].constraint)
    }

    /// The worlds satisfying live constraint `id`.
    pub fn satisfied(&self, id: ConstraintId) -> Option<&WorldSet> {
        self.find(id).map(|i| &self.live[i].satisfied)
    }

    /// How many live constraints `world` satisfies (§4.4.3 "satisfied constraints" metric).
    pub fn satisfied_count(&self, world: u32) -> u32 {
        self.live
            .iter()
            .filter(|l| l.satisfied.contains(world))
            .count() as u32
    }

    fn find(&self, id: ConstraintId) -> Option<usize> {
        self.live.iter().position(|l| l.constraint.id == id)
    }

    fn recompute(&mut self) {
        let mut result = self.worlds.clone();
        for l in &self.live {
            result.and_assign(&l.satisfied);
        }
        self.result = result;
    }

    /// Adds a constraint, evaluating it for every known world with `evaluator(constraint,
    /// world) → satisfied`. Clears the redo stack.
    pub fn add(
        &mut self,
        constraint: Constraint,
        mut evaluator: impl FnMut(&Constraint, u32) -> bool,
    ) -> Result<(), BrowseError> {
        if self.find(constraint.id).is_some() {
            return Err(BrowseError::DuplicateConstraint(constraint.id.0));
        }
        let satisfied = self
            .worlds
            .iter()
            .filter(|&w| evaluator(&constraint, w))
            .collect();
        self.add_evaluated(constraint, satisfied)
    }

    /// Adds a constraint whose satisfied bits were computed elsewhere (in parallel, or merged
    /// from shards) for the worlds the session knows now; bits of unknown worlds are dropped.
    pub fn add_evaluated(
        &mut self,
        constraint: Constraint,
        satisfied: WorldSet,
    ) -> Result<(), BrowseError> {
        let parked = Parked {
            constraint,
            satisfied,
            evaluated: self.worlds.clone(),
        };
        let position = self.live.len();
        let inverse = self.apply(
            Edit::Insert {
                parked: Box::new(parked),
                position,
            },
            &mut |_, _| false,
        )?;
        self.undo.push(inverse);
        self.redo.clear();
        Ok(())
    }

    /// Removes any live constraint (not only the most recent); the result becomes the AND of
    /// the remaining bitsets. Undoable; clears the redo stack.
    pub fn remove(&mut self, id: ConstraintId) -> Result<(), BrowseError> {
        let inverse = self.apply(Edit::Remove(id), &mut |_, _| false)?;
        self.undo.push(inverse);
        self.redo.clear();
        Ok(())
    }

    pub fn can_undo(&self) -> bool {
        !self.undo.is_empty()
    }

    pub fn can_redo(&self) -> bool {
        !self.redo.is_empty()
    }

    /// Reverts the last add or remove. A constraint that comes back keeps its bits; only worlds
    /// that arrived while it was off are evaluated, with `evaluator`. Returns whether there was
    /// anything to undo.
    pub fn undo(&mut self, mut evaluator: impl FnMut(&Constraint, u32) -> bool) -> bool {
        self.step(true, &mut evaluator)
    }

    /// Re-applies the last undone edit (see [`undo`](Self::undo)).
    pub fn redo(&mut self, mut evaluator: impl FnMut(&Constraint, u32) -> bool) -> bool {
        self.step(false, &mut evaluator)
    }

    fn step(&mut self, undo: bool, evaluator: &mut dyn FnMut(&Constraint, u32) -> bool) -> bool {
        let popped = if undo {
            self.undo.pop()
        } else {
            self.redo.pop()
        };
        let Some(edit) = popped else {
            return false;
        };
        match self.apply(edit.clone(), evaluator) {
            Ok(inverse) => {
                if undo {
                    self.redo.push(inverse);
                } else {
                    self.undo.push(inverse);
                }
                true
            }
            // Unreachable while the stacks stay consistent (edits are LIFO); keep the edit.
            Err(_) => {
                if undo {
                    self.undo.push(edit);
                } else {
                    self.redo.push(edit);
                }
                false
            }
        }
    }

    fn apply(
        &mut self,
        edit: Edit,
        evaluator: &mut dyn FnMut(&Constraint, u32) -> bool,
    ) -> Result<Edit, BrowseError> {
        match edit {
            Edit::Insert { parked, position } => {
                let Parked {
                    constraint,
                    mut satisfied,
                    evaluated,
                } = *parked;
                let id = constraint.id;
                if self.find(id).is_some() {
                    return Err(BrowseError::DuplicateConstraint(id.0));
                }
                for w in self.worlds.and_not(&evaluated).iter() {
                    satisfied.set(w, evaluator(&constraint, w));
                }
                satisfied.and_assign(&self.worlds);
                // Adding a constraint only narrows the result.
                self.result.and_assign(&satisfied);
                let position = position.min(self.live.len());
                self.live.insert(
                    position,
                    Live {
                        constraint,
                        satisfied,
                    },
                );
                Ok(Edit::Remove(id))
            }
            Edit::Remove(id) => {
                let position = self.find(id).ok_or(BrowseError::UnknownConstraint(id.0))?;
                let Live {
                    constraint,
                    satisfied,
                } = self.live.remove(position);
                // §4.4.2: the AND of the remaining bitsets; no geometry is re-evaluated.
                self.recompute();
                Ok(Edit::Insert {
                    parked: Box::new(Parked {
                        constraint,
                        satisfied,
                        evaluated: self.worlds.clone(),
                    }),
                    position,
                })
            }
        }
    }

    /// A world arrived (or was re-ingested): evaluates it against every live constraint and
    /// updates the result (§4.4: new worlds are evaluated against all live constraints as they
    /// arrive). Parked constraints catch up when they come back.
    pub fn on_new_world(
        &mut self,
        world: u32,
        mut evaluator: impl FnMut(&Constraint, u32) -> bool,
    ) {
        self.worlds.insert(world);
        let mut all = true;
        for l in &mut self.live {
            let ok = evaluator(&l.constraint, world);
            l.satisfied.set(world, ok);
            all &= ok;
        }
        self.result.set(world, all);
    }

    /// A world left the store (evicted under the memory cap): it disappears from every bitset,
    /// including those of parked constraints, so that a later world with the same index is
    /// evaluated afresh.
    pub fn forget_world(&mut self, world: u32) {
        self.worlds.remove(world);
        self.result.remove(world);
        for l in &mut self.live {
            l.satisfied.remove(world);
        }
        for edit in self.undo.iter_mut().chain(self.redo.iter_mut()) {
            if let Edit::Insert { parked, .. } = edit {
                parked.satisfied.remove(world);
                parked.evaluated.remove(world);
            }
        }
    }

    /// The live constraint whose drawn frustum the ray `origin + s·dir` enters first (§4.4.2:
    /// the user removes an older constraint by clicking on its frustum).
    pub fn pick(&self, origin: Vec3, dir: Vec3) -> Option<ConstraintId> {
        self.live
            .iter()
            .filter_map(|l| {
                l.constraint
                    .frustum
                    .ray_hit(origin, dir)
                    .map(|s| (s, l.constraint.id))
            })
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map(|(_, id)| id)
    }
}

#[cfg(test)]
mod tests;
