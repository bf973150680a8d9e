//! `mwb query …`: scripted browsing against node-query (§4.4) — add, remove, undo and list
//! constraints, list and rank the surviving worlds, show one world; and `mwb query serve`, the
//! coordinator node itself. Every command prints a human summary or, with `--json`, the reply
//! as one JSON line.

use crate::bus::BusArgs;
use anyhow::{Context, Result, anyhow, bail};
use clap::{Args, Subcommand, ValueEnum};
use mwb_core::browse::api::{Reply, Request};
use mwb_core::browse::{
    Aggregate, Camera, Constraint, ConstraintId, Frustum, Metric, Order, Polarity, RankKey,
    ScreenRect, TimeWindow, WorldMetric,
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
    /// Seconds until the objects rest.
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
        /// Object indices, comma-separated, or `all`.
        #[arg(long, default_value = "all")]
        objects: String,
        #[arg(long, value_enum, default_value = "sum")]
        aggregate: AggregateArg,
        /// [default: ascending, except descending for `constraints`]
        #[arg(long, value_enum)]
        order: Option<OrderArg>,
        #[arg(short, long, default_value_t = 10)]
        k: usize,
        /// Rank every world, not only the survivors.
        #[arg(long)]
        all: bool,
        /// With `--by orientation-error`: the goal orientation as a world-frame quaternion
        /// `x,y,z,w` (e.g. `0,0,0,1`: upright as modelled) instead of each object's start.
        #[arg(long, allow_hyphen_values = true)]
        goal: Option<String>,
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
    window: Option<TimeWindow>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct AabbFile {
    min: [f64; 3],
    max: [f64; 3],
}

fn numbers(field: &str, text: &str, n: usize) -> Result<Vec<f64>> {
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

    /// Object indices from `all` or a comma list; `all` asks a stored world how many it has.
    async fn objects(&self, text: &str) -> Result<Vec<u32>> {
        if text.trim() != "all" {
            return text
                .split(',')
                .map(|t| {
                    t.trim()
                        .parse::<u32>()
                        .with_context(|| format!("--objects: {t:?} is not an object index"))
                })
                .collect();
        }
        let Reply::Worlds { worlds, .. } = self.send(&Request::Result { limit: Some(1) }).await?
        else {
            bail!("unexpected reply to a result request");
        };
        // Any world will do: all worlds of a scene have the same bodies. Without survivors, ask
        // a ranking over all worlds for one.
        let world = match worlds.first() {
            Some(&w) => w,
            None => match self
                .send(&Request::Rank {
                    key: RankKey::ConstraintsSatisfied,
                    order: Order::Descending,
                    k: 1,
                    all_worlds: true,
                })
                .await?
            {
                Reply::Ranking { rows, .. } => rows
                    .first()
                    .map(|r| r.world)
                    .ok_or_else(|| anyhow!("--objects all: the stores hold no worlds yet"))?,
                _ => bail!("unexpected reply to a rank request"),
            },
        };
        match self.send(&Request::Summary { world }).await? {
            Reply::Summary(s) => Ok((0..s.objects.len() as u32).collect()),
            _ => bail!("--objects all: world {world} has no summary"),
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
            client.close().await;
            let reply = reply?;
            print_reply(&s, &reply, Some(&format!("added constraint {id}")))?;
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
            let aggregate = match aggregate {
                AggregateArg::Sum => Aggregate::Sum,
                AggregateArg::Max => Aggregate::Max,
            };
            let client = Client::open(&s).await?;
            let key = match by {
                RankBy::Constraints => Ok(RankKey::ConstraintsSatisfied),
                RankBy::EnergyGrowth => Ok(RankKey::World {
                    metric: WorldMetric::EnergyGrowth,
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
            let reply = match key {
                Ok(key) => {
                    client
                        .send(&Request::Rank {
                            key,
                            order,
                            k,
                            all_worlds: all || matches!(by, RankBy::Constraints),
                        })
                        .await
                }
                Err(e) => Err(e),
            };
            client.close().await;
            print_reply(&s, &reply?, None)?;
            return Ok(());
        }
        QueryCommand::Show { s, world } => (s, Request::Summary { world }),
        QueryCommand::Close { s } => (s, Request::Close),
    };
    let client = Client::open(&s).await?;
    let reply = client.send(&request).await;
    client.close().await;
    print_reply(&s, &reply?, None)
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
    /// Object indices (scene body order), comma-separated, or `all`.
    #[arg(long)]
    objects: Option<String>,
    /// Only during this time window, seconds: START:END.
    #[arg(long)]
    window: Option<String>,
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
    /// window; flags override it.
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
        (None, Some(list)) => list,
        (None, None) => bail!("which objects? give --objects 0,2 (scene body order) or all"),
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
    Ok(Constraint {
        id,
        polarity,
        frustum,
        objects,
        window: file.window,
    })
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

fn print_reply(s: &SessionArgs, reply: &Reply, headline: Option<&str>) -> Result<()> {
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
                let window = c
                    .window
                    .map(|w| format!(" during {:.3}–{:.3} s", w.start(), w.end()))
                    .unwrap_or_default();
                println!(
                    "  #{:<4} {:<8} objects {:?}{window}: {} worlds",
                    c.id.0,
                    match c.polarity {
                        Polarity::Positive => "through",
                        Polarity::Negative => "never",
                    },
                    c.objects,
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
        Reply::Ranking { candidates, rows } => {
            println!("top {} of {candidates}", rows.len());
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
            println!(
                "satisfies {} constraint(s); {}",
                w.constraints_satisfied,
                if w.in_result {
                    "in the result"
                } else {
                    "not in the result"
                }
            );
            if let Some(e) = w.world_metrics.energy_growth {
                println!("energy growth going back: {e:.3} m of drop height (§5.3.1)");
            }
            if let Some(a) = w.world_metrics.angular_speed_growth {
                println!("angular-speed growth going back: {a:.3} rad/s");
            }
            println!("object  turned[rad]  rest[s]  impacts  orient.err[rad]  path±[mm]");
            for (i, (m, r)) in w.objects.iter().zip(&w.path_radius).enumerate() {
                println!(
                    "{i:>6}  {:>11.3}  {:>7.3}{} {:>7}  {:>15.4}  {:>9.2}",
                    m.angular_travel_rad,
                    m.time_to_rest_s,
                    if m.came_to_rest { " " } else { "+" },
                    m.impacts,
                    m.orientation_error_rad,
                    r * 1000.0
                );
            }
        }
        Reply::NoSuchWorld { world } => println!("no store holds world {world}"),
        Reply::Closed => println!("session {} closed", s.session),
        Reply::Error { message } => bail!("{message}"),
    }
    Ok(())
}
