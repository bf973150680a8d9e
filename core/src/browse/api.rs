//! The browsing protocol between the viewer / `mwb query`, node-query and the store shards, and
//! the pure functions node-query uses to merge shard answers (§4.4, DESIGN.md "Store and
//! queries").
//!
//! Requests and replies travel as JSON: they are small, they are what scripts consume
//! (`mwb query … --json`), and [`Constraint`] validates its frustum on the way in.
//!
//! **Consistency.** Every store shard keeps, per browsing session, a [`ConstraintSet`] over its
//! own worlds. Edits (add, remove, undo, redo) are numbered by node-query; a shard applies edit
//! `n` only after `n − 1` and otherwise answers [`ShardReply::OutOfSync`] with how many it has, so
//! node-query replays the missing ones. That is also how a shard that joins late (or restarts)
//! catches up with a session begun without it.
//!
//! [`ConstraintSet`]: super::ConstraintSet

use serde::{Deserialize, Serialize};

use super::constraint::{Constraint, ConstraintId, Polarity, Quantifier, Scope, TimeWindow};
use super::metrics::{ObjectMetrics, Order, RankKey, Ranked, WorldMetrics, merge_top_k};

/// A browsing request, as a user or the viewer sends it to node-query.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "op", rename_all = "snake_case")]
pub enum Request {
    /// Adds a constraint (its id must not be live in the session).
    Add {
        constraint: Box<Constraint>,
    },
    /// Removes any live constraint; the result is the AND of the others, no geometry re-run.
    Remove {
        id: ConstraintId,
    },
    Undo,
    Redo,
    /// The session's constraints with their counts.
    Status,
    /// The surviving worlds (global indices, ascending), at most `limit` of them.
    Result {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        limit: Option<usize>,
    },
    /// The best `k` worlds by `key`. Over the survivors, or over every world when `all_worlds`
    /// (§4.4.3 does this when ranking by satisfied constraints, to suggest worlds to refine).
    Rank {
        key: RankKey,
        order: Order,
        k: usize,
        #[serde(default)]
        all_worlds: bool,
        /// Only worlds measured plausible (backward and mixed worlds whose
        /// `WorldDone.plausible` is true; docs/reverse.md): the others are not candidates.
        #[serde(default)]
        plausible_only: bool,
    },
    /// One world's per-object metrics and standing in the session.
    Summary {
        world: u32,
    },
    /// The bodies of the worlds held: one entry per distinct scene body list, so that a client
    /// can turn body names into object indices and check indices against the body count.
    Bodies,
    /// Forgets the session (its bitsets and undo history).
    Close,
}

impl Request {
    /// Whether the request changes the session (and so is numbered and replayed).
    pub fn is_edit(&self) -> bool {
        matches!(
            self,
            Request::Add { .. } | Request::Remove { .. } | Request::Undo | Request::Redo
        )
    }
}

/// An edit node-query applied, as it publishes it on `browse/<session>/edit` after the shards
/// answered, in the session's order: so that a recorder keeps the browsing session (the
/// requests and answers themselves travel as queries, which no subscriber sees).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EditRecord {
    pub session: String,
    /// 1-based number of the edit in the session.
    pub edit: u64,
    pub request: Request,
    /// The merged answer the client got.
    pub reply: Reply,
}

/// What node-query sends to a shard: the request, and for edits its number in the session.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ShardRequest {
    pub session: String,
    /// 1-based edit number for edits; `None` for reads.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seq: Option<u64>,
    pub request: Request,
}

/// A live constraint and how many worlds satisfy it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ConstraintStatus {
    pub id: ConstraintId,
    pub polarity: Polarity,
    pub objects: Vec<u32>,
    #[serde(default)]
    pub quantifier: Quantifier,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub window: Option<TimeWindow>,
    #[serde(default)]
    pub scope: Scope,
    pub satisfied: u64,
}

/// The bodies of a scene as the stores hold its worlds: names in object-index order (empty when
/// the store could not read the scene) and the object count.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub struct SceneBodies {
    pub objects: u32,
    pub names: Vec<String>,
    /// Worlds held with this body list.
    pub worlds: u64,
}

/// A session's state: worlds known, survivors, and each live constraint's count.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct SessionStatus {
    pub worlds: u64,
    pub result: u64,
    pub constraints: Vec<ConstraintStatus>,
    pub can_undo: bool,
    pub can_redo: bool,
    /// Edits applied.
    pub edits: u64,
}

/// One world's standing.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WorldSummary {
    pub world: u32,
    pub job: String,
    pub seed: u64,
    pub frames: u32,
    pub frame_dt: f64,
    pub rested: bool,
    /// Body names in object-index order (the scene's `[[body]]` names, `name[i]` for generated
    /// instances); empty if the store could not read the scene.
    #[serde(default)]
    pub bodies: Vec<String>,
    /// Per object, in the scene's body order.
    pub objects: Vec<ObjectMetrics>,
    /// Path-index inflation per object: codec e_max + low-res deviation, metres.
    pub path_radius: Vec<f64>,
    /// Per-world measurements (plausibility of backward worlds).
    #[serde(default)]
    pub world_metrics: WorldMetrics,
    pub constraints_satisfied: u32,
    pub in_result: bool,
    /// The shard (store node) holding it.
    pub shard: String,
    /// A refined world (§4.5): how it came to be. Absent for sampled worlds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refined: Option<Refined>,
}

/// How a refined world came to be: its root world, then each refinement in order (the last is
/// the world's own), and from which frame each body's motion is new in it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Refined {
    pub root_job: String,
    pub root_seed: u64,
    pub steps: Vec<RefineStep>,
    /// Per body, the first frame of new motion; `None`: the parent's motion throughout.
    pub active_from: Vec<Option<u32>>,
}

/// One refinement: from frame `frame` of its parent, `objects` re-simulated with seed `seed`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RefineStep {
    pub frame: u32,
    pub objects: Vec<u32>,
    pub seed: u64,
    /// A scene edit: the scene revision the world's scene became (0: a refinement).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub scene_revision: u64,
}

fn is_zero(x: &u64) -> bool {
    *x == 0
}

/// A shard's (or, merged, node-query's) answer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "reply", rename_all = "snake_case")]
pub enum Reply {
    Status(SessionStatus),
    Worlds {
        /// Survivors in all.
        result: u64,
        /// The first `limit` of them, ascending.
        worlds: Vec<u32>,
    },
    Ranking {
        /// Worlds ranked over (survivors, or all).
        candidates: u64,
        /// Candidates without a value for the key (ranked last): e.g. worlds whose chosen
        /// bodies were still moving at the end, for time to rest.
        #[serde(default)]
        unscored: u64,
        rows: Vec<Ranked>,
    },
    Summary(Box<WorldSummary>),
    Bodies {
        /// Distinct body lists, in a stable order.
        scenes: Vec<SceneBodies>,
    },
    /// The world is not in this shard (or, merged, in none).
    NoSuchWorld {
        world: u32,
    },
    Closed,
    /// The request is invalid (e.g. an unknown constraint id); names the problem.
    Error {
        message: String,
    },
}

/// A shard's answer to a [`ShardRequest`]: the reply, or how many edits it has applied when the
/// request's `seq` is not the next one.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "shard_reply", rename_all = "snake_case")]
pub enum ShardReply {
    Ok { edits: u64, reply: Reply },
    OutOfSync { edits: u64 },
}

/// Why shard answers cannot be merged.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MergeError {
    #[error("no shard answered")]
    NoShards,
    #[error("shards answered with different kinds of reply ({0} and {1})")]
    Mismatch(&'static str, &'static str),
    #[error("shards disagree about the session's constraints: {0}")]
    Constraints(String),
}

fn kind(r: &Reply) -> &'static str {
    match r {
        Reply::Status(_) => "status",
        Reply::Worlds { .. } => "worlds",
        Reply::Ranking { .. } => "ranking",
        Reply::Summary(_) => "summary",
        Reply::Bodies { .. } => "bodies",
        Reply::NoSuchWorld { .. } => "no_such_world",
        Reply::Closed => "closed",
        Reply::Error { .. } => "error",
    }
}

/// Merges the answers of every shard to the same request. Shards hold disjoint worlds, so
/// counts add, world lists are unions, rankings merge by [`merge_top_k`] (ties stay in world
/// order), and a summary comes from the one shard that has the world. An error from any shard
/// is the answer (edits are applied everywhere or reported).
pub fn merge(request: &Request, replies: Vec<Reply>) -> Result<Reply, MergeError> {
    if let Some(e) = replies.iter().find(|r| matches!(r, Reply::Error { .. })) {
        return Ok(e.clone());
    }
    let mut iter = replies.into_iter();
    let first = iter.next().ok_or(MergeError::NoShards)?;
    match (request, first) {
        (_, Reply::Status(mut acc)) => {
            for r in iter {
                let Reply::Status(s) = r else {
                    return Err(MergeError::Mismatch("status", kind(&r)));
                };
                merge_status(&mut acc, s)?;
            }
            Ok(Reply::Status(acc))
        }
        (Request::Result { limit }, Reply::Worlds { result, worlds }) => {
            let mut total = result;
            let mut all = worlds;
            for r in iter {
                let Reply::Worlds { result, worlds } = r else {
                    return Err(MergeError::Mismatch("worlds", kind(&r)));
                };
                total += result;
                all.extend(worlds);
            }
            all.sort_unstable();
            all.dedup();
            if let Some(l) = limit {
                all.truncate(*l);
            }
            Ok(Reply::Worlds {
                result: total,
                worlds: all,
            })
        }
        (
            Request::Rank { order, k, .. },
            Reply::Ranking {
                candidates,
                unscored,
                rows,
            },
        ) => {
            let (mut total, mut none) = (candidates, unscored);
            let mut lists = vec![rows];
            for r in iter {
                let Reply::Ranking {
                    candidates,
                    unscored,
                    rows,
                } = r
                else {
                    return Err(MergeError::Mismatch("ranking", kind(&r)));
                };
                total += candidates;
                none += unscored;
                lists.push(rows);
            }
            Ok(Reply::Ranking {
                candidates: total,
                unscored: none,
                rows: merge_top_k(lists, *k, *order),
            })
        }
        (Request::Bodies, Reply::Bodies { scenes }) => {
            let mut all = scenes;
            for r in iter {
                let Reply::Bodies { scenes } = r else {
                    return Err(MergeError::Mismatch("bodies", kind(&r)));
                };
                all.extend(scenes);
            }
            Ok(Reply::Bodies {
                scenes: merge_bodies(all),
            })
        }
        (Request::Summary { world }, first) => {
            let mut found = None;
            for r in std::iter::once(first).chain(iter) {
                match r {
                    Reply::Summary(s) => found = Some(Reply::Summary(s)),
                    Reply::NoSuchWorld { .. } => {}
                    other => return Err(MergeError::Mismatch("summary", kind(&other))),
                }
            }
            Ok(found.unwrap_or(Reply::NoSuchWorld { world: *world }))
        }
        (_, first) => {
            for r in iter {
                if kind(&r) != kind(&first) {
                    return Err(MergeError::Mismatch(kind(&first), kind(&r)));
                }
            }
            Ok(first)
        }
    }
}

/// One entry per distinct body list (names and count), worlds added, most worlds first.
pub fn merge_bodies(scenes: Vec<SceneBodies>) -> Vec<SceneBodies> {
    let mut by_list: std::collections::BTreeMap<(u32, Vec<String>), u64> = Default::default();
    for s in scenes {
        *by_list.entry((s.objects, s.names)).or_default() += s.worlds;
    }
    let mut out: Vec<SceneBodies> = by_list
        .into_iter()
        .map(|((objects, names), worlds)| SceneBodies {
            objects,
            names,
            worlds,
        })
        .collect();
    out.sort_by(|a, b| b.worlds.cmp(&a.worlds).then_with(|| a.cmp(b)));
    out
}

/// Adds one shard's session status into `acc`. The constraint lists must agree (same ids in the
/// same order): every shard applied the same edits.
fn merge_status(acc: &mut SessionStatus, s: SessionStatus) -> Result<(), MergeError> {
    let ids = |st: &SessionStatus| st.constraints.iter().map(|c| c.id).collect::<Vec<_>>();
    if ids(acc) != ids(&s) {
        return Err(MergeError::Constraints(format!(
            "{:?} vs {:?}",
            ids(acc),
            ids(&s)
        )));
    }
    acc.worlds += s.worlds;
    acc.result += s.result;
    for (a, b) in acc.constraints.iter_mut().zip(&s.constraints) {
        a.satisfied += b.satisfied;
    }
    acc.can_undo &= s.can_undo;
    acc.can_redo &= s.can_redo;
    acc.edits = acc.edits.min(s.edits);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::browse::{Aggregate, Metric};

    fn status(worlds: u64, result: u64, sat: &[(u64, u64)]) -> Reply {
        Reply::Status(SessionStatus {
            worlds,
            result,
            constraints: sat
                .iter()
                .map(|&(id, satisfied)| ConstraintStatus {
                    id: ConstraintId(id),
                    polarity: Polarity::Positive,
                    objects: vec![0],
                    quantifier: Quantifier::Any,
                    window: None,
                    scope: Scope::Motion,
                    satisfied,
                })
                .collect(),
            can_undo: true,
            can_redo: false,
            edits: 3,
        })
    }

    #[test]
    fn status_counts_add_and_lists_must_agree() {
        let merged = merge(
            &Request::Status,
            vec![
                status(10, 4, &[(1, 6), (2, 5)]),
                status(7, 2, &[(1, 3), (2, 4)]),
            ],
        )
        .expect("merges");
        let Reply::Status(s) = merged else {
            panic!("status expected")
        };
        assert_eq!((s.worlds, s.result), (17, 6));
        assert_eq!(s.constraints[0].satisfied, 9);
        assert_eq!(s.constraints[1].satisfied, 9);
        assert!(matches!(
            merge(
                &Request::Status,
                vec![status(1, 1, &[(1, 1)]), status(1, 1, &[(2, 1)])]
            ),
            Err(MergeError::Constraints(_))
        ));
        assert_eq!(merge(&Request::Status, vec![]), Err(MergeError::NoShards));
    }

    #[test]
    fn worlds_union_sorted_and_limited() {
        let req = Request::Result { limit: Some(3) };
        let merged = merge(
            &req,
            vec![
                Reply::Worlds {
                    result: 3,
                    worlds: vec![0, 4, 8],
                },
                Reply::Worlds {
                    result: 2,
                    worlds: vec![1, 5],
                },
            ],
        )
        .expect("merges");
        assert_eq!(
            merged,
            Reply::Worlds {
                result: 5,
                worlds: vec![0, 1, 4]
            }
        );
    }

    #[test]
    fn ranking_merges_top_k_and_summary_finds_the_owner() {
        let req = Request::Rank {
            key: RankKey::Metric {
                metric: Metric::Impacts,
                objects: vec![0],
                aggregate: Aggregate::Sum,
            },
            order: Order::Descending,
            k: 2,
            all_worlds: false,
            plausible_only: false,
        };
        let row = |world, score| Ranked {
            world,
            score: Some(score),
        };
        let merged = merge(
            &req,
            vec![
                Reply::Ranking {
                    candidates: 5,
                    unscored: 1,
                    rows: vec![row(2, 9.0), row(0, 3.0)],
                },
                Reply::Ranking {
                    candidates: 4,
                    unscored: 2,
                    rows: vec![row(1, 9.0), row(3, 7.0)],
                },
            ],
        )
        .expect("merges");
        assert_eq!(
            merged,
            Reply::Ranking {
                candidates: 9,
                unscored: 3,
                rows: vec![row(1, 9.0), row(2, 9.0)]
            }
        );
        let none = merge(
            &Request::Summary { world: 4 },
            vec![
                Reply::NoSuchWorld { world: 4 },
                Reply::NoSuchWorld { world: 4 },
            ],
        );
        assert_eq!(none, Ok(Reply::NoSuchWorld { world: 4 }));
        let err = Reply::Error {
            message: "no live constraint with id 3".into(),
        };
        assert_eq!(
            merge(
                &Request::Remove {
                    id: ConstraintId(3)
                },
                vec![status(1, 1, &[]), err.clone()]
            ),
            Ok(err)
        );
    }

    #[test]
    fn bodies_merge_by_list_and_old_replies_still_parse() {
        let scene = |names: &[&str], worlds| SceneBodies {
            objects: names.len() as u32,
            names: names.iter().map(|n| (*n).to_owned()).collect(),
            worlds,
        };
        let merged = merge(
            &Request::Bodies,
            vec![
                Reply::Bodies {
                    scenes: vec![scene(&["a", "b"], 3), scene(&["x"], 5)],
                },
                Reply::Bodies {
                    scenes: vec![scene(&["a", "b"], 4)],
                },
                Reply::Bodies { scenes: vec![] },
            ],
        );
        assert_eq!(
            merged,
            Ok(Reply::Bodies {
                scenes: vec![scene(&["a", "b"], 7), scene(&["x"], 5)]
            })
        );
        // A ranking from a shard that does not count unscored worlds yet.
        let old: Reply = serde_json::from_str(r#"{"reply":"ranking","candidates":2,"rows":[]}"#)
            .expect("parses");
        assert_eq!(
            old,
            Reply::Ranking {
                candidates: 2,
                unscored: 0,
                rows: vec![]
            }
        );
    }

    #[test]
    fn requests_round_trip_as_json() {
        let reqs = [
            r#"{"op":"undo"}"#,
            r#"{"op":"result","limit":5}"#,
            r#"{"op":"rank","key":{"key":"constraints_satisfied"},"order":"descending","k":3,"all_worlds":true}"#,
            r#"{"op":"remove","id":4}"#,
            r#"{"op":"bodies"}"#,
        ];
        for text in reqs {
            let r: Request = serde_json::from_str(text).expect(text);
            let back: Request =
                serde_json::from_str(&serde_json::to_string(&r).expect("serialises"))
                    .expect("parses");
            assert_eq!(r, back);
        }
        assert!(serde_json::from_str::<Request>(r#"{"op":"explode"}"#).is_err());
        assert!(Request::Undo.is_edit() && !Request::Status.is_edit());
    }
}
