//! `mwb record` and `mwb replay`: sessions to MCAP and back (`mwb-record`).
//!
//! * `mwb record --out session.mcap [--connect …] [--space S] [--duration 10m] [--lossless]`
//!   records every put on `mwb/<space>/**` — jobs, job states, segments, world summaries, node
//!   stats — until Ctrl-C or the duration, then finishes the file. Queries and their replies
//!   (world fetches, browsing) are not visible to a subscriber and are not recorded. If the
//!   disk cannot keep up, messages are dropped, counted and reported (the command then exits
//!   with an error, the file being complete otherwise); `--lossless` makes the bus wait instead.
//! * `mwb replay session.mcap [--connect …] [--space S] [--speed 1|4|max]` puts the recording
//!   back on the bus in order into space `S` (the bus option every command has; the recorded
//!   space is rewritten), at the recorded pace, faster, or as fast as the bus takes it. A
//!   damaged file is replayed up to the damage, and the command then fails naming the file
//!   and the byte offset.

use crate::bus::BusArgs;
use anyhow::{Context, Result, bail};
use mwb_record::{
    Family, Overflow, RecordSummary, RecorderConfig, ReplayConfig, ReplaySummary, Speed,
    parse_duration, run_recorder,
};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::{Duration, Instant};

/// After the last put of a replay, the session stays open this long so that the transport's
/// queues drain before it closes (a put returns once queued, not once delivered).
const REPLAY_DRAIN: Duration = Duration::from_millis(500);

/// Arguments of `mwb record`.
#[derive(Debug, Clone, clap::Args)]
pub struct RecordArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// The recording to write (MCAP; created, or truncated if it exists).
    #[arg(long, short = 'o', value_name = "FILE")]
    pub out: PathBuf,
    /// Stop after this long: 500ms, 90s, 10m, 1h [default: until Ctrl-C].
    #[arg(long, value_parser = parse_duration)]
    pub duration: Option<Duration>,
    /// When the disk cannot keep up, make the bus wait (the cluster slows down to disk speed)
    /// instead of dropping messages, which are then counted and reported.
    #[arg(long)]
    pub lossless: bool,
    /// Memory between the bus and the disk, MiB.
    #[arg(long, default_value_t = 256)]
    pub queue_mib: u64,
    /// Print the summary as one JSON line.
    #[arg(long)]
    pub json: bool,
}

/// Arguments of `mwb replay`.
#[derive(Debug, Clone, clap::Args)]
pub struct ReplayArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// The recording (`mwb record --out`).
    #[arg(value_name = "FILE")]
    pub file: PathBuf,
    /// 1: the recorded pace; 4: four times as fast; max: as fast as the bus takes it.
    #[arg(long, default_value = "1")]
    pub speed: Speed,
    /// Wait up to this long for a store in the target space before the first message
    /// (0: do not wait).
    #[arg(long, default_value = "10s", value_parser = parse_duration)]
    pub wait: Duration,
    /// Print the summary as one JSON line.
    #[arg(long)]
    pub json: bool,
}

/// `mwb record`'s result line.
#[derive(Debug, Clone, serde::Serialize)]
pub struct RecordReport {
    pub out: String,
    pub space: String,
    pub seconds: f64,
    pub messages: u64,
    pub by_topic: BTreeMap<String, u64>,
    pub received: u64,
    pub not_written: u64,
    pub not_written_by_topic: BTreeMap<String, u64>,
    pub bus_waited_s: f64,
    pub file_bytes: u64,
    /// Binary and physics build of the recorded worlds (`WorldDone.provenance`).
    pub provenance: Vec<String>,
}

/// `mwb replay`'s result line.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ReplayReport {
    pub file: String,
    pub recorded_space: Option<String>,
    pub space: String,
    pub speed: String,
    pub published: u64,
    pub by_topic: BTreeMap<String, u64>,
    pub skipped_unknown_channels: BTreeMap<String, u64>,
    pub put_failures: u64,
    pub seconds: f64,
    pub recorded_seconds: f64,
    /// The damage that ended the replay early, if any (file: byte offset: what).
    pub damage: Option<String>,
    pub stopped_by_user: bool,
}

fn by_topic(m: &BTreeMap<Family, u64>) -> BTreeMap<String, u64> {
    m.iter().map(|(f, n)| (f.topic().to_owned(), *n)).collect()
}

fn topics_line(m: &BTreeMap<String, u64>) -> String {
    let parts: Vec<String> = m.iter().map(|(t, n)| format!("{t} {n}")).collect();
    parts.join(", ")
}

/// Resolves on Ctrl-C, or after `limit` if given. Without a signal handler and a limit, there
/// is no way to stop: that is an error, not a recording that never ends.
async fn stop_signal(limit: Option<Duration>) -> Result<()> {
    let ctrl_c = async {
        match tokio::signal::ctrl_c().await {
            Ok(()) => Ok(()),
            Err(e) if limit.is_some() => {
                tracing::warn!(error = %e, "no Ctrl-C handler; stopping at --duration only");
                std::future::pending().await
            }
            Err(e) => Err(anyhow::Error::new(e).context("installing the Ctrl-C handler")),
        }
    };
    match limit {
        Some(d) => tokio::select! {
            r = ctrl_c => r,
            () = tokio::time::sleep(d) => Ok(()),
        },
        None => ctrl_c.await,
    }
}

pub fn record_report(args: &RecordArgs, s: &RecordSummary, seconds: f64) -> RecordReport {
    RecordReport {
        out: s.path.display().to_string(),
        space: args.bus.space.clone(),
        seconds,
        messages: s.written.messages,
        by_topic: by_topic(&s.written.by_family),
        received: s.received,
        not_written: s.dropped,
        not_written_by_topic: by_topic(&s.dropped_by_family),
        bus_waited_s: s.bus_waited.as_secs_f64(),
        file_bytes: s.file_bytes,
        provenance: s.written.provenance.iter().cloned().collect(),
    }
}

/// `mwb record`.
pub async fn record(args: RecordArgs) -> Result<()> {
    let session = args.bus.open(args.bus.client_default()).await?;
    let mut extra = BTreeMap::new();
    extra.insert("recorder_build".into(), mwb_sampler::world::provenance());
    let cfg = RecorderConfig {
        space: args.bus.space.clone(),
        out: args.out.clone(),
        overflow: if args.lossless {
            Overflow::Block
        } else {
            Overflow::Drop
        },
        queue_bytes: usize::try_from(args.queue_mib.saturating_mul(1 << 20)).unwrap_or(usize::MAX),
        mwb_version: env!("CARGO_PKG_VERSION").into(),
        extra_metadata: extra,
        ..Default::default()
    };
    let rec = run_recorder(&session, cfg)
        .await
        .with_context(|| format!("starting to record into {}", args.out.display()))?;
    let start = Instant::now();
    eprintln!(
        "mwb record: recording mwb/{}/** into {}{} (Ctrl-C ends it)",
        args.bus.space,
        args.out.display(),
        args.duration
            .map_or(String::new(), |d| format!(" for {:.1} s", d.as_secs_f64()))
    );
    let stopped = stop_signal(args.duration).await;
    let summary = rec.finish().await;
    crate::bus::close(session).await;
    stopped?;
    let s = summary.with_context(|| format!("finishing {}", args.out.display()))?;
    let report = record_report(&args, &s, start.elapsed().as_secs_f64());
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        println!(
            "mwb record: {} messages ({}), {:.2} MB in {} over {:.1} s; {} not written",
            report.messages,
            topics_line(&report.by_topic),
            report.file_bytes as f64 / 1e6,
            report.out,
            report.seconds,
            report.not_written
        );
    }
    if let Some(e) = s.write_error {
        return Err(anyhow::Error::new(e).context(format!(
            "recording into {} stopped early; the file ends at its last whole chunk",
            args.out.display()
        )));
    }
    if s.dropped > 0 {
        bail!(
            "{} of {} messages were not written ({}): the disk could not keep up; the recording \
             is otherwise complete (--lossless makes the bus wait instead)",
            s.dropped,
            s.received,
            topics_line(&report.not_written_by_topic)
        );
    }
    Ok(())
}

pub fn replay_report(args: &ReplayArgs, s: &ReplaySummary) -> ReplayReport {
    ReplayReport {
        file: args.file.display().to_string(),
        recorded_space: s.recorded_space.clone(),
        space: args.bus.space.clone(),
        speed: args.speed.to_string(),
        published: s.published,
        by_topic: by_topic(&s.by_family),
        skipped_unknown_channels: s.read.skipped_unknown.clone(),
        put_failures: s.put_failures,
        seconds: s.seconds,
        recorded_seconds: s.recorded_seconds,
        damage: s.damage.as_ref().map(|e| e.to_string()),
        stopped_by_user: s.stopped,
    }
}

/// `mwb replay`.
pub async fn replay(args: ReplayArgs) -> Result<()> {
    let session = args.bus.open(args.bus.client_default()).await?;
    let cfg = ReplayConfig {
        path: args.file.clone(),
        speed: args.speed,
        space: args.bus.space.clone(),
        wait_for_subscribers: args.wait,
    };
    let stop = async {
        if let Err(e) = tokio::signal::ctrl_c().await {
            // Without a handler the replay runs to its end.
            tracing::warn!(error = %e, "no Ctrl-C handler");
            std::future::pending::<()>().await;
        }
    };
    let result = mwb_record::replay(&session, &cfg, stop).await;
    tokio::time::sleep(REPLAY_DRAIN).await;
    crate::bus::close(session).await;
    let s = result.with_context(|| format!("replaying {}", args.file.display()))?;
    let report = replay_report(&args, &s);
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        println!(
            "mwb replay: {} messages ({}) from {} into space {} at speed {} in {:.1} s \
             (recorded over {:.1} s){}",
            report.published,
            topics_line(&report.by_topic),
            report.file,
            report.space,
            report.speed,
            report.seconds,
            report.recorded_seconds,
            if report.skipped_unknown_channels.is_empty() {
                String::new()
            } else {
                format!(
                    "; skipped on unknown channels: {}",
                    topics_line(&report.skipped_unknown_channels)
                )
            }
        );
    }
    if s.put_failures > 0 {
        bail!("{} puts failed (see the warnings above)", s.put_failures);
    }
    if let Some(e) = s.damage {
        return Err(anyhow::Error::new(e).context(format!(
            "the recording is damaged: the {} messages before the damage were replayed",
            s.published
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bus::Mode;
    use mwb_proto::v1::{JobState, Message};
    use zenoh::qos::CongestionControl;

    fn bus(space: &str, connect: u16) -> BusArgs {
        BusArgs {
            connect: vec![format!("tcp/127.0.0.1:{connect}")],
            listen: Vec::new(),
            config: None,
            mode: Some(Mode::Peer),
            space: space.into(),
            multicast: false,
        }
    }

    /// The two command bodies against a real peer: record for a while, replay into another
    /// space, and the replay sees exactly what was put.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn record_then_replay_commands() {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .map(|a| a.port())
            .unwrap();
        let mut c = zenoh::Config::default();
        for (k, v) in [
            ("mode", "\"peer\"".to_owned()),
            ("listen/endpoints", format!("[\"tcp/127.0.0.1:{port}\"]")),
            ("scouting/multicast/enabled", "false".into()),
            ("scouting/gossip/enabled", "false".into()),
        ] {
            c.insert_json5(k, &v).unwrap();
        }
        let hub = tokio::time::timeout(Duration::from_secs(20), zenoh::open(c))
            .await
            .unwrap()
            .unwrap();
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("cmd.mcap");
        let args = RecordArgs {
            bus: bus("c1", port),
            out: out.clone(),
            duration: Some(Duration::from_secs(3)),
            lossless: false,
            queue_mib: 16,
            json: true,
        };
        let recording = tokio::spawn(record(args));
        // Once the recorder's subscription is known here, put three job states.
        let p = hub
            .declare_publisher("mwb/c1/job/j/state")
            .congestion_control(CongestionControl::Block)
            .await
            .unwrap();
        let deadline = Instant::now() + Duration::from_secs(10);
        while !p.matching_status().await.unwrap().matching() {
            assert!(Instant::now() < deadline, "recorder never subscribed");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let states: Vec<Vec<u8>> = (1..=3)
            .map(|n| {
                JobState {
                    job_id: "j".into(),
                    revision: n,
                    worlds_done: n as u32,
                    ..Default::default()
                }
                .encode_to_vec()
            })
            .collect();
        for s in &states {
            p.put(s.clone()).await.unwrap();
        }
        tokio::time::timeout(Duration::from_secs(30), recording)
            .await
            .unwrap()
            .unwrap()
            .unwrap();

        let sub = hub.declare_subscriber("mwb/c2/**").await.unwrap();
        let args = ReplayArgs {
            bus: bus("c2", port),
            file: out,
            speed: Speed::Max,
            // The subscriber above stands in for a store (it takes jobs, segments, summaries).
            wait: Duration::from_secs(10),
            json: true,
        };
        let replaying = tokio::spawn(replay(args));
        let mut got = Vec::new();
        while got.len() < states.len() {
            let s = tokio::time::timeout(Duration::from_secs(20), sub.recv_async())
                .await
                .unwrap()
                .unwrap();
            assert_eq!(s.key_expr().as_str(), "mwb/c2/job/j/state");
            got.push(s.payload().to_bytes().into_owned());
        }
        assert_eq!(got, states);
        tokio::time::timeout(Duration::from_secs(30), replaying)
            .await
            .unwrap()
            .unwrap()
            .unwrap();
        let _ = tokio::time::timeout(Duration::from_secs(5), hub.close()).await;
    }
}
