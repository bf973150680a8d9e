//! `mwb query …`: scripted browsing against node-query (§4.4) — add, remove, undo and list
//! constraints, list and rank the surviving worlds, show one world; and `mwb query serve`, the
//! coordinator node itself. Every command prints a human summary or, with `--json`, the reply
//! as one JSON line.

use crate::bus::BusArgs;
use anyhow::{Context, Result, anyhow, bail};
use clap::{Args, Subcommand, ValueEnum};
use mwb_core::browse::api::{Reply, Request};
use mwb_core::browse::{
    Aggregate, Camera, Constraint, ConstraintId, Frustum, Metric, Order, Polarity, Quantifier,
    RankKey, Scope, ScreenRect, TimeWindow, WorldMetric, object_label, resolve_objects,
};
use mwb_core::keys::Keys;
use serde::Deserialize;
use std::path::PathBuf;
use std::time::Duration;

/// Options every `mwb query` request takes.
#[derive(Debug, Clone, Args)]
pub struct SessionArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// Browsing session: constraints and undo history are per session.
    #[arg(long, default_value = "default", env = "MWB_SESSION")]
    pub session: String,
    /// Print the reply as one JSON line.
    #[arg(long)]
    pub json: bool,
    /// Seconds to wait for node-query.
    #[arg(long, default_value_t = 30)]
    pub timeout: u64,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum RankBy {
    /// Integrated angular speed (radians turned).
    AngularTravel,
    /// Seconds until the chosen objects rest (by default the last of them: `--aggregate max`);
    /// worlds with a chosen body still moving at the end have no value and rank last.
    TimeToRest,
    /// Impact count.
    Impacts,
    /// Angle between the final and the starting orientation, or `--goal`.
    OrientationError,
    /// Number of live constraints satisfied (ranks every world, not only survivors).
    Constraints,
    /// Backward worlds: metres of drop height gained going back (§5.3.1; least first).
    EnergyGrowth,
    /// Backward worlds: rad/s of angular speed gained going back (§5.3.1; least first).
    AngularSpeedGrowth,
    /// Backward worlds: metres by which the worst body breaks the plausibility definition of
    /// docs/reverse.md (≤ 0: plausible; most plausible first).
    Plausibility,
}

#[derive(Debug, Subcommand)]
pub enum QueryCommand {
    /// Run the browsing coordinator (node-query) until Ctrl-C. One per space.
    Serve {
        #[command(flatten)]
        bus: BusArgs,
    },
    /// Add a constraint: a screen rectangle seen by a camera, a world-space box, or a JSON file.
    Add {
        #[command(flatten)]
        s: SessionArgs,
        #[command(flatten)]
        flags: ConstraintFlags,
    },
    /// Remove any live constraint by id (the result is the AND of the others).
    Remove {
        #[command(flatten)]
        s: SessionArgs,
        id: u64,
    },
    /// Undo the last add or remove.
    Undo {
        #[command(flatten)]
        s: SessionArgs,
    },
    /// Redo the last undone edit.
    Redo {
        #[command(flatten)]
        s: SessionArgs,
    },
    /// Live constraints with their counts, and the number of surviving worlds.
    List {
        #[command(flatten)]
        s: SessionArgs,
    },
    /// The surviving worlds (global indices).
    Result {
        #[command(flatten)]
        s: SessionArgs,
        #[arg(long)]
        limit: Option<usize>,
    },
    /// Rank the survivors by a metric over chosen objects.
    Rank {
        #[command(flatten)]
        s: SessionArgs,
        #[arg(long, value_enum, default_value = "time-to-rest")]
        by: RankBy,
        /// Objects: indices, body names (`S`, `block[17]`, `block` for all its instances),
        /// comma-separated, or `all`.
        #[arg(long, default_value = "all")]
        objects: String,
        /// How the chosen objects' values combine [default: max for time-to-rest (the world
        /// rests when its last chosen body does), sum for the others].
        #[arg(long, value_enum)]
        aggregate: Option<AggregateArg>,
        /// [default: ascending, except descending for `constraints`]
        #[arg(long, value_enum)]
        order: Option<OrderArg>,
        #[arg(short, long, default_value_t = 10)]
        k: usize,
        /// Rank every world, not only the survivors.
        #[arg(long)]
        all: bool,
        /// Only worlds measured plausible (backward and mixed worlds; docs/reverse.md).
        #[arg(long)]
        plausible: bool,
        /// With `--by orientation-error`: the goal orientation as a world-frame quaternion
        /// `x,y,z,w` (e.g. `0,0,0,1`: upright as modelled) instead of each object's start.
        #[arg(long, allow_hyphen_values = true)]
        goal: Option<String>,
    },
    /// The bodies of the worlds held: object indices and names, per scene.
    Bodies {
        #[command(flatten)]
        s: SessionArgs,
    },
    /// One world's metrics and standing in the session.
    Show {
        #[command(flatten)]
        s: SessionArgs,
        world: u32,
    },
    /// Forget the session.
    Close {
        #[command(flatten)]
        s: SessionArgs,
    },
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum AggregateArg {
    Sum,
    Max,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum OrderArg {
    Ascending,
    Descending,
}

/// A constraint file: any subset of the fields; flags override.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct ConstraintFile {
    camera: Option<Camera>,
    rect: Option<ScreenRect>,
    aabb: Option<AabbFile>,
    frustum: Option<Frustum>,
    polarity: Option<Polarity>,
    objects: Option<Vec<u32>>,
    quantifier: Option<Quantifier>,
    window: Option<TimeWindow>,
    scope: Option<Scope>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct AabbFile {
    min: [f64; 3],
    max: [f64; 3],
}

/// `n` comma-separated numbers of flag `--field`, or an error naming the flag.
pub(crate) fn numbers(field: &str, text: &str, n: usize) -> Result<Vec<f64>> {
    let v: Vec<f64> = text
        .split(',')
        .map(|t| {
            t.trim()
                .parse::<f64>()
                .with_context(|| format!("--{field}: {t:?} is not a number"))
        })
        .collect::<Result<_>>()?;
    if v.len() != n {
        bail!(
            "--{field}: expected {n} comma-separated numbers, found {}",
            v.len()
        );
    }
    if let Some(x) = v.iter().find(|x| !x.is_finite()) {
        bail!("--{field}: {x} is not finite");
    }
    Ok(v)
}

struct Client {
    session: zenoh::Session,
    keys: Keys,
    name: String,
    timeout: Duration,
}

impl Client {
    async fn open(s: &SessionArgs) -> Result<Self> {
        mwb_core::keys::check_identifier("session", &s.session)?;
        Ok(Self {
            session: s.bus.open(s.bus.client_default()).await?,
            keys: Keys::new(&s.bus.space)?,
            name: s.session.clone(),
            timeout: Duration::from_secs(s.timeout.max(1)),
        })
    }

    async fn send(&self, request: &Request) -> Result<Reply> {
        let reply =
            mwb_query::send(&self.session, &self.keys, &self.name, request, self.timeout).await?;
        if let Reply::Error { message } = &reply {
            bail!("{message}");
        }
        Ok(reply)
    }

    /// The distinct body lists of the worlds held.
    async fn bodies(&self) -> Result<Vec<mwb_core::browse::api::SceneBodies>> {
        match self.send(&Request::Bodies).await? {
            Reply::Bodies { scenes } => Ok(scenes),
            other => bail!("unexpected reply to a bodies request: {other:?}"),
        }
    }

    /// Object indices from indices, body names, generator instances or `all`, checked against
    /// the bodies of the worlds held (out-of-range indices are refused with the body count).
    async fn objects(&self, text: &str) -> Result<Vec<u32>> {
        let scenes = self.bodies().await?;
        if text.trim() == "all" && scenes.is_empty() {
            bail!("--objects all: the stores hold no worlds yet");
        }
        Ok(resolve_objects(text, &scenes)?)
    }

    /// Body names for printing: those of the one scene held (none if several or unnamed).
    async fn names(&self) -> Vec<String> {
        match self.bodies().await {
            Ok(scenes) if scenes.len() == 1 => scenes
                .into_iter()
                .next()
                .map(|s| s.names)
                .unwrap_or_default(),
            _ => Vec::new(),
        }
    }

    async fn close(self) {
        crate::bus::close(self.session).await;
    }
}

/// Runs one `mwb query` subcommand.
pub async fn run(command: QueryCommand) -> Result<()> {
    let (s, request) = match command {
        QueryCommand::Serve { bus } => return serve(bus).await,
        QueryCommand::Add { s, flags } => {
            let client = Client::open(&s).await?;
            let built = build_constraint(&client, flags).await;
            let constraint = match built {
                Ok(c) => c,
                Err(e) => {
                    client.close().await;
                    return Err(e);
                }
            };
            let id = constraint.id;
            let reply = client
                .send(&Request::Add {
                    constraint: Box::new(constraint),
                })
                .await;
            let names = client.names().await;
            client.close().await;
            let reply = reply?;
            print_reply(&s, &reply, &names, Some(&format!("added constraint {id}")))?;
            return Ok(());
        }
        QueryCommand::Remove { s, id } => (
            s,
            Request::Remove {
                id: ConstraintId(id),
            },
        ),
        QueryCommand::Undo { s } => (s, Request::Undo),
        QueryCommand::Redo { s } => (s, Request::Redo),
        QueryCommand::List { s } => (s, Request::Status),
        QueryCommand::Result { s, limit } => (s, Request::Result { limit }),
        QueryCommand::Rank {
            s,
            by,
            objects,
            aggregate,
            order,
            k,
            all,
            plausible,
            goal,
        } => {
            let goal = match (&goal, by) {
                (None, _) => None,
                (Some(g), RankBy::OrientationError) => {
                    let v = numbers("goal", g, 4)?;
                    Some([v[0], v[1], v[2], v[3]])
                }
                (Some(_), _) => bail!("--goal applies to --by orientation-error only"),
            };
            let metric = match by {
                RankBy::AngularTravel => Some(Metric::AngularTravel),
                RankBy::TimeToRest => Some(Metric::TimeToRest),
                RankBy::Impacts => Some(Metric::Impacts),
                RankBy::OrientationError => Some(Metric::OrientationError),
                RankBy::Constraints
                | RankBy::EnergyGrowth
                | RankBy::AngularSpeedGrowth
                | RankBy::Plausibility => None,
            };
            let aggregate = match aggregate {
                Some(AggregateArg::Sum) => Aggregate::Sum,
                Some(AggregateArg::Max) => Aggregate::Max,
                None => metric.map_or(Aggregate::Sum, Metric::default_aggregate),
            };
            let client = Client::open(&s).await?;
            let key = match by {
                RankBy::Constraints => Ok(RankKey::ConstraintsSatisfied),
                RankBy::EnergyGrowth => Ok(RankKey::World {
                    metric: WorldMetric::EnergyGrowth,
                }),
                RankBy::Plausibility => Ok(RankKey::World {
                    metric: WorldMetric::PlausibilityExcess,
                }),
                RankBy::AngularSpeedGrowth => Ok(RankKey::World {
                    metric: WorldMetric::AngularSpeedGrowth,
                }),
                RankBy::OrientationError if let Some(goal) = goal => client
                    .objects(&objects)
                    .await
                    .map(|objects| RankKey::OrientationTo {
                        goal,
                        objects,
                        aggregate,
                    }),
                other => client
                    .objects(&objects)
                    .await
                    .map(|objects| RankKey::Metric {
                        metric: match other {
                            RankBy::AngularTravel => Metric::AngularTravel,
                            RankBy::TimeToRest => Metric::TimeToRest,
                            RankBy::Impacts => Metric::Impacts,
                            _ => Metric::OrientationError,
                        },
                        objects,
                        aggregate,
                    }),
            };
            let order = match (order, by) {
                (Some(OrderArg::Ascending), _) => Order::Ascending,
                (Some(OrderArg::Descending), _) | (None, RankBy::Constraints) => Order::Descending,
                (None, _) => Order::Ascending,
            };
            let names = client.names().await;
            let reply = match &key {
                Ok(key) => {
                    client
                        .send(&Request::Rank {
                            key: key.clone(),
                            order,
                            k,
                            all_worlds: all || matches!(by, RankBy::Constraints),
                            plausible_only: plausible,
                        })
                        .await
                }
                Err(e) => Err(anyhow!("{e:#}")),
            };
            client.close().await;
            let headline = rank_headline(&key?, order, &names);
            print_reply(&s, &reply?, &names, Some(&headline))?;
            return Ok(());
        }
        QueryCommand::Show { s, world } => (s, Request::Summary { world }),
        QueryCommand::Bodies { s } => (s, Request::Bodies),
        QueryCommand::Close { s } => (s, Request::Close),
    };
    let client = Client::open(&s).await?;
    let reply = client.send(&request).await;
    let names = match (&reply, s.json) {
        (Ok(Reply::Status(_)), false) => client.names().await,
        _ => Vec::new(),
    };
    client.close().await;
    print_reply(&s, &reply?, &names, None)
}

/// What a ranking is by, over which objects, combined how, in which unit and order.
fn rank_headline(key: &RankKey, order: Order, names: &[String]) -> String {
    let objects = |list: &[u32]| {
        list.iter()
            .map(|&o| object_label(names, o))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let order = match order {
        Order::Ascending => "least first",
        Order::Descending => "most first",
    };
    match key {
        RankKey::Metric {
            metric,
            objects: list,
            aggregate,
        } => {
            let what = match metric {
                Metric::AngularTravel => "angular travel",
                Metric::TimeToRest => "time to rest",
                Metric::Impacts => "impacts",
                Metric::OrientationError => "orientation error from the start",
            };
            format!(
                "ranked by {what} [{}], {} over {}; {order}",
                metric.unit(),
                aggregate.name(),
                objects(list)
            )
        }
        RankKey::OrientationTo {
            goal,
            objects: list,
            aggregate,
        } => format!(
            "ranked by orientation error from {goal:?} [rad], {} over {}; {order}",
            aggregate.name(),
            objects(list)
        ),
        RankKey::ConstraintsSatisfied => {
            format!("ranked by live constraints satisfied [constraints]; {order}")
        }
        RankKey::World { metric } => {
            let what = match metric {
                WorldMetric::EnergyGrowth => "energy growth going back",
                WorldMetric::PlausibilityExcess => "plausibility excess",
                WorldMetric::AngularSpeedGrowth => "angular-speed growth going back",
            };
            format!("ranked by {what} [{}] (per world); {order}", metric.unit())
        }
    }
}

/// What `mwb query add` takes.
#[derive(Debug, Clone, Args)]
pub struct ConstraintFlags {
    /// Constraint id [default: one more than the largest live id].
    #[arg(long)]
    id: Option<u64>,
    /// "Never passes through" instead of "passes through".
    #[arg(long)]
    negative: bool,
    /// Objects: indices (scene body order), body names (`S`, `block[17]`, or `block` for all
    /// of its instances), comma-separated, or `all`. The constraint holds when any of them
    /// passes (§4.4.1), or every one with `--all`.
    #[arg(long)]
    objects: Option<String>,
    /// Every chosen object must pass, not just one of them (with `--negative`: worlds where
    /// not all of them pass through are kept).
    #[arg(long)]
    all: bool,
    /// Only during this time window, seconds: START:END. A body whose world ended before END
    /// stays at its final pose for the rest of the window.
    #[arg(long, conflicts_with = "final_pose")]
    window: Option<String>,
    /// Only the final (resting) pose counts: "ends in this box".
    #[arg(long = "final", id = "final_pose")]
    final_pose: bool,
    /// World-space box: MINX,MINY,MINZ,MAXX,MAXY,MAXZ (metres).
    #[arg(long, allow_hyphen_values = true)]
    aabb: Option<String>,
    /// Screen rectangle in pixels: X0,Y0,X1,Y1 (needs a camera).
    #[arg(long)]
    rect: Option<String>,
    /// Camera JSON file: {"position":[..],"rotation":[x,y,z,w],"intrinsics":{..},"viewport":{..}}.
    #[arg(long)]
    camera: Option<PathBuf>,
    /// JSON file with any of: camera, rect, aabb {min,max}, frustum, polarity, objects,
    /// quantifier ("any"/"all"), window, scope ("motion"/"final_pose"); flags override it.
    #[arg(long)]
    file: Option<PathBuf>,
}

async fn build_constraint(client: &Client, f: ConstraintFlags) -> Result<Constraint> {
    let mut file: ConstraintFile = match &f.file {
        Some(p) => {
            let text = std::fs::read_to_string(p)
                .with_context(|| format!("reading constraint file {}", p.display()))?;
            serde_json::from_str(&text)
                .with_context(|| format!("constraint file {}", p.display()))?
        }
        None => ConstraintFile::default(),
    };
    if let Some(p) = &f.camera {
        let text = std::fs::read_to_string(p)
            .with_context(|| format!("reading camera file {}", p.display()))?;
        file.camera = Some(
            serde_json::from_str(&text).with_context(|| format!("camera file {}", p.display()))?,
        );
    }
    if let Some(r) = &f.rect {
        let v = numbers("rect", r, 4)?;
        file.rect = Some(ScreenRect {
            x0: v[0],
            y0: v[1],
            x1: v[2],
            y1: v[3],
        });
    }
    if let Some(b) = &f.aabb {
        let v = numbers("aabb", b, 6)?;
        file.aabb = Some(AabbFile {
            min: [v[0], v[1], v[2]],
            max: [v[3], v[4], v[5]],
        });
    }
    let frustum = if let Some(b) = &file.aabb {
        Frustum::aabb(b.min, b.max)?
    } else if let Some(rect) = &file.rect {
        let camera = file
            .camera
            .ok_or_else(|| anyhow!("a screen rectangle needs a camera (--camera FILE)"))?;
        camera.frustum(rect)?
    } else if let Some(fr) = file.frustum {
        fr
    } else {
        bail!("no region: give --aabb, --rect with --camera, or --file");
    };
    if let Some(w) = &f.window {
        let (a, b) = w
            .split_once(':')
            .ok_or_else(|| anyhow!("--window: expected START:END seconds, e.g. 0.5:2"))?;
        let start: f64 = a
            .trim()
            .parse()
            .with_context(|| format!("--window: start {a:?} is not a number"))?;
        let end: f64 = b
            .trim()
            .parse()
            .with_context(|| format!("--window: end {b:?} is not a number"))?;
        file.window = Some(TimeWindow::new(start, end)?);
    }
    let objects = match (&f.objects, file.objects) {
        (Some(text), _) => client.objects(text).await?,
        (None, Some(list)) => {
            let text = list
                .iter()
                .map(u32::to_string)
                .collect::<Vec<_>>()
                .join(",");
            client
                .objects(&text)
                .await
                .context("constraint file: objects")?
        }
        (None, None) => {
            bail!(
                "which objects? give --objects 0,2 (scene body order), names (S, block[3]) or all"
            )
        }
    };
    let quantifier = if f.all {
        Quantifier::All
    } else {
        file.quantifier.unwrap_or_default()
    };
    let scope = if f.final_pose {
        Scope::FinalPose
    } else {
        file.scope.unwrap_or_default()
    };
    let polarity = if f.negative {
        Polarity::Negative
    } else {
        file.polarity.unwrap_or(Polarity::Positive)
    };
    let id = match f.id {
        Some(id) => ConstraintId(id),
        None => match client.send(&Request::Status).await? {
            Reply::Status(st) => {
                ConstraintId(st.constraints.iter().map(|c| c.id.0 + 1).max().unwrap_or(1))
            }
            _ => bail!("unexpected reply to a status request"),
        },
    };
    let constraint = Constraint {
        id,
        polarity,
        frustum,
        objects,
        quantifier,
        window: file.window,
        scope,
    };
    constraint.validate()?;
    Ok(constraint)
}

async fn serve(bus: BusArgs) -> Result<()> {
    let session = bus.open(bus.client_default()).await?;
    let q = mwb_query::run_query(
        session.clone(),
        mwb_query::QueryConfig {
            space: bus.space.clone(),
            ..Default::default()
        },
    )
    .await?;
    tracing::info!(node = q.node_id(), "node-query running; Ctrl-C stops it");
    let _ = tokio::signal::ctrl_c().await;
    q.stop();
    crate::bus::close(session).await;
    Ok(())
}

/// Prints a reply; `names` are the body names used to label objects (may be empty). A reply
/// that says the request failed (no such world) is an error, so the command exits non-zero.
fn print_reply(
    s: &SessionArgs,
    reply: &Reply,
    names: &[String],
    headline: Option<&str>,
) -> Result<()> {
    if let Reply::NoSuchWorld { world } = reply {
        bail!("no store holds world {world} (`mwb query result` lists the surviving worlds)");
    }
    if s.json {
        println!("{}", serde_json::to_string(reply)?);
        return Ok(());
    }
    if let Some(h) = headline {
        println!("{h}");
    }
    match reply {
        Reply::Status(st) => {
            println!(
                "session {}: {} of {} worlds satisfy all {} constraint(s){}{}",
                s.session,
                st.result,
                st.worlds,
                st.constraints.len(),
                if st.can_undo { "; undo possible" } else { "" },
                if st.can_redo { "; redo possible" } else { "" },
            );
            for c in &st.constraints {
                let when = match (c.scope, c.window) {
                    (Scope::FinalPose, _) => " in the final pose".to_owned(),
                    (Scope::Motion, Some(w)) => {
                        format!(" during {:.3}–{:.3} s", w.start(), w.end())
                    }
                    (Scope::Motion, None) => String::new(),
                };
                let objects = c
                    .objects
                    .iter()
                    .map(|&o| object_label(names, o))
                    .collect::<Vec<_>>()
                    .join(", ");
                let quantifier = match (c.quantifier, c.objects.len()) {
                    (_, 0 | 1) => "",
                    (Quantifier::Any, _) => "any of ",
                    (Quantifier::All, _) => "all of ",
                };
                println!(
                    "  #{:<4} {:<8} {quantifier}{objects}{when}: {} worlds",
                    c.id.0,
                    match c.polarity {
                        Polarity::Positive => "through",
                        Polarity::Negative => "never",
                    },
                    c.satisfied
                );
            }
        }
        Reply::Worlds { result, worlds } => {
            println!("{result} surviving worlds");
            let list: Vec<String> = worlds.iter().map(u32::to_string).collect();
            if !list.is_empty() {
                println!("{}", list.join(" "));
            }
        }
        Reply::Ranking {
            candidates,
            unscored,
            rows,
        } => {
            println!(
                "top {} of {candidates}; {unscored} without a value (sorted last{})",
                rows.len(),
                if headline.is_some_and(|h| h.contains("time to rest")) {
                    ": a chosen body was still moving at the end"
                } else {
                    ""
                }
            );
            for (i, r) in rows.iter().enumerate() {
                match r.score {
                    Some(v) => println!("{:>4}. world {:<8} {v:.4}", i + 1, r.world),
                    None => println!("{:>4}. world {:<8} (no value)", i + 1, r.world),
                }
            }
        }
        Reply::Summary(w) => {
            println!(
                "world {} (job {}, seed {:#018x}, shard {}): {} frames at {:.1} Hz, {}",
                w.world,
                w.job,
                w.seed,
                w.shard,
                w.frames,
                1.0 / w.frame_dt,
                if w.rested {
                    "came to rest"
                } else {
                    "still moving at the end"
                }
            );
            let edited = w
                .refined
                .as_ref()
                .is_some_and(|r| r.steps.iter().any(|s| s.scene_revision != 0));
            if edited {
                println!("regenerate: not yet for a world made by a scene edit");
            } else {
                println!(
                    "regenerate: {}",
                    crate::world_cmd::regenerate_command(w.world, w.seed)
                );
            }
            println!(
                "satisfies {} constraint(s); {}",
                w.constraints_satisfied,
                if w.in_result {
                    "in the result"
                } else {
                    "not in the result"
                }
            );
            if let Some(r) = &w.refined {
                let label = |o: &u32| mwb_core::browse::object_label(&w.bodies, *o);
                println!(
                    "refined (§4.5) from world seed {:#018x} of job {}:",
                    r.root_seed, r.root_job
                );
                for s in &r.steps {
                    if s.scene_revision != 0 {
                        println!(
                            "  from frame 0: its scene edited to revision {}, seed {:#018x}",
                            s.scene_revision, s.seed
                        );
                        continue;
                    }
                    let objects: Vec<String> = s.objects.iter().map(label).collect();
                    println!(
                        "  from frame {} (t = {:.3} s): {} re-simulated, seed {:#018x}",
                        s.frame,
                        f64::from(s.frame) * w.frame_dt,
                        objects.join(", "),
                        s.seed
                    );
                }
                let new: Vec<String> = r
                    .active_from
                    .iter()
                    .enumerate()
                    .filter_map(|(i, f)| f.map(|f| format!("{} from {f}", label(&(i as u32)))))
                    .collect();
                const SHOWN: usize = 8;
                println!(
                    "  new motion ({} of {} bodies): {}{}",
                    new.len(),
                    r.active_from.len(),
                    new[..new.len().min(SHOWN)].join(", "),
                    if new.len() > SHOWN { ", …" } else { "" }
                );
            }
            if let (Some(p), Some(x)) = (
                w.world_metrics.plausible,
                w.world_metrics.plausibility_excess,
            ) {
                println!(
                    "plausible: {} (worst body {x:+.3} m beyond the definition of docs/reverse.md)",
                    if p { "yes" } else { "no" }
                );
            }
            if let Some(e) = w.world_metrics.energy_growth {
                println!("energy growth going back: {e:.3} m of drop height (§5.3.1)");
            }
            if let Some(a) = w.world_metrics.angular_speed_growth {
                println!("angular-speed growth going back: {a:.3} rad/s");
            }
            let width = w.bodies.iter().map(String::len).max().unwrap_or(0).max(6);
            println!(
                "{:>width$}  {:<width$}  turned[rad]  rest[s]  impacts  orient.err[rad]  path±[mm]",
                "object", "name"
            );
            for (i, (m, r)) in w.objects.iter().zip(&w.path_radius).enumerate() {
                let name = w.bodies.get(i).map_or("", String::as_str);
                println!(
                    "{i:>width$}  {name:<width$}  {:>11.3}  {:>7.3}{} {:>7}  {:>15.4}  {:>9.2}",
                    m.angular_travel_rad,
                    m.time_to_rest_s,
                    if m.came_to_rest { " " } else { "+" },
                    m.impacts,
                    m.orientation_error_rad,
                    r * 1000.0
                );
            }
            if w.objects.iter().any(|m| !m.came_to_rest) {
                println!("+ still moving at the end: no time to rest (ranked last by it)");
            }
        }
        Reply::NoSuchWorld { .. } => {}
        Reply::Bodies { scenes } => {
            for sc in scenes {
                println!(
                    "{} worlds with {} bodies: {}",
                    sc.worlds,
                    sc.objects,
                    if sc.names.is_empty() {
                        "(names unknown)".to_owned()
                    } else {
                        sc.names.join(", ")
                    }
                );
            }
        }
        Reply::Closed => println!("session {} closed", s.session),
        Reply::Error { message } => bail!("{message}"),
    }
    Ok(())
}
