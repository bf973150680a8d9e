//! `mwb status`: live nodes, job progress and throughput.

use crate::bus::BusArgs;
use crate::client::{self, Status};
use crate::output::Summary;
use anyhow::Result;
use mwb_core::keys::Keys;
use std::fmt::Write as _;
use std::time::Duration;

/// Arguments of `mwb status`.
#[derive(Debug, Clone, clap::Args)]
pub struct StatusArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// Print the status as one JSON line.
    #[arg(long)]
    pub json: bool,
}

/// Gathers the status over the bus and prints it.
pub async fn run(args: StatusArgs) -> Result<()> {
    let keys = Keys::new(&args.bus.space)?;
    let session = args.bus.open(args.bus.client_default()).await?;
    let st = client::status(&session, &keys, Duration::from_millis(1500)).await;
    crate::bus::close(session).await;
    crate::output::print(&st?, args.json)
}

impl Summary for Status {
    fn table(&self) -> String {
        let mut t = format!(
            "{:<8} {:<40} {:>8} {:>9} {:>12}\n",
            "ROLE", "NODE", "WORLDS", "WORLDS/S", "MEMORY MiB"
        );
        for n in &self.nodes {
            let _ = writeln!(
                t,
                "{:<8} {:<40} {:>8} {:>9.1} {:>12.1}",
                n.role,
                n.node,
                n.worlds,
                n.worlds_per_s,
                n.memory_bytes as f64 / f64::from(1u32 << 20)
            );
            if n.index_failures > 0 {
                let _ = writeln!(
                    t,
                    "  {} stored worlds not browsable (their motion could not be indexed)",
                    n.index_failures
                );
            }
            if n.index_mismatches > 0 {
                let _ = writeln!(
                    t,
                    "  {} indexes sent by samplers differed from this store's own (its own kept; \
                     samplers and store of different builds?)",
                    n.index_mismatches
                );
            }
        }
        let links = links_table(self);
        if !links.is_empty() {
            let _ = writeln!(t);
            t.push_str(&links);
        }
        let _ = writeln!(t);
        let _ = writeln!(
            t,
            "{:<40} {:>12} {:>8} {:>9}",
            "JOB", "DONE", "STATE", "WORLDS/S"
        );
        for j in &self.jobs {
            let _ = writeln!(
                t,
                "{:<40} {:>5}/{:<6} {:>8} {:>9.1}",
                j.job,
                j.done,
                j.target,
                client::state_name(j.closed, j.cancelled),
                j.worlds_per_s
            );
            if let Some(why) = &j.stalled {
                let _ = writeln!(t, "  cannot complete: {why}");
            }
        }
        t
    }
}

/// Each session's links, one row per link: the nodes that share a session (a store and the
/// browsing coordinator it runs in-process) are one row's `NODE`, so a link is listed once.
/// Columns are as wide as their longest cell. Empty when no node reports links.
fn links_table(st: &Status) -> String {
    let mut sessions: Vec<(String, &[client::ConnectionStatus])> = Vec::new();
    let mut seen: std::collections::BTreeMap<&str, usize> = std::collections::BTreeMap::new();
    for n in st.nodes.iter().filter(|n| !n.connections.is_empty()) {
        let name = format!("{}/{}", n.role, n.node);
        match seen.get(n.zid.as_str()).filter(|_| !n.zid.is_empty()) {
            Some(&i) => sessions[i].0 = format!("{} + {name}", sessions[i].0),
            None => {
                seen.insert(n.zid.as_str(), sessions.len());
                sessions.push((name, &n.connections));
            }
        }
    }
    let mut rows = vec![[
        "NODE".to_owned(),
        "CONNECTED TO".to_owned(),
        "KIND".to_owned(),
        "CERTIFICATE".to_owned(),
        "ADDRESS".to_owned(),
    ]];
    for (name, links) in &sessions {
        for c in links.iter() {
            let to = if c.peer.is_empty() {
                format!("zenoh id {}", short(&c.zid))
            } else {
                compact(&c.peer)
            };
            let cert = c.certificate.as_deref().unwrap_or("none (tcp)").to_owned();
            rows.push([
                compact(name),
                to,
                c.whatami.clone(),
                cert,
                c.address.clone(),
            ]);
        }
    }
    if rows.len() == 1 {
        return String::new();
    }
    let width = |i: usize| rows.iter().map(|r| r[i].chars().count()).max().unwrap_or(0);
    let w = [width(0), width(1), width(2), width(3)];
    let mut t = String::new();
    for r in &rows {
        let _ = writeln!(
            t,
            "{:<w0$}  {:<w1$}  {:<w2$}  {:<w3$}  {}",
            r[0],
            r[1],
            r[2],
            r[3],
            r[4],
            w0 = w[0],
            w1 = w[1],
            w2 = w[2],
            w3 = w[3]
        );
    }
    t
}

/// Node names (`role/id`, several joined by ` + ` when they share a session) with each id cut
/// to 8 characters, and one id for roles that share it: `query/ab12…-query + store/ab12…`
/// → `query+store/ab12cd34`.
fn compact(names: &str) -> String {
    let parts: Vec<(&str, &str)> = names
        .split(" + ")
        .map(|n| n.split_once('/').unwrap_or((n, "")))
        .collect();
    let first = parts.first().map_or("", |p| short(p.1));
    if parts.iter().all(|p| short(p.1) == first) {
        let roles: Vec<&str> = parts.iter().map(|p| p.0).collect();
        format!("{}/{first}", roles.join("+"))
    } else {
        let each: Vec<String> = parts
            .iter()
            .map(|(role, id)| format!("{role}/{}", short(id)))
            .collect();
        each.join(" + ")
    }
}

/// The first 8 hex digits of a zenoh id: enough to tell sessions apart on screen.
fn short(zid: &str) -> &str {
    zid.get(..8).unwrap_or(zid)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::client::{ConnectionStatus, NodeStatus};

    fn link(peer: &str, cert: Option<&str>) -> ConnectionStatus {
        ConnectionStatus {
            peer: peer.into(),
            zid: "729f808b11".into(),
            whatami: "client".into(),
            address: "tls/127.0.0.1:58354".into(),
            certificate: cert.map(str::to_owned),
        }
    }

    /// Nodes sharing a session list its links once, under both names; a link without a
    /// certificate says so; no links, no table.
    #[test]
    fn links_are_listed_once_per_session() {
        let links = vec![
            link("sampler/ffeee5ea0123", Some("mwb-worker")),
            link("", None),
        ];
        let node = |role: &str, id: &str| NodeStatus {
            role: role.into(),
            node: id.into(),
            zid: "aa".into(),
            connections: links.clone(),
            ..Default::default()
        };
        let st = Status {
            nodes: vec![
                node("store", "149f81b3eaf7"),
                node("query", "149f81b3eaf7-query"),
            ],
            jobs: vec![],
        };
        let table = links_table(&st);
        let lines: Vec<&str> = table.lines().collect();
        assert_eq!(lines.len(), 3, "{table}");
        assert!(
            lines[1].starts_with("store+query/149f81b3  sampler/ffeee5ea"),
            "{table}"
        );
        assert!(lines[1].contains("mwb-worker"), "{table}");
        assert!(lines[2].contains("zenoh id 729f808b "), "{table}");
        assert!(lines[2].contains("none (tcp)"), "{table}");
        let bare = Status {
            nodes: vec![NodeStatus::default()],
            jobs: vec![],
        };
        assert_eq!(links_table(&bare), "");
        assert_eq!(
            compact("a/1234567890 + b/abcdefghij"),
            "a/12345678 + b/abcdefgh"
        );
    }

    /// A store's index trouble shows under its row; none, no line.
    #[test]
    fn index_trouble_is_shown_under_the_store() {
        let mut st = Status {
            nodes: vec![NodeStatus {
                role: "store".into(),
                node: "149f81b3".into(),
                ..Default::default()
            }],
            jobs: vec![],
        };
        assert!(!st.table().contains("index"), "{}", st.table());
        st.nodes[0].index_mismatches = 3;
        st.nodes[0].index_failures = 2;
        let table = st.table();
        assert!(
            table.contains("  3 indexes sent by samplers differed"),
            "{table}"
        );
        assert!(table.contains("  2 stored worlds not browsable"), "{table}");
    }
}
