//! Who answers the animator's constraints: this process (offline worlds) or node-query (a live
//! store). Either way the viewer sees the same things — the live constraints with their
//! counts, the survivors, whether undo and redo can do anything — so the UI does not care.
//!
//! * [`Session::Local`] holds a [`ConstraintSet`] and evaluates every constraint here with
//!   `Constraint::evaluate` over the worlds' path trees: the code a store shard runs.
//! * [`Session::Remote`] mirrors node-query's last answer for the viewer's browsing session.
//!   Edits become requests ([`Command::Browse`]) that the bus task sends; the answer comes back
//!   as a message. node-query's status carries no frustum, so the geometry of the constraints
//!   this viewer drew is kept here, for drawing their outlines.

use std::collections::BTreeMap;

use mwb_core::browse::api::{Request, SessionStatus};

use crate::state::RankSpec;
use mwb_core::browse::{
    Constraint, ConstraintId, ConstraintSet, Frustum, Polarity, Quantifier, Scope, TimeWindow,
    WorldSet,
};

/// What the state asks the bus task to do (live viewers only).
#[derive(Debug, Clone, PartialEq)]
pub enum Command {
    /// A browsing request for node-query, in the viewer's session.
    Browse(Request),
    /// A ranking by node-query (§4.4.3).
    Rank(RankSpec),
    /// Fetch world `world` (of `job`) from the store and decode its motion.
    FetchMotion { world: u32, job: String },
    /// Fetch the indexed paths of these worlds, which the viewer does not hold (it holds a
    /// sample of a large store, `live::LiveConfig::max_worlds`): a world picked from the
    /// ranking, say.
    FetchPaths(Vec<u32>),
    /// Read the scene (a file, or a shipped scene's name), write `sim` into it (`auto`
    /// calibrated), check it for what the simulator cannot do faithfully (a refusal is the
    /// notice), announce a sampling job of `worlds` worlds at `quality`, and wait for a store to
    /// acknowledge it.
    SubmitJob {
        scene: String,
        worlds: u32,
        quality: mwb_proto::v1::Quality,
        sim: Option<mwb_core::scene::SimPreset>,
    },
    /// Cancel an open job.
    CancelJob(String),
    /// Refine stored world `world` (§4.5): re-simulate `objects` from the first frame one of
    /// them is inside `frustum`, `worlds` times (the bus task fetches the world and its job,
    /// checks the request with `mwb_sampler::request::plan` and submits a REFINE job).
    Refine {
        world: u32,
        objects: Vec<u32>,
        frustum: Box<Frustum>,
        worlds: u32,
    },
}

/// One live constraint as the UI lists it.
#[derive(Debug, Clone, PartialEq)]
pub struct ConstraintRow {
    pub id: ConstraintId,
    pub polarity: Polarity,
    pub objects: Vec<u32>,
    pub quantifier: Quantifier,
    pub window: Option<TimeWindow>,
    pub scope: Scope,
    /// Worlds satisfying it.
    pub satisfied: u64,
    /// Its frustum, when known here (a constraint another client added to a shared live
    /// session has none).
    pub frustum: Option<Frustum>,
}

/// node-query's view of the viewer's session, as last answered.
#[derive(Debug, Clone, Default)]
pub struct Remote {
    /// The constraints this viewer drew, by id (kept after removal: redo brings them back).
    pub drawn: BTreeMap<ConstraintId, Constraint>,
    pub status: SessionStatus,
    pub survivors: WorldSet,
    /// Edits handed to the bus task.
    pub sent: u32,
    /// Edits sent whose answer has not come back.
    pub pending: u32,
    /// Whether any answer came back yet.
    pub answered: bool,
}

/// Where the session lives.
#[derive(Debug, Clone)]
pub enum Session {
    Local(ConstraintSet),
    Remote(Box<Remote>),
}

impl Session {
    pub fn is_remote(&self) -> bool {
        matches!(self, Session::Remote(_))
    }

    /// The live constraints with their counts, in the order they were added.
    pub fn rows(&self) -> Vec<ConstraintRow> {
        match self {
            Session::Local(set) => set
                .constraints()
                .map(|c| ConstraintRow {
                    id: c.id,
                    polarity: c.polarity,
                    objects: c.objects.clone(),
                    quantifier: c.quantifier,
                    window: c.window,
                    scope: c.scope,
                    satisfied: set.satisfied(c.id).map_or(0, |s| s.len() as u64),
                    frustum: Some(c.frustum),
                })
                .collect(),
            Session::Remote(r) => r
                .status
                .constraints
                .iter()
                .map(|c| ConstraintRow {
                    id: c.id,
                    polarity: c.polarity,
                    objects: c.objects.clone(),
                    quantifier: c.quantifier,
                    window: c.window,
                    scope: c.scope,
                    satisfied: c.satisfied,
                    frustum: r.drawn.get(&c.id).map(|d| d.frustum),
                })
                .collect(),
        }
    }

    /// The surviving worlds.
    pub fn survivors(&self) -> &WorldSet {
        match self {
            Session::Local(set) => set.result(),
            Session::Remote(r) => &r.survivors,
        }
    }

    /// How many worlds survive (a live session counts the store's worlds, which may be more
    /// than the viewer has loaded).
    pub fn survivor_count(&self) -> u64 {
        match self {
            Session::Local(set) => set.result().len() as u64,
            Session::Remote(r) => r.status.result,
        }
    }

    pub fn can_undo(&self) -> bool {
        match self {
            Session::Local(set) => set.can_undo(),
            Session::Remote(r) => r.status.can_undo,
        }
    }

    pub fn can_redo(&self) -> bool {
        match self {
            Session::Local(set) => set.can_redo(),
            Session::Remote(r) => r.status.can_redo,
        }
    }

    /// The next constraint id no constraint of the session has used.
    pub fn next_id(&self, floor: u64) -> ConstraintId {
        let used = match self {
            Session::Local(set) => set.constraints().map(|c| c.id.0).max().unwrap_or(0),
            Session::Remote(r) => r
                .status
                .constraints
                .iter()
                .map(|c| c.id.0)
                .chain(r.drawn.keys().map(|k| k.0))
                .max()
                .unwrap_or(0),
        };
        ConstraintId(used.max(floor.saturating_sub(1)) + 1)
    }
}
