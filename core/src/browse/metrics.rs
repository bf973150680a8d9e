//! §4.4.3 ranking metrics: computed once per object at ingest from the full-rate track, combined
//! over a chosen subset of objects at query time, and used to order the surviving worlds.
//!
//! When the constraints leave more worlds than a user can look through (the reference says more
//! than about a hundred), metrics order them: how much the objects spin (integrated angular
//! speed), how long they take to come to rest (frame budgets), how often they collide, and how
//! far their final orientation is from a goal (the starting one by default, which §4.4.3 found
//! sufficient). Per-object values are precomputed; a ranking only sums or maxes them.

use serde::{Deserialize, Serialize};

use super::geom::{Quat, Vec3, norm, quat_angle_between, quat_normalize, sub};
use super::{BrowseError, finite};
use crate::scene::Settings;

/// Speeds below which a body counts as at rest.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RestThresholds {
    /// m/s.
    pub linear: f64,
    /// rad/s.
    pub angular: f64,
}

impl From<&Settings> for RestThresholds {
    /// The scene's own rest thresholds (the ones the sampler ends a world with).
    fn from(s: &Settings) -> Self {
        Self {
            linear: s.rest_linear,
            angular: s.rest_angular,
        }
    }
}

/// One object's full-rate motion: a pose every `frame_dt` seconds from t = 0.
#[derive(Debug, Clone, Copy)]
pub struct Track<'a> {
    pub frame_dt: f64,
    pub positions: &'a [Vec3],
    /// Unit quaternions `[x, y, z, w]` (normalised on use).
    pub rotations: &'a [Quat],
}

/// Per-object metrics of one world.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ObjectMetrics {
    /// ∫‖ω‖ dt over the track, radians: the sum of the rotation angles between frames.
    pub angular_travel_rad: f64,
    /// The first time after which the object stays below the rest thresholds, seconds; the
    /// track's end if it never settles (then `came_to_rest` is false).
    pub time_to_rest_s: f64,
    pub came_to_rest: bool,
    /// Impacts, counted by the caller with the §4.1.2 thresholds.
    pub impacts: u32,
    /// Angle between the final orientation and the goal, radians in [0, π].
    pub orientation_error_rad: f64,
    /// The final orientation (unit quaternion `[x, y, z, w]`), kept so that a ranking can
    /// measure the error against a goal chosen at query time ([`RankKey::OrientationTo`]).
    #[serde(default = "identity")]
    pub final_rotation: Quat,
}

fn identity() -> Quat {
    [0.0, 0.0, 0.0, 1.0]
}

/// [`ObjectMetrics`] as a store keeps it: every value in f32, 36 bytes against 64 (a million
/// 10-object worlds: 280 MB less). f32 keeps 24 bits: a rest time of 10 s to 1 µs, an angle to
/// 1e-7 of itself, far below any difference a ranking can show an animator. Rankings read it in
/// place through [`MetricValues`], as the unpacked f64 values ([`PackedMetrics::unpack`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PackedMetrics {
    angular_travel_rad: f32,
    time_to_rest_s: f32,
    orientation_error_rad: f32,
    impacts: u32,
    final_rotation: [f32; 4],
    came_to_rest: bool,
}

impl PackedMetrics {
    /// The values, each rounded to the nearest f32.
    pub fn pack(m: &ObjectMetrics) -> Self {
        Self {
            angular_travel_rad: m.angular_travel_rad as f32,
            time_to_rest_s: m.time_to_rest_s as f32,
            orientation_error_rad: m.orientation_error_rad as f32,
            impacts: m.impacts,
            final_rotation: m.final_rotation.map(|v| v as f32),
            came_to_rest: m.came_to_rest,
        }
    }

    /// The metrics back, in f64 (each the f32 it was rounded to).
    #[inline]
    pub fn unpack(&self) -> ObjectMetrics {
        ObjectMetrics {
            angular_travel_rad: f64::from(self.angular_travel_rad),
            time_to_rest_s: f64::from(self.time_to_rest_s),
            came_to_rest: self.came_to_rest,
            impacts: self.impacts,
            orientation_error_rad: f64::from(self.orientation_error_rad),
            final_rotation: self.final_rotation.map(f64::from),
        }
    }
}

/// What a ranking reads of one object's metrics: [`ObjectMetrics`] and its packed form alike,
/// so a store scores its packed metrics without unpacking them.
pub trait MetricValues {
    /// The value of `metric` (`None`: time to rest of a body that never rested).
    fn get(&self, metric: Metric) -> Option<f64>;
    /// The final orientation, `[x, y, z, w]`.
    fn final_rotation(&self) -> Quat;
}

impl MetricValues for ObjectMetrics {
    fn get(&self, metric: Metric) -> Option<f64> {
        ObjectMetrics::get(self, metric)
    }
    fn final_rotation(&self) -> Quat {
        self.final_rotation
    }
}

impl MetricValues for PackedMetrics {
    /// [`ObjectMetrics::get`] of the unpacked values (inlined, the conversions a metric does not
    /// read are dropped).
    #[inline]
    fn get(&self, metric: Metric) -> Option<f64> {
        self.unpack().get(metric)
    }
    fn final_rotation(&self) -> Quat {
        self.final_rotation.map(f64::from)
    }
}

impl ObjectMetrics {
    /// Computes the metrics of one object's track. `goal` defaults to the first orientation.
    pub fn compute(
        track: &Track<'_>,
        impacts: u32,
        rest: RestThresholds,
        goal: Option<Quat>,
    ) -> Result<ObjectMetrics, BrowseError> {
        let dt = finite("frame_dt", track.frame_dt)?;
        if dt <= 0.0 {
            return Err(BrowseError::OutOfRange {
                field: "frame_dt",
                value: dt,
                expected: "a positive frame interval",
            });
        }
        let n = track.positions.len();
        if n == 0 {
            return Err(BrowseError::Empty {
                field: "track.positions",
            });
        }
        if track.rotations.len() != n {
            return Err(BrowseError::LengthMismatch {
                field: "track.rotations",
                expected: n,
                found: track.rotations.len(),
            });
        }
        for p in track.positions {
            for &v in p {
                finite("track.positions", v)?;
            }
        }
        let mut rotations = Vec::with_capacity(n);
        for q in track.rotations {
            for &v in q {
                finite("track.rotations", v)?;
            }
            rotations.push(quat_normalize(*q).ok_or(BrowseError::ZeroVector {
                field: "track.rotations",
            })?);
        }
        let goal = match goal {
            Some(g) => {
                for v in g {
                    finite("goal", v)?;
                }
                quat_normalize(g).ok_or(BrowseError::ZeroVector { field: "goal" })?
            }
            None => rotations[0],
        };

        let mut angular_travel = 0.0;
        // Index of the last frame interval in which the body moved.
        let mut last_moving: Option<usize> = None;
        for i in 0..n - 1 {
            let angle = quat_angle_between(rotations[i], rotations[i + 1]);
            angular_travel += angle;
            let speed = norm(sub(track.positions[i + 1], track.positions[i])) / dt;
            if speed >= rest.linear || angle / dt >= rest.angular {
                last_moving = Some(i);
            }
        }
        let (time_to_rest, came_to_rest) = match last_moving {
            None => (0.0, true),
            Some(i) => ((i + 1) as f64 * dt, i + 2 < n),
        };
        Ok(ObjectMetrics {
            angular_travel_rad: angular_travel,
            time_to_rest_s: time_to_rest,
            came_to_rest,
            impacts,
            orientation_error_rad: quat_angle_between(goal, rotations[n - 1]),
            final_rotation: rotations[n - 1],
        })
    }

    /// The object's value of `metric`. A body still moving when its world ended has no time to
    /// rest (`None`): its `time_to_rest_s` is only the world's end, and ranking it as if it had
    /// settled then would put the worlds that never settle first.
    pub fn get(&self, metric: Metric) -> Option<f64> {
        match metric {
            Metric::AngularTravel => Some(self.angular_travel_rad),
            Metric::TimeToRest => self.came_to_rest.then_some(self.time_to_rest_s),
            Metric::Impacts => Some(f64::from(self.impacts)),
            Metric::OrientationError => Some(self.orientation_error_rad),
        }
    }
}

/// The precomputed per-object metrics of §4.4.3.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Metric {
    AngularTravel,
    TimeToRest,
    Impacts,
    OrientationError,
}

impl Metric {
    /// How a ranking combines the chosen objects unless told otherwise — the one definition
    /// `mwb query rank` and the demo's summary share. Time to rest: the largest, since a world
    /// has come to rest when its last chosen body has (a sum of rest times means nothing to an
    /// animator); the others add up (§4.4.3: total spin, total impacts, total error).
    pub fn default_aggregate(self) -> Aggregate {
        match self {
            Metric::TimeToRest => Aggregate::Max,
            Metric::AngularTravel | Metric::Impacts | Metric::OrientationError => Aggregate::Sum,
        }
    }

    /// The unit of the metric's values (and of their sum or maximum).
    pub fn unit(self) -> &'static str {
        match self {
            Metric::AngularTravel | Metric::OrientationError => "rad",
            Metric::TimeToRest => "s",
            Metric::Impacts => "impacts",
        }
    }
}

impl WorldMetric {
    /// The unit of the measurement.
    pub fn unit(self) -> &'static str {
        match self {
            WorldMetric::EnergyGrowth | WorldMetric::PlausibilityExcess => "m",
            WorldMetric::AngularSpeedGrowth => "rad/s",
        }
    }
}

impl Aggregate {
    pub fn name(self) -> &'static str {
        match self {
            Aggregate::Sum => "sum",
            Aggregate::Max => "max",
        }
    }
}

/// How per-object values combine over the chosen objects (§4.4.3: sum or supremum).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Aggregate {
    Sum,
    Max,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Order {
    Ascending,
    Descending,
}

/// Per-world measurements (not per object): the §5.3.1 plausibility of a backward or mixed
/// world, as its reverse node measured it. `None` when not measured (forward worlds).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct WorldMetrics {
    /// Metres of drop height the whole mass gained over the backward part (see
    /// `WorldDone.energy_growth`); the larger, the less plausible.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub energy_growth: Option<f64>,
    /// rad/s: the largest angular speed over the backward part minus the given state's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub angular_speed_growth: Option<f64>,
    /// Whether the world is plausible by the definition of docs/reverse.md
    /// (`WorldDone.plausible`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plausible: Option<bool>,
    /// Metres by which the world's worst body breaks that definition, as a height; ≤ 0 means
    /// plausible (`WorldDone.plausibility_excess`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plausibility_excess: Option<f64>,
}

/// A per-world measurement to rank by.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WorldMetric {
    EnergyGrowth,
    AngularSpeedGrowth,
    PlausibilityExcess,
}

impl WorldMetrics {
    pub fn get(&self, metric: WorldMetric) -> Option<f64> {
        match metric {
            WorldMetric::EnergyGrowth => self.energy_growth,
            WorldMetric::AngularSpeedGrowth => self.angular_speed_growth,
            WorldMetric::PlausibilityExcess => self.plausibility_excess,
        }
    }
}

/// What to sort worlds by.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "key", rename_all = "snake_case")]
pub enum RankKey {
    /// A precomputed metric over the chosen objects.
    Metric {
        metric: Metric,
        objects: Vec<u32>,
        aggregate: Aggregate,
    },
    /// How many live constraints a world satisfies. §4.4.3: with this key the viewer shows all
    /// worlds, not only the survivors, to suggest which ones to refine.
    ConstraintsSatisfied,
    /// The angle (radians) between each chosen object's final orientation and `goal`, a world-
    /// frame unit quaternion `[x, y, z, w]` (normalised on use) chosen at query time — "lands
    /// upright" — where [`Metric::OrientationError`] measures against the starting orientation.
    OrientationTo {
        goal: Quat,
        objects: Vec<u32>,
        aggregate: Aggregate,
    },
    /// A per-world measurement; worlds without it (forward worlds for the plausibility
    /// measures) have no score and sort last. Ascending = most plausible first.
    World { metric: WorldMetric },
}

impl RankKey {
    /// The score of a world with these per-object metrics (indexed by object) that satisfies
    /// `constraints_satisfied` live constraints.
    pub fn score(&self, objects: &[ObjectMetrics], constraints_satisfied: u32) -> Option<f64> {
        self.score_with(objects, &WorldMetrics::default(), constraints_satisfied)
    }

    /// [`score`](Self::score) for a world with per-world measurements `world`.
    pub fn score_with<M: MetricValues>(
        &self,
        objects: &[M],
        world: &WorldMetrics,
        constraints_satisfied: u32,
    ) -> Option<f64> {
        match self {
            RankKey::World { metric } => world.get(*metric),
            RankKey::Metric {
                metric,
                objects: chosen,
                aggregate,
            } => score(objects, chosen, *metric, *aggregate),
            RankKey::ConstraintsSatisfied => Some(f64::from(constraints_satisfied)),
            RankKey::OrientationTo {
                goal,
                objects: chosen,
                aggregate,
            } => {
                let goal = quat_normalize(*goal)?;
                aggregate_over(chosen, *aggregate, |o| {
                    objects
                        .get(o as usize)
                        .map(|m| quat_angle_between(goal, m.final_rotation()))
                })
            }
        }
    }

    /// Checks what a shard cannot score: a goal orientation must be a finite, non-zero
    /// quaternion. The error names the field.
    pub fn validate(&self) -> Result<(), BrowseError> {
        if let RankKey::OrientationTo { goal, .. } = self {
            for &v in goal {
                finite("goal", v)?;
            }
            quat_normalize(*goal).ok_or(BrowseError::ZeroVector { field: "goal" })?;
        }
        Ok(())
    }
}

/// `metric` summed or maxed over the `chosen` objects of one world; `None` if none is chosen, a
/// chosen object is missing from `objects`, or one has no value (see [`ObjectMetrics::get`]).
pub fn score<M: MetricValues>(
    objects: &[M],
    chosen: &[u32],
    metric: Metric,
    aggregate: Aggregate,
) -> Option<f64> {
    aggregate_over(chosen, aggregate, |o| {
        objects.get(o as usize).and_then(|m| m.get(metric))
    })
}

/// `value` of the `chosen` objects summed or maxed; `None` if none is chosen or one has no value.
fn aggregate_over(
    chosen: &[u32],
    aggregate: Aggregate,
    value: impl Fn(u32) -> Option<f64>,
) -> Option<f64> {
    let mut values = chosen.iter().map(|&o| value(o));
    let first = values.next()??;
    values.try_fold(first, |acc, v| {
        let v = v?;
        Some(match aggregate {
            Aggregate::Sum => acc + v,
            Aggregate::Max => acc.max(v),
        })
    })
}

/// One row of a ranking.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Ranked {
    pub world: u32,
    /// `None` when the world has no value for the key (sorted last).
    pub score: Option<f64>,
}

/// Total order for rankings: scored before unscored, then by score in `order`, then by world
/// index ascending, so equal scores keep a stable, reproducible order across shards.
fn rank_cmp(order: Order, a: &Ranked, b: &Ranked) -> std::cmp::Ordering {
    let by_score = match (a.score, b.score) {
        (Some(x), Some(y)) => match order {
            Order::Ascending => x.total_cmp(&y),
            Order::Descending => y.total_cmp(&x),
        },
        (Some(_), None) => std::cmp::Ordering::Less,
        (None, Some(_)) => std::cmp::Ordering::Greater,
        (None, None) => std::cmp::Ordering::Equal,
    };
    by_score.then(a.world.cmp(&b.world))
}

/// NaN is "no value"; −0 and +0 tie.
fn clean(score: Option<f64>) -> Option<f64> {
    score.filter(|s| !s.is_nan()).map(|s| s + 0.0)
}

/// The best `k` of `candidates` by `score`, ties broken by world index.
pub fn top_k(
    candidates: impl IntoIterator<Item = u32>,
    k: usize,
    order: Order,
    score: impl FnMut(u32) -> Option<f64>,
) -> Vec<Ranked> {
    top_k_counted(candidates, k, order, score).0
}

/// [`top_k`] and how many candidates had no value (NaN counts as none); those sort last.
pub fn top_k_counted(
    candidates: impl IntoIterator<Item = u32>,
    k: usize,
    order: Order,
    mut score: impl FnMut(u32) -> Option<f64>,
) -> (Vec<Ranked>, u64) {
    let mut unscored = 0;
    let rows = candidates
        .into_iter()
        .map(|world| {
            let score = clean(score(world));
            unscored += u64::from(score.is_none());
            Ranked { world, score }
        })
        .collect();
    (select(rows, k, order), unscored)
}

/// Merges per-shard top-k lists into the global top `k` (each shard's list must be its own top
/// `k` under the same key and order).
pub fn merge_top_k(
    lists: impl IntoIterator<Item = Vec<Ranked>>,
    k: usize,
    order: Order,
) -> Vec<Ranked> {
    select(lists.into_iter().flatten().collect(), k, order)
}

fn select(mut rows: Vec<Ranked>, k: usize, order: Order) -> Vec<Ranked> {
    for r in &mut rows {
        r.score = clean(r.score);
    }
    if k == 0 {
        return Vec::new();
    }
    if k < rows.len() {
        rows.select_nth_unstable_by(k - 1, |a, b| rank_cmp(order, a, b));
        rows.truncate(k);
    }
    rows.sort_unstable_by(|a, b| rank_cmp(order, a, b));
    rows
}

#[cfg(test)]
mod tests;
