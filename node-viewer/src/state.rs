//! The viewer's whole state, changed only by [`Msg`]s: no window, no I/O, no clock of its own.
//!
//! A screen rectangle through the current camera becomes a [`Frustum`] with
//! [`mwb_core::browse::Camera::frustum`] and a [`Constraint`] over the chosen objects
//! (§4.4.1–4.4.2 of Twigg and James, SIGGRAPH 2007). Offline, the [`Session`] evaluates it here
//! over the worlds' path trees; live, the state queues a request ([`Command`]) for the bus task
//! and mirrors node-query's answer when it comes back as a message. The same holds for
//! rankings (§4.4.3) and for a world's motion, which a live viewer fetches when it is shown.

use std::collections::{HashSet, VecDeque};
use std::sync::Arc;

use mwb_core::browse::api::{Reply, Request, SessionStatus};
use mwb_core::browse::{
    Constraint, ConstraintId, ConstraintSet, Frustum, Order, Polarity, Quat, RankKey, Ranked,
    ScreenRect, TimeWindow, Viewport, WorldSet, top_k_counted,
};
use mwb_core::scene::{Body, StaticBody};

use crate::ViewerError;
use crate::camera::OrbitCamera;
use crate::math::V3;
use crate::session::{Command, ConstraintRow, Session};
use crate::world::{Motion, WorldData};

/// Playback speeds the timeline allows.
pub const MIN_SPEED: f64 = 0.1;
pub const MAX_SPEED: f64 = 4.0;
/// Decoded motions a live viewer keeps (the selected world's is never dropped).
pub const MOTION_CACHE: usize = 64;

/// The playback clock of the selected world.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Playback {
    /// Simulated time shown, seconds.
    pub time: f64,
    pub playing: bool,
    /// Simulated seconds per wall second, in [[`MIN_SPEED`], [`MAX_SPEED`]].
    pub speed: f64,
    pub looping: bool,
}

impl Default for Playback {
    fn default() -> Self {
        Self {
            time: 0.0,
            playing: false,
            speed: 1.0,
            looping: true,
        }
    }
}

/// What the metric sorter ranks by (§4.4.3).
#[derive(Debug, Clone, PartialEq)]
pub struct RankSpec {
    pub key: RankKey,
    pub order: Order,
    pub k: usize,
    /// Rank every world, not only the survivors (what §4.4.3 does for "constraints satisfied",
    /// to suggest worlds worth refining).
    pub all_worlds: bool,
}

impl RankSpec {
    /// The browsing request that asks node-query for this ranking.
    pub fn request(&self) -> Request {
        Request::Rank {
            key: self.key.clone(),
            order: self.order,
            k: self.k,
            all_worlds: self.all_worlds,
            plausible_only: false,
        }
    }
}

/// A camera kept to come back to (the Views panel), by name. Saved views are kept with the
/// session on disk by the app ([`crate::views`]); the state only holds them.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SavedView {
    pub name: String,
    pub camera: OrbitCamera,
}

/// A goal orientation picked in the view (§4.4.3: rank by "orientation error to a goal"): one
/// object's decoded orientation at one frame of a world being played back. Rankings by
/// [`RankKey::OrientationTo`] measure each chosen object's final orientation against it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Goal {
    /// Unit quaternion `[x, y, z, w]`, world frame: the decoded frame's, normalised.
    pub rotation: Quat,
    pub world: u32,
    pub object: u32,
    /// The decoded frame it was taken from (the playback time rounded to a frame).
    pub frame: usize,
    /// That frame's time, seconds.
    pub time: f64,
}

/// The sorter's current answer.
#[derive(Debug, Clone, PartialEq)]
pub struct Ranking {
    pub spec: RankSpec,
    /// Worlds ranked over.
    pub candidates: u64,
    /// Candidates without a value (ranked last).
    pub unscored: u64,
    pub rows: Vec<Ranked>,
}

/// The bus as a live viewer last saw it (shown in the status bar).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LinkStatus {
    /// Where the viewer connects, as the user gave it.
    pub endpoint: String,
    /// The most worlds the viewer holds the paths of (0: no limit); when the stores hold more,
    /// it holds a sample of them (`live::LiveConfig::max_worlds`).
    pub max_worlds: usize,
    /// Worlds the stores have indexed, as their path batches said.
    pub indexed: u64,
    /// Worlds the bus task has handed over and not let go since (all of them, or its sample).
    pub held: u64,
    /// The last poll read every shard's new worlds to the end and fetched the sampled
    /// survivors without an error: what the viewer holds is what it will hold until more
    /// worlds arrive or the survivors change.
    pub synced: bool,
    /// The last round trip to the bus succeeded.
    pub connected: bool,
    pub stores: u32,
    pub samplers: u32,
    /// Worlds the stores hold (their statistics).
    pub store_worlds: u64,
    pub memory_bytes: u64,
    pub memory_cap_bytes: u64,
    /// Worlds per second arriving, over the last few seconds.
    pub worlds_per_s: f64,
    /// Open jobs: id, worlds done, worlds wanted.
    pub jobs: Vec<(String, u32, u32)>,
    /// Why the last request failed, if it did.
    pub error: Option<String>,
}

/// Everything that changes the state.
#[derive(Debug, Clone)]
pub enum Msg {
    /// Turn the camera about its target, radians.
    Orbit {
        d_yaw: f64,
        d_pitch: f64,
    },
    /// Slide the camera by pixels on a view `height` pixels tall.
    Pan {
        dx: f64,
        dy: f64,
        height: f64,
    },
    /// Dolly: `factor` < 1 comes closer.
    Zoom {
        factor: f64,
    },
    /// Frame every path and body (A), for a view of this aspect ratio.
    FrameAll {
        aspect: f64,
    },
    /// Frame the selected world's paths of the chosen objects (F; every path when no world is
    /// selected).
    FrameSelected {
        aspect: f64,
    },
    /// Keep the current camera as a named view.
    SaveView(String),
    /// The views kept with the session, read at start (replaces the list; not an edit, so
    /// [`ViewerState::views_edits`] does not move).
    LoadViews(Vec<SavedView>),
    /// Go back to saved view `i`.
    RecallView(usize),
    DeleteView(usize),
    SetCamera(OrbitCamera),
    /// A rectangle drawn on a view of `viewport` pixels through the current camera.
    AddConstraint {
        viewport: Viewport,
        rect: ScreenRect,
        polarity: Polarity,
    },
    RemoveConstraint(ConstraintId),
    Undo,
    Redo,
    /// Show / hide an object's paths and include / exclude it from new constraints.
    ToggleObject(u32),
    /// Choose exactly these objects (unknown ones are ignored).
    ChooseObjects(Vec<u32>),
    /// Limit new constraints to a time window (`None`: any time).
    SetWindow(Option<TimeWindow>),
    SelectWorld(Option<u32>),
    Play,
    Pause,
    TogglePlay,
    /// Jump to a simulated time (clamped to the selected world's motion).
    Seek(f64),
    /// One frame step forward (+1) or back (−1) of the selected world.
    Step(i32),
    /// Wall-clock seconds passed (the window's frame time): advances playback when playing.
    Tick(f64),
    SetSpeed(f64),
    SetLoop(bool),
    /// Rank by this (`None`: no ranking).
    Rank(Option<RankSpec>),
    /// Take the goal orientation from the playback: the first chosen object's decoded
    /// orientation in the shown world at the frame nearest the playback time. A ranking by
    /// orientation to a goal is redone with it.
    GoalFromPlayback,
    ClearGoal,

    // What a live viewer's bus task reports.
    /// The scene the worlds are of: its name, body names and static geometry, and its bodies
    /// as one instance (seed 0) starts them — drawn while no world's motion is shown.
    Scene {
        name: String,
        bodies: Vec<String>,
        statics: Vec<StaticBody>,
        initial: Vec<Body>,
    },
    /// Worlds that arrived (their indexed paths). Live, a world already held is kept as it is
    /// (the bus task may send a world again that the state kept past an [`Msg::Evict`]).
    Worlds(Vec<WorldData>),
    /// Live: the bus task no longer holds these worlds in its sample (`live::LiveConfig::
    /// max_worlds`); the state lets them go, except the world shown or picked and those whose
    /// motion is loaded or on its way.
    Evict(Vec<u32>),
    /// A shard's worlds are gone (it restarted without them): forget worlds `index ≡ shard
    /// (mod count)`.
    ForgetShard {
        shard: u32,
        count: u32,
    },
    /// node-query's answer about the session: its status and every survivor, and how many of
    /// the edits the state sent the bus task has handled (answered or failed) so far.
    Session {
        status: SessionStatus,
        survivors: Vec<u32>,
        handled_edits: u32,
    },
    /// node-query's answer to a ranking request.
    Ranked {
        spec: RankSpec,
        reply: Reply,
    },
    /// A browsing request was refused or could not be sent.
    BrowseFailed(String),
    /// Something the bus task could not use (a malformed answer, a world that does not
    /// decode): shown, never fatal.
    Problem(String),
    /// A world's motion, fetched and decoded (or why not).
    MotionLoaded {
        world: u32,
        motion: Result<Arc<Motion>, String>,
    },
    Link(LinkStatus),
    /// The user asks for a job (live only): see [`Command::SubmitJob`].
    SubmitJob {
        scene: String,
        worlds: u32,
        quality: mwb_proto::v1::Quality,
        /// Simulation preset written into the job's scene (`auto` calibrated first); `None`:
        /// the scene's own.
        sim: Option<mwb_core::scene::SimPreset>,
    },
    CancelJob(String),
    /// Refine the shown world (live only): its chosen objects, from the first frame one of
    /// them is inside the rectangle drawn on a view of `viewport` pixels through the current
    /// camera (§4.5); `worlds` new worlds. See [`Command::Refine`].
    Refine {
        viewport: Viewport,
        rect: ScreenRect,
        worlds: u32,
    },
    /// What became of a job submission or cancellation.
    JobNotice(Result<String, String>),
}

/// The viewer state: scene, worlds, camera, constraints, selection, playback.
#[derive(Debug, Clone)]
pub struct ViewerState {
    scene_name: String,
    body_names: Vec<String>,
    statics: Vec<StaticBody>,
    /// The bodies where an instance of the scene starts them (seed 0; a scene with
    /// distributions starts each world elsewhere): drawn while no world's motion is shown, so
    /// an author sees the scene before any world exists (`mwb scene preview`).
    initial: Vec<Body>,
    /// Sorted by index (live stores number sparsely across shards).
    worlds: Vec<WorldData>,
    /// Worlds that could not be used, with why (shown, never fatal).
    problems: Vec<String>,
    pub camera: OrbitCamera,
    session: Session,
    /// Lowest id for the next constraint.
    next_constraint: u64,
    /// Per object: its paths are drawn and new constraints are over it.
    chosen: Vec<bool>,
    window: Option<TimeWindow>,
    selected: Option<u32>,
    playback: Playback,
    ranking: Option<Ranking>,
    rank_spec: Option<RankSpec>,
    goal: Option<Goal>,
    /// Requests for the bus task, oldest first.
    outbox: Vec<Command>,
    /// Live: worlds whose motion was asked for and has not come back.
    fetching: Vec<u32>,
    /// Live: worlds whose motion is loaded, least recently loaded first.
    loaded: VecDeque<u32>,
    /// Live: a world picked whose paths were asked for ([`Command::FetchPaths`]); picked when
    /// they arrive.
    wanted_selection: Option<u32>,
    link: Option<LinkStatus>,
    /// The last browsing error (shown until the next successful answer).
    browse_error: Option<String>,
    /// What became of the last job submitted or cancelled.
    job_notice: Option<Result<String, String>>,
    /// Axis-aligned box of every path vertex and bounded static, kept as worlds arrive.
    extent: Option<(V3, V3)>,
    /// Saved cameras, by name, in the order saved.
    views: Vec<SavedView>,
    /// Changes the user made to `views` (the app writes them to disk when this moves).
    views_edits: u64,
}

/// The smallest sphere about the line through both centres that holds `sphere` and the ball
/// (`p`, `radius`) (one step of Ritter's bounding sphere). Non-finite points change nothing.
fn grow_sphere(sphere: (V3, f64), p: V3, radius: f64) -> (V3, f64) {
    let (c, r) = sphere;
    if !(p.iter().all(|v| v.is_finite()) && radius.is_finite()) {
        return sphere;
    }
    let d = crate::math::len(crate::math::sub(p, c));
    if d + radius <= r {
        return sphere;
    }
    if d < 1e-12 {
        return (c, radius);
    }
    let grown = 0.5 * (r + d + radius);
    let shift = crate::math::scale(crate::math::sub(p, c), (grown - r) / d);
    (crate::math::add(c, shift), grown)
}

fn find(worlds: &[WorldData], w: u32) -> Option<&WorldData> {
    worlds
        .binary_search_by_key(&w, |d| d.index)
        .ok()
        .map(|i| &worlds[i])
}

fn evaluate(worlds: &[WorldData], c: &Constraint, w: u32) -> bool {
    let Some(world) = find(worlds, w) else {
        // Unknown worlds touch nothing.
        return c.satisfied_given(false);
    };
    c.evaluate(|object| {
        world
            .paths
            .get(object as usize)
            .map(|p| (&p.tree, p.radius))
    })
}

impl ViewerState {
    /// An offline state for a scene with `body_names` (scene order) and its static geometry:
    /// constraints are evaluated here.
    pub fn new(
        scene_name: impl Into<String>,
        body_names: Vec<String>,
        statics: Vec<StaticBody>,
    ) -> Self {
        let chosen = vec![true; body_names.len()];
        let mut s = Self {
            scene_name: scene_name.into(),
            body_names,
            statics,
            initial: Vec::new(),
            worlds: Vec::new(),
            problems: Vec::new(),
            camera: OrbitCamera::default(),
            session: Session::Local(ConstraintSet::new()),
            next_constraint: 1,
            chosen,
            window: None,
            selected: None,
            playback: Playback::default(),
            ranking: None,
            rank_spec: None,
            goal: None,
            outbox: Vec::new(),
            fetching: Vec::new(),
            loaded: VecDeque::new(),
            wanted_selection: None,
            link: None,
            browse_error: None,
            job_notice: None,
            extent: None,
            views: Vec::new(),
            views_edits: 0,
        };
        s.recompute_extent();
        s
    }

    /// A live state: worlds, the scene and answers arrive as messages from the bus task, and
    /// edits leave as [`Command`]s ([`take_commands`](Self::take_commands)).
    pub fn live(endpoint: impl Into<String>) -> Self {
        let mut s = Self::new("(waiting for the store)", Vec::new(), Vec::new());
        s.session = Session::Remote(Box::default());
        s.link = Some(LinkStatus {
            endpoint: endpoint.into(),
            ..LinkStatus::default()
        });
        s
    }

    pub fn is_live(&self) -> bool {
        self.session.is_remote()
    }

    /// Gives the state the scene's bodies where an instance starts them (see
    /// [`initial`](Self::initial)). Bodies beyond the scene's body names are ignored.
    pub fn with_initial(mut self, bodies: Vec<Body>) -> Self {
        self.set_initial(bodies);
        self
    }

    fn set_initial(&mut self, mut bodies: Vec<Body>) {
        bodies.truncate(self.body_names.len());
        self.initial = bodies;
        self.recompute_extent();
    }

    /// The bodies where an instance of the scene starts them (empty when unknown).
    pub fn initial(&self) -> &[Body] {
        &self.initial
    }

    /// Adds a world (its index must not be taken). Offline it is evaluated against every live
    /// constraint (§4.4: worlds arriving later are filtered too); live, the store does that.
    pub fn add_world(&mut self, world: WorldData) -> Result<(), ViewerError> {
        let at = match self.worlds.binary_search_by_key(&world.index, |d| d.index) {
            Ok(_) => {
                return Err(ViewerError::WorldIndex { found: world.index });
            }
            Err(at) => at,
        };
        if !self.body_names.is_empty() && world.paths.len() != self.body_names.len() {
            return Err(ViewerError::BodyCount {
                scene: self.body_names.len(),
                motion: world.paths.len(),
            });
        }
        let index = world.index;
        let points: Vec<V3> = world
            .paths
            .iter()
            .flat_map(|p| p.tree.path().points().iter().copied())
            .collect();
        self.extend_extent(points.into_iter());
        self.worlds.insert(at, world);
        if let Session::Local(set) = &mut self.session {
            let worlds = &self.worlds;
            set.on_new_world(index, |c, w| evaluate(worlds, c, w));
        }
        Ok(())
    }

    /// Records a world that could not be used (shown in the status bar).
    pub fn add_problem(&mut self, what: String) {
        self.problems.push(what);
    }

    pub fn scene_name(&self) -> &str {
        &self.scene_name
    }

    pub fn body_names(&self) -> &[String] {
        &self.body_names
    }

    pub fn statics(&self) -> &[StaticBody] {
        &self.statics
    }

    /// The worlds loaded here, by index.
    pub fn worlds(&self) -> &[WorldData] {
        &self.worlds
    }

    /// World `w`, if loaded.
    pub fn world(&self, w: u32) -> Option<&WorldData> {
        find(&self.worlds, w)
    }

    pub fn problems(&self) -> &[String] {
        &self.problems
    }

    /// The live constraints with their counts.
    pub fn constraint_rows(&self) -> Vec<ConstraintRow> {
        self.session.rows()
    }

    /// The live constraints whose geometry is known here (for drawing and tests).
    pub fn constraint_list(&self) -> Vec<Constraint> {
        match &self.session {
            Session::Local(set) => set.constraints().cloned().collect(),
            Session::Remote(r) => r
                .status
                .constraints
                .iter()
                .filter_map(|c| r.drawn.get(&c.id).cloned())
                .collect(),
        }
    }

    pub fn can_undo(&self) -> bool {
        self.session.can_undo()
    }

    pub fn can_redo(&self) -> bool {
        self.session.can_redo()
    }

    /// Whether world `w` satisfies every live constraint.
    pub fn survives(&self, w: u32) -> bool {
        self.session.survivors().contains(w)
    }

    /// The survivors, ascending (live: those the store named, loaded here or not).
    pub fn survivors(&self) -> impl Iterator<Item = u32> + '_ {
        self.session.survivors().iter()
    }

    /// Worlds satisfying every live constraint (live: of all the store holds).
    pub fn survivor_count(&self) -> u64 {
        self.session.survivor_count()
    }

    /// The survivors whose paths are held here (live, a sample of them when the stores hold
    /// more worlds than the viewer does).
    pub fn held_survivors(&self) -> usize {
        let survivors = self.session.survivors();
        self.worlds
            .iter()
            .filter(|w| survivors.contains(w.index))
            .count()
    }

    /// Worlds browsed: loaded here (offline), or held by the stores (live).
    pub fn world_total(&self) -> u64 {
        match &self.session {
            Session::Local(_) => self.worlds.len() as u64,
            Session::Remote(r) => r.status.worlds.max(self.worlds.len() as u64),
        }
    }

    /// Live: whether the viewer holds all it will hold of the stores' first `target` worlds
    /// (every one of them, or its sample when they are more than it holds, see
    /// [`LinkStatus::max_worlds`]): the stores have indexed `target`, the bus task's last poll
    /// was [`synced`](LinkStatus::synced) and every world it holds has arrived here. Always
    /// false offline and for a `target` of 0.
    pub fn holds_worlds(&self, target: u64) -> bool {
        self.link.as_ref().is_some_and(|l| {
            l.connected
                && l.synced
                && target > 0
                && l.indexed >= target
                && self.worlds.len() as u64 >= l.held.min(target)
        })
    }

    /// Live: edits sent whose answer has not come back.
    pub fn pending(&self) -> u32 {
        match &self.session {
            Session::Local(_) => 0,
            Session::Remote(r) => r.pending,
        }
    }

    pub fn link(&self) -> Option<&LinkStatus> {
        self.link.as_ref()
    }

    /// The saved views, in the order saved.
    pub fn views(&self) -> &[SavedView] {
        &self.views
    }

    /// How many times the user saved or deleted a view: the app keeps the views on disk and
    /// writes them when this moves (loading them does not count).
    pub fn views_edits(&self) -> u64 {
        self.views_edits
    }

    /// The first free name "view N" (N from 1), for the next view saved.
    pub fn next_view_name(&self) -> String {
        (1..)
            .map(|n| format!("view {n}"))
            .find(|name| !self.views.iter().any(|v| v.name == *name))
            .unwrap_or_default()
    }

    /// What became of the last job submitted or cancelled.
    pub fn job_notice(&self) -> Option<&Result<String, String>> {
        self.job_notice.as_ref()
    }

    pub fn browse_error(&self) -> Option<&str> {
        self.browse_error.as_deref()
    }

    pub fn ranking(&self) -> Option<&Ranking> {
        self.ranking.as_ref()
    }

    pub fn rank_spec(&self) -> Option<&RankSpec> {
        self.rank_spec.as_ref()
    }

    /// The goal orientation picked in the view, if any.
    pub fn goal(&self) -> Option<&Goal> {
        self.goal.as_ref()
    }

    /// Takes the requests queued for the bus task.
    pub fn take_commands(&mut self) -> Vec<Command> {
        std::mem::take(&mut self.outbox)
    }

    pub fn is_chosen(&self, object: u32) -> bool {
        self.chosen.get(object as usize).copied().unwrap_or(false)
    }

    /// The objects new constraints are over, ascending.
    pub fn chosen_objects(&self) -> Vec<u32> {
        (0..self.chosen.len() as u32)
            .filter(|&o| self.is_chosen(o))
            .collect()
    }

    pub fn window(&self) -> Option<TimeWindow> {
        self.window
    }

    pub fn selected(&self) -> Option<u32> {
        self.selected
    }

    pub fn playback(&self) -> Playback {
        self.playback
    }

    /// The world whose bodies are drawn: the selected one, else the first loaded survivor.
    pub fn shown_world(&self) -> Option<&WorldData> {
        match self.selected {
            Some(w) => self.world(w),
            None => self.survivors().find_map(|w| self.world(w)),
        }
    }

    /// Whether the shown world's motion is being fetched.
    pub fn shown_loading(&self) -> bool {
        self.shown_world()
            .is_some_and(|w| w.motion.is_none() && self.fetching.contains(&w.index))
    }

    /// Length of the timeline: the shown world's motion, or the longest world's.
    pub fn duration(&self) -> f64 {
        match self.shown_world() {
            Some(w) => w.duration(),
            None => self
                .worlds
                .iter()
                .map(WorldData::duration)
                .fold(0.0, f64::max),
        }
    }

    /// A sphere around every path of every world and the bounded statics (the ground grid's
    /// extent); kept up to date as worlds arrive, so a frame does not walk every path.
    pub fn bounds(&self) -> Option<(V3, f64)> {
        let (lo, hi) = self.extent?;
        let c = crate::math::scale(crate::math::add(lo, hi), 0.5);
        Some((
            c,
            (0.5 * crate::math::len(crate::math::sub(hi, lo))).max(0.1),
        ))
    }

    /// Grows the cached extent by `points`.
    fn extend_extent(&mut self, points: impl Iterator<Item = V3>) {
        for p in points {
            if !p.iter().all(|c| c.is_finite()) {
                continue;
            }
            let (lo, hi) = self.extent.get_or_insert((p, p));
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
    }

    /// Recomputes the cached extent from every world and static.
    fn recompute_extent(&mut self) {
        self.extent = None;
        let statics: Vec<V3> = self
            .statics
            .iter()
            .filter_map(|s| match &s.shape {
                mwb_core::scene::Shape::Plane { .. } => None,
                _ => Some(s.position),
            })
            .collect();
        let paths: Vec<V3> = self
            .worlds
            .iter()
            .flat_map(|w| w.paths.iter())
            .flat_map(|p| p.tree.path().points().iter().copied())
            .collect();
        let starts: Vec<V3> = self.initial.iter().map(|b| b.position).collect();
        self.extend_extent(statics.into_iter().chain(paths).chain(starts));
    }

    /// What "frame all" (`world` `None`) or "frame selected" frames: a sphere around the bulk
    /// of the chosen objects' paths (of that world, if it is loaded) — the median point, out to
    /// the distance within which 99 % of the path vertices lie — and, framing all, the bounded
    /// statics. A few bodies thrown far away would otherwise shrink every other path to a dot.
    /// (At most 20 000 vertices are looked at, evenly spread.) Framing all, the sphere then
    /// grows to hold what the scene is made of: every bounded static whole (unless it is far
    /// larger than the paths, like a floor box) and where each chosen body starts — the tower's
    /// projectile and backstop, which few path vertices are near.
    pub fn framing(&self, world: Option<u32>) -> Option<(V3, f64)> {
        let worlds: &[WorldData] = match world.and_then(|w| self.world(w)) {
            Some(w) => std::slice::from_ref(w),
            None => &self.worlds,
        };
        let chosen: Vec<usize> = (0..self.chosen.len()).filter(|&o| self.chosen[o]).collect();
        let total: usize = worlds
            .iter()
            .flat_map(|w| chosen.iter().filter_map(move |&o| w.paths.get(o)))
            .map(|p| p.tree.path().len())
            .sum();
        let step = total.div_ceil(20_000).max(1);
        let mut points: Vec<V3> = worlds
            .iter()
            .flat_map(|w| chosen.iter().filter_map(move |&o| w.paths.get(o)))
            .flat_map(|p| p.tree.path().points().iter().copied())
            .step_by(step)
            .filter(|p| p.iter().all(|c| c.is_finite()))
            .collect();
        if world.is_none() {
            if points.is_empty() {
                // No paths yet: the scene as it starts is what there is to frame.
                points.extend(
                    self.initial
                        .iter()
                        .enumerate()
                        .filter(|&(o, _)| self.chosen.get(o).copied().unwrap_or(false))
                        .map(|(_, b)| b.position),
                );
            }
            points.extend(self.statics.iter().filter_map(|s| match &s.shape {
                mwb_core::scene::Shape::Plane { .. } => None,
                _ => Some(s.position),
            }));
        }
        if points.is_empty() {
            return None;
        }
        let median = |k: usize| {
            let mut v: Vec<f64> = points.iter().map(|p| p[k]).collect();
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        };
        let centre = [median(0), median(1), median(2)];
        let mut d: Vec<f64> = points
            .iter()
            .map(|p| crate::math::len(crate::math::sub(*p, centre)))
            .collect();
        d.sort_by(f64::total_cmp);
        let r = d[((d.len() - 1) as f64 * 0.99).round() as usize].max(0.5);
        let mut sphere = (centre, r);
        if world.is_none() {
            for s in &self.statics {
                let reach = s.shape.bounding_radius();
                if !(reach.is_finite() && reach <= 4.0 * r) {
                    continue;
                }
                match &s.shape {
                    mwb_core::scene::Shape::Box { half_extents: h } => {
                        for i in 0..8 {
                            let local =
                                [0, 1, 2].map(|k| if i >> k & 1 == 0 { -h[k] } else { h[k] });
                            let corner = crate::math::add(
                                s.position,
                                crate::camera::rotate(s.rotation, local),
                            );
                            sphere = grow_sphere(sphere, corner, 0.0);
                        }
                    }
                    _ => sphere = grow_sphere(sphere, s.position, reach),
                }
            }
            for w in &self.worlds {
                for &o in &chosen {
                    if let Some(start) = w.paths.get(o).and_then(|p| p.tree.path().points().first())
                    {
                        sphere = grow_sphere(sphere, *start, 0.0);
                    }
                }
            }
            for &o in &chosen {
                if let Some(b) = self.initial.get(o) {
                    sphere = grow_sphere(sphere, b.position, b.shape.bounding_radius());
                }
            }
        }
        Some(sphere)
    }

    /// Applies one message. Errors (a degenerate rectangle, an unknown constraint) leave the
    /// state as it was.
    pub fn update(&mut self, msg: Msg) -> Result<(), ViewerError> {
        let r = self.apply(msg);
        self.want_shown_motion();
        r
    }

    fn apply(&mut self, msg: Msg) -> Result<(), ViewerError> {
        match msg {
            Msg::Orbit { d_yaw, d_pitch } => self.camera.orbit(d_yaw, d_pitch),
            Msg::Pan { dx, dy, height } => self.camera.pan(dx, dy, height),
            Msg::Zoom { factor } => self.camera.zoom(factor),
            Msg::FrameAll { aspect } => {
                if let Some((c, r)) = self.framing(None) {
                    self.camera.frame(c, r, aspect);
                }
            }
            Msg::FrameSelected { aspect } => {
                if let Some((c, r)) = self.framing(self.selected) {
                    self.camera.frame(c, r, aspect);
                }
            }
            Msg::SaveView(name) => {
                self.views.push(SavedView {
                    name,
                    camera: self.camera,
                });
                self.views_edits += 1;
            }
            Msg::LoadViews(views) => self.views = views,
            Msg::RecallView(i) => {
                if let Some(v) = self.views.get(i) {
                    self.camera = v.camera;
                }
            }
            Msg::DeleteView(i) => {
                if i < self.views.len() {
                    self.views.remove(i);
                    self.views_edits += 1;
                }
            }
            Msg::SetCamera(c) => self.camera = c,
            Msg::AddConstraint {
                viewport,
                rect,
                polarity,
            } => {
                let frustum = self.camera.browse_camera(viewport).frustum(&rect)?;
                self.add_frustum(frustum, polarity)?;
            }
            Msg::RemoveConstraint(id) => match &mut self.session {
                Session::Local(set) => {
                    set.remove(id)?;
                    self.rerank_local();
                }
                Session::Remote(r) => {
                    if !r.status.constraints.iter().any(|c| c.id == id) {
                        return Err(mwb_core::browse::BrowseError::UnknownConstraint(id.0).into());
                    }
                    self.send_edit(Request::Remove { id });
                }
            },
            Msg::Undo | Msg::Redo => {
                let undo = matches!(msg, Msg::Undo);
                match &mut self.session {
                    Session::Local(set) => {
                        let worlds = &self.worlds;
                        if undo {
                            set.undo(|c, w| evaluate(worlds, c, w));
                        } else {
                            set.redo(|c, w| evaluate(worlds, c, w));
                        }
                        self.rerank_local();
                    }
                    Session::Remote(r) => {
                        // As offline: nothing to undo (or redo) is no edit at all.
                        let can = if undo {
                            r.status.can_undo
                        } else {
                            r.status.can_redo
                        };
                        if can {
                            self.send_edit(if undo { Request::Undo } else { Request::Redo });
                        }
                    }
                }
            }
            Msg::ToggleObject(o) => {
                if let Some(c) = self.chosen.get_mut(o as usize) {
                    *c = !*c;
                }
            }
            Msg::ChooseObjects(objects) => {
                self.chosen.fill(false);
                for o in objects {
                    if let Some(c) = self.chosen.get_mut(o as usize) {
                        *c = true;
                    }
                }
            }
            Msg::SetWindow(w) => self.window = w,
            Msg::SelectWorld(w) => self.select(w),
            Msg::Play => {
                if self.playback.time >= self.duration() {
                    self.playback.time = 0.0;
                }
                self.playback.playing = true;
            }
            Msg::Pause => self.playback.playing = false,
            Msg::TogglePlay => {
                let m = if self.playback.playing {
                    Msg::Pause
                } else {
                    Msg::Play
                };
                return self.apply(m);
            }
            Msg::Seek(t) => {
                if t.is_finite() {
                    self.playback.time = t.clamp(0.0, self.duration());
                }
            }
            Msg::Step(n) => {
                let dt = self.shown_world().map_or(1.0 / 60.0, |w| w.frame_dt);
                let frame = (self.playback.time / dt).round() + f64::from(n);
                self.playback.playing = false;
                self.playback.time = (frame * dt).clamp(0.0, self.duration());
            }
            Msg::Tick(dt) => self.tick(dt),
            Msg::SetSpeed(s) => {
                if s.is_finite() {
                    self.playback.speed = s.clamp(MIN_SPEED, MAX_SPEED);
                }
            }
            Msg::SetLoop(l) => self.playback.looping = l,
            Msg::Rank(spec) => {
                if let Some(s) = &spec {
                    s.key.validate()?;
                }
                self.rank_spec = spec;
                self.ranking = None;
                self.rerank();
            }
            Msg::GoalFromPlayback => {
                let goal = self.goal_from_playback()?;
                self.goal = Some(goal);
                if let Some(RankSpec {
                    key: RankKey::OrientationTo { goal: g, .. },
                    ..
                }) = &mut self.rank_spec
                {
                    *g = goal.rotation;
                    self.ranking = None;
                    self.rerank();
                }
            }
            Msg::ClearGoal => {
                self.goal = None;
                if let Some(RankSpec {
                    key: RankKey::OrientationTo { .. },
                    ..
                }) = &self.rank_spec
                {
                    self.rank_spec = None;
                    self.ranking = None;
                }
            }
            Msg::Scene {
                name,
                bodies,
                statics,
                initial,
            } => {
                if bodies.len() != self.body_names.len() {
                    self.chosen = vec![true; bodies.len()];
                }
                self.scene_name = name;
                self.body_names = bodies;
                self.statics = statics;
                self.set_initial(initial);
            }
            Msg::Worlds(worlds) => {
                let live = self.is_live();
                for w in worlds {
                    let i = w.index;
                    if live && self.world(i).is_some() {
                        continue;
                    }
                    if let Err(e) = self.add_world(w) {
                        self.problems.push(format!("world {i}: {e}"));
                    }
                    if self.wanted_selection == Some(i) {
                        self.wanted_selection = None;
                        self.select(Some(i));
                    }
                }
                self.rerank_local();
            }
            Msg::Evict(gone) => {
                let gone: HashSet<u32> = gone.into_iter().collect();
                let shown = self.shown_world().map(|w| w.index);
                let keep = |w: &WorldData| {
                    !gone.contains(&w.index)
                        || Some(w.index) == self.selected
                        || Some(w.index) == shown
                        || w.motion.is_some()
                        || self.fetching.contains(&w.index)
                };
                let before = self.worlds.len();
                let kept: Vec<WorldData> = std::mem::take(&mut self.worlds)
                    .into_iter()
                    .filter(keep)
                    .collect();
                self.worlds = kept;
                if self.worlds.len() != before {
                    self.recompute_extent();
                }
            }
            Msg::ForgetShard { shard, count } => {
                let gone = |w: u32| count > 0 && w % count == shard;
                self.worlds.retain(|w| !gone(w.index));
                self.recompute_extent();
                if self.selected.is_some_and(gone) {
                    self.selected = None;
                }
            }
            Msg::Session {
                status,
                survivors,
                handled_edits,
            } => self.on_session(status, survivors, handled_edits),
            Msg::Ranked { spec, reply } => self.on_ranked(spec, reply),
            Msg::BrowseFailed(e) => self.browse_error = Some(e),
            Msg::Problem(p) => self.problems.push(p),
            Msg::MotionLoaded { world, motion } => self.on_motion(world, motion),
            Msg::Link(l) => self.link = Some(l),
            Msg::SubmitJob {
                scene,
                worlds,
                quality,
                sim,
            } => {
                if !self.is_live() {
                    return Err(ViewerError::Offline("submitting jobs"));
                }
                self.job_notice = None;
                self.outbox.push(Command::SubmitJob {
                    scene,
                    worlds,
                    quality,
                    sim,
                });
            }
            Msg::CancelJob(job) => {
                if !self.is_live() {
                    return Err(ViewerError::Offline("cancelling jobs"));
                }
                self.outbox.push(Command::CancelJob(job));
            }
            Msg::Refine {
                viewport,
                rect,
                worlds,
            } => {
                if !self.is_live() {
                    return Err(ViewerError::Offline("refining a world"));
                }
                let Some(world) = self.selected else {
                    return Err(ViewerError::Refine("pick the world to refine first"));
                };
                let objects = self.chosen_objects();
                if objects.is_empty() {
                    return Err(ViewerError::Refine("choose the objects to re-simulate"));
                }
                if worlds == 0 {
                    return Err(ViewerError::Refine("ask for at least one world"));
                }
                let frustum = self.camera.browse_camera(viewport).frustum(&rect)?;
                self.job_notice = None;
                self.outbox.push(Command::Refine {
                    world,
                    objects,
                    frustum: Box::new(frustum),
                    worlds,
                });
            }
            Msg::JobNotice(n) => self.job_notice = Some(n),
        }
        Ok(())
    }

    /// The goal [`Msg::GoalFromPlayback`] takes: the first chosen object's orientation in the
    /// shown world's decoded motion at the frame nearest the playback time.
    fn goal_from_playback(&self) -> Result<Goal, ViewerError> {
        let object = *self
            .chosen_objects()
            .first()
            .ok_or(ViewerError::Goal("no object is chosen".into()))?;
        let world = self
            .shown_world()
            .ok_or(ViewerError::Goal("no world is being played back".into()))?;
        let motion = world.motion.as_ref().ok_or_else(|| {
            ViewerError::Goal(format!("world {}'s motion is not loaded yet", world.index))
        })?;
        let rotations = motion
            .tracks
            .get(object as usize)
            .map(|t| &t.rotations[..])
            .unwrap_or_default();
        let last = rotations.len().checked_sub(1).ok_or_else(|| {
            ViewerError::Goal(format!(
                "world {} has no motion of object {object}",
                world.index
            ))
        })?;
        let frame = ((self.playback.time / motion.frame_dt).round().max(0.0) as usize).min(last);
        let q = rotations[frame];
        let norm = q.iter().map(|c| c * c).sum::<f64>().sqrt();
        if !(norm.is_finite() && norm > 1e-12) {
            return Err(ViewerError::Goal(format!(
                "world {} frame {frame}: object {object}'s orientation {q:?} is not a rotation",
                world.index
            )));
        }
        Ok(Goal {
            rotation: q.map(|c| c / norm),
            world: world.index,
            object,
            frame,
            time: frame as f64 * motion.frame_dt,
        })
    }

    fn tick(&mut self, dt: f64) {
        if self.playback.playing && dt.is_finite() && dt > 0.0 {
            let end = self.duration();
            let t = self.playback.time + dt * self.playback.speed;
            if t <= end {
                self.playback.time = t;
            } else if self.playback.looping && end > 0.0 {
                self.playback.time = t.rem_euclid(end);
            } else {
                self.playback.time = end;
                self.playback.playing = false;
            }
        }
    }

    /// Adds a constraint over the chosen objects (and the time window, if any) and returns its
    /// id. Live, it is sent to node-query and counts once the answer is back.
    pub fn add_frustum(
        &mut self,
        frustum: Frustum,
        polarity: Polarity,
    ) -> Result<ConstraintId, ViewerError> {
        let id = self.session.next_id(self.next_constraint);
        let constraint = Constraint {
            id,
            polarity,
            frustum,
            objects: self.chosen_objects(),
            quantifier: Default::default(),
            window: self.window,
            scope: Default::default(),
        };
        constraint.validate()?;
        match &mut self.session {
            Session::Local(set) => {
                let worlds = &self.worlds;
                set.add(constraint, |c, w| evaluate(worlds, c, w))?;
                self.rerank_local();
            }
            Session::Remote(r) => {
                r.drawn.insert(id, constraint.clone());
                self.send_edit(Request::Add {
                    constraint: Box::new(constraint),
                });
            }
        }
        self.next_constraint = id.0 + 1;
        Ok(id)
    }

    fn send_edit(&mut self, request: Request) {
        if let Session::Remote(r) = &mut self.session {
            r.sent += 1;
            r.pending += 1;
        }
        self.outbox.push(Command::Browse(request));
    }

    fn on_session(&mut self, status: SessionStatus, survivors: Vec<u32>, handled: u32) {
        let Session::Remote(r) = &mut self.session else {
            return;
        };
        let changed = !r.answered
            || r.status.edits != status.edits
            || r.status.worlds != status.worlds
            || r.status.result != status.result;
        let mut set = WorldSet::new();
        for w in survivors {
            set.insert(w);
        }
        r.survivors = set;
        r.pending = r.sent.saturating_sub(handled);
        r.status = status;
        r.answered = true;
        self.browse_error = None;
        if changed {
            self.rerank();
        }
    }

    fn on_ranked(&mut self, spec: RankSpec, reply: Reply) {
        if self.rank_spec.as_ref() != Some(&spec) {
            return; // an answer to a ranking the user has since changed
        }
        match reply {
            Reply::Ranking {
                candidates,
                unscored,
                rows,
            } => {
                self.ranking = Some(Ranking {
                    spec,
                    candidates,
                    unscored,
                    rows,
                });
            }
            Reply::Error { message } => self.browse_error = Some(message),
            other => self.browse_error = Some(format!("unexpected answer to a ranking: {other:?}")),
        }
    }

    fn on_motion(&mut self, world: u32, motion: Result<Arc<Motion>, String>) {
        self.fetching.retain(|&w| w != world);
        match motion {
            Ok(m) => {
                if let Ok(i) = self.worlds.binary_search_by_key(&world, |d| d.index) {
                    self.worlds[i].motion = Some(m);
                    self.loaded.push_back(world);
                }
                // Keep the cache bounded; never drop the world being shown.
                let shown = self.shown_world().map(|w| w.index);
                while self.loaded.len() > MOTION_CACHE {
                    let Some(old) = self.loaded.pop_front() else {
                        break;
                    };
                    if Some(old) == shown {
                        self.loaded.push_back(old);
                        continue;
                    }
                    if let Ok(i) = self.worlds.binary_search_by_key(&old, |d| d.index) {
                        self.worlds[i].motion = None;
                    }
                }
            }
            Err(e) => self.problems.push(format!("world {world}: {e}")),
        }
    }

    /// Picks world `w` (or none). Live, a world whose paths the viewer does not hold (it holds
    /// a sample of a large store) is asked for, and picked when it arrives.
    fn select(&mut self, w: Option<u32>) {
        self.wanted_selection = None;
        if let Some(w) = w.filter(|&w| self.is_live() && self.world(w).is_none()) {
            self.wanted_selection = Some(w);
            self.outbox.push(Command::FetchPaths(vec![w]));
        }
        self.selected = w.filter(|&w| self.world(w).is_some());
        self.playback.time = self.playback.time.clamp(0.0, self.duration());
    }

    /// Live: asks for the shown world's motion when it is not loaded or on its way.
    fn want_shown_motion(&mut self) {
        if !self.is_live() {
            return;
        }
        let Some(w) = self.shown_world() else {
            return;
        };
        if w.motion.is_some() || self.fetching.contains(&w.index) {
            return;
        }
        let cmd = Command::FetchMotion {
            world: w.index,
            job: w.job.clone(),
        };
        self.fetching.push(w.index);
        self.outbox.push(cmd);
    }

    /// Refreshes the ranking: computed here offline, asked of node-query live.
    fn rerank(&mut self) {
        let Some(spec) = self.rank_spec.clone() else {
            return;
        };
        match &self.session {
            Session::Local(_) => self.rerank_local(),
            Session::Remote(_) => self.outbox.push(Command::Rank(spec)),
        }
    }

    /// Offline ranking over the worlds' metrics, with the function a store shard uses.
    fn rerank_local(&mut self) {
        let (Some(spec), Session::Local(set)) = (&self.rank_spec, &self.session) else {
            return;
        };
        let candidates: Vec<u32> = if spec.all_worlds {
            self.worlds.iter().map(|w| w.index).collect()
        } else {
            set.result().iter().collect()
        };
        let n = candidates.len() as u64;
        let (rows, unscored) = top_k_counted(candidates, spec.k, spec.order, |w| {
            let world = find(&self.worlds, w)?;
            spec.key.score(&world.metrics, set.satisfied_count(w))
        });
        self.ranking = Some(Ranking {
            spec: spec.clone(),
            candidates: n,
            unscored,
            rows,
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mwb_codec::Track;
    use mwb_core::browse::api::ConstraintStatus;
    use mwb_core::browse::{Aggregate, Metric, ObjectMetrics};
    use mwb_core::scene::SceneTemplate;

    fn scene() -> mwb_core::scene::Scene {
        SceneTemplate::parse(
            "name = \"t\"\n[[material]]\nname = \"m\"\n[[body]]\nname = \"ball\"\nshape = \"sphere\"\nradius = 0.1\nmaterial = \"m\"\nposition = [0, 1, 0]\n",
            "t.toml",
        )
        .expect("scene parses")
        .instantiate(0)
    }

    /// World `i` of a one-body scene whose body flies along x at height `y`.
    fn world(i: u32, y: f64) -> WorldData {
        world_along(i, |f| [-3.0 + 0.1 * f, y, 0.0])
    }

    fn state(heights: &[f64]) -> ViewerState {
        let sc = scene();
        let names = sc.bodies.iter().map(|b| b.name.clone()).collect();
        let mut s = ViewerState::new("t", names, sc.statics.clone());
        for (i, &y) in heights.iter().enumerate() {
            s.add_world(world(i as u32, y)).expect("adds");
        }
        s
    }

    /// A camera at z = 10 looking at the origin, 640 × 480.
    fn front(s: &mut ViewerState) -> Viewport {
        s.update(Msg::SetCamera(OrbitCamera {
            target: [0.0, 0.0, 0.0],
            yaw: 0.0,
            pitch: 0.0,
            distance: 10.0,
            ..OrbitCamera::default()
        }))
        .expect("camera");
        Viewport {
            width: 640,
            height: 480,
        }
    }

    const MIDDLE: ScreenRect = ScreenRect {
        x0: 300.0,
        y0: 220.0,
        x1: 340.0,
        y1: 260.0,
    };

    fn survivors(s: &ViewerState) -> Vec<u32> {
        s.survivors().collect()
    }

    /// The path meshes kept between frames are exactly what a fresh frame draws, through a box,
    /// its undo, a world arriving, a camera move and a change of objects; a frame in which
    /// nothing changed reuses them.
    #[test]
    fn kept_path_meshes_are_what_a_fresh_frame_draws() {
        use crate::draw::{Overlay, PathMeshes, View, scene_shapes};
        let mut s = state(&[0.0, 2.0, 0.05, -1.0]);
        let viewport = front(&mut s);
        let rect = egui::Rect::from_min_size(egui::Pos2::ZERO, egui::vec2(640.0, 480.0));
        let meshes = |shapes: &[egui::Shape]| -> Vec<std::sync::Arc<egui::epaint::Mesh>> {
            shapes
                .iter()
                .filter_map(|sh| match sh {
                    egui::Shape::Mesh(m) => Some(m.clone()),
                    _ => None,
                })
                .collect()
        };
        let mut kept = PathMeshes::default();
        let frame = |s: &ViewerState, kept: &mut PathMeshes| {
            let view = View::new(&s.camera, rect, 1.0).expect("view");
            let cached = scene_shapes(s, &view, Overlay::default(), kept);
            let fresh = scene_shapes(s, &view, Overlay::default(), &mut PathMeshes::default());
            let (c, f) = (meshes(&cached), meshes(&fresh));
            assert_eq!(c.len(), f.len());
            for (c, f) in c.iter().zip(&f) {
                assert_eq!(**c, **f);
            }
            c
        };
        let first = frame(&s, &mut kept);
        // Nothing changed: the same meshes, not copies.
        let again = frame(&s, &mut kept);
        assert!(
            first
                .iter()
                .zip(&again)
                .filter(|(a, b)| std::sync::Arc::ptr_eq(a, b))
                .count()
                >= 1
        );
        drop((first, again));
        s.update(Msg::AddConstraint {
            viewport,
            rect: MIDDLE,
            polarity: Polarity::Positive,
        })
        .expect("adds");
        frame(&s, &mut kept);
        s.update(Msg::Undo).expect("undo");
        frame(&s, &mut kept);
        s.add_world(world(4, 0.5)).expect("adds");
        frame(&s, &mut kept);
        s.update(Msg::Orbit {
            d_yaw: 0.3,
            d_pitch: 0.1,
        })
        .expect("orbit");
        frame(&s, &mut kept);
        s.update(Msg::ChooseObjects(Vec::new())).expect("none");
        frame(&s, &mut kept);
    }

    #[test]
    fn a_box_keeps_the_worlds_that_pass_through_it_and_undo_redo_remove_work() {
        let mut s = state(&[0.0, 2.0, 0.05]);
        let viewport = front(&mut s);
        // A box around the screen centre: heights 0 and 0.05 pass through, 2 does not.
        let rect = MIDDLE;
        s.update(Msg::AddConstraint {
            viewport,
            rect,
            polarity: Polarity::Positive,
        })
        .expect("adds");
        assert_eq!(survivors(&s), vec![0, 2]);
        let c = s.constraint_list().remove(0);
        assert_eq!(
            c.frustum,
            s.camera
                .browse_camera(viewport)
                .frustum(&rect)
                .expect("frustum")
        );
        assert_eq!(c.objects, vec![0]);
        // A negative box over the same place keeps none of them.
        s.update(Msg::AddConstraint {
            viewport,
            rect,
            polarity: Polarity::Negative,
        })
        .expect("adds");
        assert_eq!(s.survivor_count(), 0);
        s.update(Msg::Undo).expect("undo");
        assert_eq!(s.survivor_count(), 2);
        s.update(Msg::Redo).expect("redo");
        assert_eq!(s.survivor_count(), 0);
        s.update(Msg::RemoveConstraint(ConstraintId(1)))
            .expect("removes");
        // Only the negative one is left: world 1 (y = 2) never enters the box.
        assert_eq!(survivors(&s), vec![1]);
        assert!(s.update(Msg::RemoveConstraint(ConstraintId(9))).is_err());
        // A degenerate rectangle is refused and changes nothing.
        let before = s.survivor_count();
        let flat = ScreenRect { y1: 220.0, ..rect };
        assert!(
            s.update(Msg::AddConstraint {
                viewport,
                rect: flat,
                polarity: Polarity::Positive
            })
            .is_err()
        );
        assert_eq!(s.survivor_count(), before);
        assert_eq!(s.constraint_rows().len(), 1);
        assert!(s.take_commands().is_empty(), "offline sends nothing");
    }

    #[test]
    fn worlds_arriving_later_are_filtered_and_unchosen_objects_are_left_out() {
        let mut s = state(&[0.0]);
        let viewport = front(&mut s);
        s.update(Msg::ToggleObject(0)).expect("toggle");
        assert!(s.chosen_objects().is_empty());
        s.update(Msg::ChooseObjects(vec![3, 0])).expect("choose");
        assert_eq!(s.chosen_objects(), vec![0], "object 3 does not exist");
        s.update(Msg::ChooseObjects(Vec::new())).expect("choose");
        assert!(s.chosen_objects().is_empty());
        s.update(Msg::ToggleObject(0)).expect("toggle");
        s.update(Msg::AddConstraint {
            viewport,
            rect: MIDDLE,
            polarity: Polarity::Positive,
        })
        .expect("adds");
        assert_eq!(s.survivor_count(), 1);
        // Indices need not be dense (a sharded store numbers 0, 2, 4, … on one shard).
        s.add_world(world(7, 3.0)).expect("adds");
        s.add_world(world(5, 0.0)).expect("adds");
        assert_eq!(
            s.worlds().iter().map(|w| w.index).collect::<Vec<_>>(),
            vec![0, 5, 7]
        );
        assert_eq!(survivors(&s), vec![0, 5]);
        assert!(s.add_world(world(7, 0.0)).is_err(), "index 7 is taken");
    }

    #[test]
    fn playback_clock() {
        let mut s = state(&[0.0, 1.0]);
        assert_eq!(s.duration(), 1.0);
        s.update(Msg::SelectWorld(Some(1))).expect("select");
        assert_eq!(s.shown_world().map(|w| w.index), Some(1));
        s.update(Msg::Tick(0.5)).expect("tick");
        assert_eq!(s.playback().time, 0.0, "paused clocks do not move");
        s.update(Msg::Play).expect("play");
        s.update(Msg::SetSpeed(2.0)).expect("speed");
        s.update(Msg::Tick(0.25)).expect("tick");
        assert_eq!(s.playback().time, 0.5);
        s.update(Msg::Tick(0.5)).expect("tick");
        assert!((s.playback().time - 0.5).abs() < 1e-12, "loops");
        s.update(Msg::SetLoop(false)).expect("loop");
        s.update(Msg::Tick(1.0)).expect("tick");
        assert_eq!(s.playback().time, 1.0);
        assert!(!s.playback().playing, "stops at the end");
        s.update(Msg::Seek(0.5)).expect("seek");
        s.update(Msg::Step(1)).expect("step");
        assert!((s.playback().time - 0.5 - 1.0 / 60.0).abs() < 1e-12);
        s.update(Msg::SetSpeed(100.0)).expect("speed");
        assert_eq!(s.playback().speed, MAX_SPEED);
        s.update(Msg::Seek(-4.0)).expect("seek");
        assert_eq!(s.playback().time, 0.0);
        let (p, _) = s
            .shown_world()
            .and_then(|w| w.pose_at(0, 0.5))
            .expect("pose");
        assert!((p[0] - 0.0).abs() < 1e-9 && (p[1] - 1.0).abs() < 1e-9);
    }

    #[test]
    fn views_are_saved_and_recalled_and_f_frames_the_selected_world() {
        let mut s = state(&[0.0, 0.0, 4.0]);
        let home = s.camera;
        assert_eq!(s.next_view_name(), "view 1");
        s.update(Msg::SaveView("home".into())).expect("save");
        s.update(Msg::Orbit {
            d_yaw: 1.0,
            d_pitch: 0.2,
        })
        .expect("orbit");
        assert_ne!(s.camera, home);
        s.update(Msg::RecallView(0)).expect("recall");
        assert_eq!(s.camera, home);
        assert_eq!(s.views().len(), 1);
        s.update(Msg::RecallView(5))
            .expect("an unknown view changes nothing");
        assert_eq!(s.views_edits(), 1, "recalling is not an edit");
        s.update(Msg::DeleteView(3))
            .expect("an unknown view changes nothing");
        s.update(Msg::DeleteView(0)).expect("delete");
        assert!(s.views().is_empty());
        assert_eq!(s.views_edits(), 2);
        // Views read at start replace the list and are not edits (nothing to write back).
        let kept = vec![
            SavedView {
                name: "view 1".into(),
                camera: home,
            },
            SavedView {
                name: "view 3".into(),
                camera: home,
            },
        ];
        s.update(Msg::LoadViews(kept.clone())).expect("load");
        assert_eq!((s.views(), s.views_edits()), (&kept[..], 2));
        assert_eq!(s.next_view_name(), "view 2", "the first free name");
        s.update(Msg::DeleteView(0)).expect("delete");
        s.update(Msg::DeleteView(0)).expect("delete");
        // World 2 flies at y = 4: framing it targets y = 4; framing all, what all hold.
        s.update(Msg::SelectWorld(Some(2))).expect("select");
        s.update(Msg::FrameSelected { aspect: 1.5 }).expect("frame");
        assert!(
            (s.camera.target[1] - 4.0).abs() < 1e-9,
            "{:?}",
            s.camera.target
        );
        s.update(Msg::FrameAll { aspect: 1.5 }).expect("frame");
        let (c, r) = s.framing(None).expect("framed");
        assert_eq!(s.camera.target, c);
        for start in [[-3.0, 0.0, 0.0], [-3.0, 4.0, 0.0]] {
            assert!(crate::math::len(crate::math::sub(start, c)) <= r + 1e-9);
        }
    }

    /// World `i` of the one-body scene whose body goes through `at(frame)`, frames 0..=60.
    fn world_along(i: u32, at: impl Fn(f64) -> V3) -> WorldData {
        let positions: Vec<V3> = (0..61).map(|f| at(f as f64)).collect();
        let track = Track {
            rotations: vec![[0.0, 0.0, 0.0, 1.0]; positions.len()],
            positions,
        };
        let motion = Motion {
            scene: scene(),
            frame_dt: 1.0 / 60.0,
            tracks: vec![track],
        };
        WorldData::from_exact_motion(i, u64::from(i), motion).expect("indexes")
    }

    #[test]
    fn framing_all_holds_the_bulk_of_the_paths_every_start_and_the_statics() {
        let wall = StaticBody {
            name: "backstop".into(),
            shape: mwb_core::scene::Shape::Box {
                half_extents: [0.15, 0.5, 2.5],
            },
            material: 0,
            position: [6.0, 0.5, 0.0],
            rotation: [0.0, 0.0, 0.0, 1.0],
        };
        let floor = StaticBody {
            name: "floor".into(),
            shape: mwb_core::scene::Shape::Box {
                half_extents: [100.0, 0.1, 100.0],
            },
            position: [0.0, -0.1, 0.0],
            ..wall.clone()
        };
        let mut s = ViewerState::new("t", vec!["ball".into()], vec![wall.clone(), floor]);
        // 199 worlds roll along x at y = 0; one is thrown 60 m up from the same start.
        for i in 0..199 {
            s.add_world(world_along(i, |f| [-3.0 + 0.1 * f, 0.0, 0.0]))
                .expect("adds");
        }
        s.add_world(world_along(199, |f| [-3.0, f, 0.0]))
            .expect("adds");
        // A projectile: one world starts far to the left (few vertices, but it is the scene).
        s.add_world(world_along(200, |f| [-9.0 + 0.1 * f, 0.0, 0.0]))
            .expect("adds");
        let (c, r) = s.framing(None).expect("framed");
        let inside = |p: V3| crate::math::len(crate::math::sub(p, c)) <= r + 1e-9;
        // The thrown world does not pull the view up; the projectile's start and the whole
        // backstop are in; the floor box, far larger than the paths, is left out.
        assert!(c[1].abs() < 0.6, "centre {c:?}");
        assert!(inside([-9.0, 0.0, 0.0]), "{c:?} {r}");
        for x in [5.85, 6.15] {
            for y in [0.0, 1.0] {
                for z in [-2.5, 2.5] {
                    assert!(inside([x, y, z]), "backstop corner {:?}", [x, y, z]);
                }
            }
        }
        assert!(r < 10.0, "radius {r}");
        assert!(!inside([0.0, 60.0, 0.0]));
    }

    fn metrics(spin: f64) -> Vec<ObjectMetrics> {
        vec![ObjectMetrics {
            angular_travel_rad: spin,
            time_to_rest_s: 1.0,
            came_to_rest: true,
            impacts: 0,
            orientation_error_rad: 0.0,
            final_rotation: [0.0, 0.0, 0.0, 1.0],
        }]
    }

    #[test]
    fn offline_rankings_follow_the_survivors() {
        let mut s = ViewerState::new("t", vec!["ball".into()], Vec::new());
        for (i, (y, spin)) in [(0.0, 1.0), (2.0, 9.0), (0.0, 5.0)].into_iter().enumerate() {
            let mut w = world(i as u32, y);
            w.metrics = metrics(spin);
            s.add_world(w).expect("adds");
        }
        let spec = RankSpec {
            key: RankKey::Metric {
                metric: Metric::AngularTravel,
                objects: vec![0],
                aggregate: Aggregate::Sum,
            },
            order: Order::Descending,
            k: 10,
            all_worlds: false,
        };
        s.update(Msg::Rank(Some(spec.clone()))).expect("rank");
        let order = |s: &ViewerState| {
            s.ranking()
                .expect("ranked")
                .rows
                .iter()
                .map(|r| r.world)
                .collect::<Vec<_>>()
        };
        assert_eq!(order(&s), vec![1, 2, 0], "most spin first");
        let viewport = front(&mut s);
        s.update(Msg::AddConstraint {
            viewport,
            rect: MIDDLE,
            polarity: Polarity::Positive,
        })
        .expect("adds");
        assert_eq!(order(&s), vec![2, 0], "only survivors rank");
        s.update(Msg::Rank(Some(RankSpec {
            all_worlds: true,
            ..spec
        })))
        .expect("rank");
        assert_eq!(order(&s), vec![1, 2, 0]);
        s.update(Msg::Undo).expect("undo");
        s.update(Msg::Rank(None)).expect("clear");
        assert!(s.ranking().is_none());
    }

    /// World `i` of the one-body scene whose body turns about +y by `turn` radians over its
    /// second (evenly, 61 frames), with its metrics as a store computes them.
    fn turning_world(i: u32, turn: f64) -> WorldData {
        let rotations: Vec<[f64; 4]> = (0..61)
            .map(|f| {
                let half = 0.5 * turn * f as f64 / 60.0;
                [0.0, half.sin(), 0.0, half.cos()]
            })
            .collect();
        let track = Track {
            positions: vec![[0.0, 0.0, 0.0]; rotations.len()],
            rotations,
        };
        let metrics = ObjectMetrics::compute(
            &mwb_core::browse::Track {
                frame_dt: 1.0 / 60.0,
                positions: &track.positions,
                rotations: &track.rotations,
            },
            0,
            mwb_core::browse::RestThresholds {
                linear: 0.01,
                angular: 0.01,
            },
            None,
        )
        .expect("metrics");
        let motion = Motion {
            scene: scene(),
            frame_dt: 1.0 / 60.0,
            tracks: vec![track],
        };
        let mut w = WorldData::from_exact_motion(i, u64::from(i), motion).expect("indexes");
        w.metrics = vec![metrics];
        w
    }

    #[test]
    fn a_goal_picked_in_playback_ranks_the_worlds_by_their_error_to_it() {
        let mut s = ViewerState::new("t", vec!["ball".into()], Vec::new());
        for (i, turn) in [0.0, 1.0, 2.0, 3.0].into_iter().enumerate() {
            s.add_world(turning_world(i as u32, turn)).expect("adds");
        }
        // Nothing chosen: no object to take the goal from.
        s.update(Msg::ToggleObject(0)).expect("toggle");
        assert!(matches!(
            s.update(Msg::GoalFromPlayback),
            Err(ViewerError::Goal(_))
        ));
        s.update(Msg::ToggleObject(0)).expect("toggle");
        // World 2 at 0.5 s: frame 30, turned by 1 rad, exactly the decoded frame's quaternion.
        s.update(Msg::SelectWorld(Some(2))).expect("select");
        s.update(Msg::Seek(0.5 + 0.3 / 60.0)).expect("seek");
        s.update(Msg::GoalFromPlayback).expect("goal");
        let goal = *s.goal().expect("a goal");
        let decoded = s
            .world(2)
            .and_then(|w| w.motion.clone())
            .expect("motion")
            .tracks[0]
            .rotations[30];
        assert_eq!((goal.world, goal.object, goal.frame), (2, 0, 30));
        assert_eq!(goal.rotation, decoded);
        assert!((goal.time - 0.5).abs() < 1e-12);
        // Closest to the goal first: world 1 ends turned by 1 rad (error 0), then worlds 0 and
        // 2 (1 rad either way; the lower index first), then world 3 (2 rad).
        let spec = RankSpec {
            key: RankKey::OrientationTo {
                goal: goal.rotation,
                objects: vec![0],
                aggregate: Aggregate::Sum,
            },
            order: Order::Ascending,
            k: 10,
            all_worlds: false,
        };
        s.update(Msg::Rank(Some(spec))).expect("rank");
        let rows = |s: &ViewerState| -> Vec<(u32, f64)> {
            s.ranking()
                .expect("ranked")
                .rows
                .iter()
                .map(|r| (r.world, r.score.expect("scored")))
                .collect()
        };
        let want = [(1, 0.0), (0, 1.0), (2, 1.0), (3, 2.0)];
        for ((w, v), (ww, wv)) in rows(&s).into_iter().zip(want) {
            assert_eq!(w, ww);
            assert!((v - wv).abs() < 1e-6, "world {w}: {v} vs {wv}");
        }
        // A new goal (world 3's last frame, turned 3 rad) re-ranks at once.
        s.update(Msg::SelectWorld(Some(3))).expect("select");
        s.update(Msg::Seek(1.0)).expect("seek");
        s.update(Msg::GoalFromPlayback).expect("goal");
        assert_eq!(s.goal().map(|g| (g.world, g.frame)), Some((3, 60)));
        assert_eq!(
            rows(&s).iter().map(|r| r.0).collect::<Vec<_>>(),
            vec![3, 2, 1, 0]
        );
        assert!(rows(&s)[0].1 < 1e-6);
        // Clearing the goal ends a ranking by it.
        s.update(Msg::ClearGoal).expect("clear");
        assert!(s.goal().is_none() && s.rank_spec().is_none() && s.ranking().is_none());
    }

    #[test]
    fn a_live_goal_needs_the_motion_and_its_ranking_is_asked_of_node_query() {
        let mut s = live_ball();
        let mut w = turning_world(0, 1.0);
        let motion = w.motion.take().expect("motion");
        s.update(Msg::Worlds(vec![w])).expect("worlds");
        s.update(Msg::SelectWorld(Some(0))).expect("select");
        let e = s.update(Msg::GoalFromPlayback).expect_err("not loaded yet");
        assert!(e.to_string().contains("not loaded yet"), "{e}");
        s.update(Msg::MotionLoaded {
            world: 0,
            motion: Ok(motion),
        })
        .expect("loaded");
        let spec = RankSpec {
            key: RankKey::OrientationTo {
                goal: [0.0, 0.0, 0.0, 1.0],
                objects: vec![0],
                aggregate: Aggregate::Sum,
            },
            order: Order::Ascending,
            k: 5,
            all_worlds: false,
        };
        s.update(Msg::Rank(Some(spec))).expect("rank");
        s.take_commands();
        s.update(Msg::Seek(1.0)).expect("seek");
        s.update(Msg::GoalFromPlayback).expect("goal");
        let goal = s.goal().expect("goal").rotation;
        let cmds = s.take_commands();
        let [
            Command::Rank(RankSpec {
                key: RankKey::OrientationTo { goal: sent, .. },
                ..
            }),
        ] = cmds.as_slice()
        else {
            panic!("expected one ranking request, got {cmds:?}");
        };
        assert_eq!(*sent, goal);
        assert!((goal[1] - 0.5f64.sin()).abs() < 1e-12);
    }

    #[test]
    fn a_refine_box_asks_the_bus_task_to_refine_the_shown_world_through_the_camera() {
        let viewport = Viewport {
            width: 640,
            height: 480,
        };
        let rect = ScreenRect {
            x0: 100.0,
            y0: 100.0,
            x1: 300.0,
            y1: 260.0,
        };
        let refine = || Msg::Refine {
            viewport,
            rect,
            worlds: 8,
        };
        let mut offline = state(&[0.5]);
        let e = offline.update(refine()).expect_err("offline");
        assert!(e.to_string().contains("needs a live viewer"), "{e}");

        let mut s = live_ball();
        s.update(Msg::Worlds(vec![world(4, 0.5)])).expect("worlds");
        let e = s.update(refine()).expect_err("nothing shown");
        assert!(e.to_string().contains("pick the world"), "{e}");
        s.update(Msg::SelectWorld(Some(4))).expect("select");
        s.take_commands();
        s.update(refine()).expect("refine");
        let want = s
            .camera
            .browse_camera(viewport)
            .frustum(&rect)
            .expect("frustum");
        let cmds = s.take_commands();
        let [
            Command::Refine {
                world: 4,
                objects,
                frustum,
                worlds: 8,
            },
        ] = cmds.as_slice()
        else {
            panic!("expected one refinement, got {cmds:?}");
        };
        assert_eq!(objects, &s.chosen_objects());
        assert_eq!(**frustum, want);
    }

    /// A live state of the one-ball scene, before any world arrives.
    fn live_ball() -> ViewerState {
        let mut s = ViewerState::live("tcp/127.0.0.1:7447");
        s.update(Msg::Scene {
            name: "t".into(),
            bodies: vec!["ball".into()],
            statics: Vec::new(),
            initial: scene().bodies,
        })
        .expect("scene");
        s
    }

    fn status(worlds: u64, result: u64, edits: u64, ids: &[u64]) -> SessionStatus {
        SessionStatus {
            worlds,
            result,
            constraints: ids
                .iter()
                .map(|&id| ConstraintStatus {
                    id: ConstraintId(id),
                    polarity: Polarity::Positive,
                    objects: vec![0],
                    quantifier: Default::default(),
                    window: None,
                    scope: Default::default(),
                    satisfied: result,
                })
                .collect(),
            can_undo: edits > 0,
            can_redo: false,
            edits,
        }
    }

    #[test]
    fn a_live_box_becomes_a_request_and_the_answer_is_what_counts() {
        let mut s = live_ball();
        s.update(Msg::Worlds(vec![world(0, 0.0), world(2, 2.0)]))
            .expect("worlds");
        let viewport = front(&mut s);
        s.update(Msg::AddConstraint {
            viewport,
            rect: MIDDLE,
            polarity: Polarity::Positive,
        })
        .expect("adds");
        // Nothing is evaluated here: the request carries the frustum of this camera and box.
        assert_eq!(s.survivor_count(), 0);
        assert_eq!(s.pending(), 1);
        let cmds = s.take_commands();
        let [Command::Browse(Request::Add { constraint })] = cmds.as_slice() else {
            panic!("expected one Add, got {cmds:?}");
        };
        assert_eq!(
            constraint.frustum,
            s.camera
                .browse_camera(viewport)
                .frustum(&MIDDLE)
                .expect("frustum")
        );
        assert_eq!(constraint.objects, vec![0]);
        // node-query answers: 5 worlds in the store, 3 survive, the edit is handled.
        s.update(Msg::Session {
            status: status(5, 3, 1, &[constraint.id.0]),
            survivors: vec![0, 3, 4],
            handled_edits: 1,
        })
        .expect("answer");
        assert_eq!(s.pending(), 0);
        assert_eq!((s.survivor_count(), s.world_total()), (3, 5));
        assert!(s.survives(0) && !s.survives(2));
        let rows = s.constraint_rows();
        assert_eq!(rows.len(), 1);
        assert_eq!(rows[0].satisfied, 3);
        assert_eq!(rows[0].frustum.as_ref(), Some(&constraint.frustum));
        // Undo and remove become requests too; an unknown id is refused here.
        s.update(Msg::Undo).expect("undo");
        s.update(Msg::RemoveConstraint(constraint.id))
            .expect("remove");
        assert!(s.update(Msg::RemoveConstraint(ConstraintId(99))).is_err());
        assert_eq!(
            s.take_commands(),
            vec![
                Command::Browse(Request::Undo),
                Command::Browse(Request::Remove { id: constraint.id })
            ]
        );
        assert_eq!(s.pending(), 2);
    }

    #[test]
    fn a_live_viewer_fetches_the_shown_world_and_keeps_a_bounded_cache() {
        let mut s = ViewerState::live("tcp/127.0.0.1:7447");
        let mut arriving: Vec<WorldData> = (0..(MOTION_CACHE as u32 + 3))
            .map(|i| world(i, 0.0))
            .collect();
        let motions: Vec<Arc<Motion>> = arriving
            .iter_mut()
            .map(|w| w.motion.take().expect("exact worlds have motion"))
            .collect();
        s.update(Msg::Worlds(arriving)).expect("worlds");
        s.update(Msg::SelectWorld(Some(4))).expect("select");
        assert_eq!(
            s.take_commands(),
            vec![Command::FetchMotion {
                world: 4,
                job: String::new(),
            }]
        );
        assert!(s.shown_loading());
        s.update(Msg::SelectWorld(Some(4))).expect("select");
        assert!(s.take_commands().is_empty(), "asked once");
        for (i, m) in motions.iter().enumerate() {
            s.update(Msg::MotionLoaded {
                world: i as u32,
                motion: Ok(m.clone()),
            })
            .expect("loaded");
        }
        let loaded = s.worlds().iter().filter(|w| w.motion.is_some()).count();
        assert_eq!(loaded, MOTION_CACHE);
        assert!(s.world(4).is_some_and(|w| w.motion.is_some()), "shown kept");
        s.update(Msg::MotionLoaded {
            world: 1,
            motion: Err("CRC mismatch".into()),
        })
        .expect("error");
        assert!(s.problems().iter().any(|p| p.contains("CRC")));
    }

    #[test]
    fn a_live_viewer_lets_sampled_worlds_go_but_keeps_what_it_shows() {
        let mut s = ViewerState::live("tcp/127.0.0.1:7447");
        let mut arriving: Vec<WorldData> = (0..6).map(|i| world(i, 0.0)).collect();
        for w in &mut arriving {
            w.motion = None;
        }
        s.update(Msg::Worlds(arriving.clone())).expect("worlds");
        // World 2 is picked (its motion on its way), world 5's motion is loaded.
        s.update(Msg::SelectWorld(Some(2))).expect("select");
        s.take_commands();
        let motion = world(5, 0.0).motion.expect("exact worlds have motion");
        s.update(Msg::MotionLoaded {
            world: 5,
            motion: Ok(motion),
        })
        .expect("loaded");
        // The bus task lets 1, 2, 4 and 5 go: the picked world and the one with motion stay.
        s.update(Msg::Evict(vec![1, 2, 4, 5])).expect("evict");
        let held: Vec<u32> = s.worlds().iter().map(|w| w.index).collect();
        assert_eq!(held, vec![0, 2, 3, 5]);
        // A world sent again while still held is no problem (the bus task forgot it was kept).
        s.update(Msg::Worlds(vec![arriving[2].clone()]))
            .expect("again");
        assert!(s.problems().is_empty(), "{:?}", s.problems());
        assert_eq!(s.worlds().len(), 4);
    }

    #[test]
    fn picking_a_world_the_live_viewer_does_not_hold_fetches_its_paths_first() {
        let mut s = ViewerState::live("tcp/127.0.0.1:7447");
        let mut w7 = world(7, 0.0);
        w7.motion = None;
        s.update(Msg::SelectWorld(Some(7))).expect("select");
        assert_eq!(s.selected(), None, "not held yet");
        assert_eq!(s.take_commands(), vec![Command::FetchPaths(vec![7])]);
        s.update(Msg::Worlds(vec![w7])).expect("arrives");
        assert_eq!(s.selected(), Some(7), "picked when it arrives");
        // Picking it asked for its motion, as picking a held world does.
        assert_eq!(
            s.take_commands(),
            vec![Command::FetchMotion {
                world: 7,
                job: String::new(),
            }]
        );
        // Picking another world meanwhile wins over a pick still waiting.
        s.update(Msg::SelectWorld(Some(9))).expect("select");
        s.update(Msg::SelectWorld(None)).expect("none");
        let mut w9 = world(9, 0.0);
        w9.motion = None;
        s.update(Msg::Worlds(vec![w9])).expect("arrives");
        assert_eq!(s.selected(), None);
    }
}
