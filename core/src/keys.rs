//! Bus key expressions — the one source of truth for DESIGN.md "The bus".
//!
//! All keys live under `mwb/<space>/…`. Identifiers used as key chunks (space, job id, node id,
//! role) are restricted to `[A-Za-z0-9_.-]` so they can never contain a wildcard or separator.

use thiserror::Error;

/// The space every node and client uses unless told otherwise (`mwb/default/…`).
pub const DEFAULT_SPACE: &str = "default";

/// An identifier that cannot be a key chunk.
#[derive(Debug, Error, PartialEq, Eq)]
#[error("{what} {value:?} is not a valid identifier: use 1-64 characters from [A-Za-z0-9_.-]")]
pub struct BadIdentifier {
    pub what: &'static str,
    pub value: String,
}

/// Checks that `value` may be used as one key chunk.
pub fn check_identifier(what: &'static str, value: &str) -> Result<(), BadIdentifier> {
    let ok = !value.is_empty()
        && value.len() <= 64
        && value
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-' || b == b'.');
    if ok {
        Ok(())
    } else {
        Err(BadIdentifier {
            what,
            value: value.to_owned(),
        })
    }
}

/// The last chunk of a key (a node id, a session, an index), or "" for an empty key.
pub fn last_chunk(key: &str) -> &str {
    key.rsplit('/').next().unwrap_or("")
}

/// The word a `q/scene/<rev>` query uses for the highest revision the store holds.
pub const LATEST: &str = "latest";

/// Which scene revision a key names: `scene/<rev>` (always a number) or `q/scene/<rev>` (a
/// number or [`LATEST`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SceneRev {
    Latest,
    Number(u64),
}

/// A key chunk that names no scene revision.
#[derive(Debug, Error, PartialEq, Eq)]
#[error("scene revision {value:?} is neither a number nor {LATEST:?}")]
pub struct BadSceneRev {
    pub value: String,
}

impl SceneRev {
    /// Reads a key chunk: [`LATEST`], or a revision in plain decimal (no sign, no leading
    /// zero), so that one revision has exactly one key.
    pub fn parse(chunk: &str) -> Result<Self, BadSceneRev> {
        if chunk == LATEST {
            return Ok(Self::Latest);
        }
        let canonical = chunk.bytes().all(|b| b.is_ascii_digit())
            && !(chunk.len() > 1 && chunk.starts_with('0'));
        match chunk.parse::<u64>() {
            Ok(n) if canonical => Ok(Self::Number(n)),
            _ => Err(BadSceneRev {
                value: chunk.to_owned(),
            }),
        }
    }
}

impl std::fmt::Display for SceneRev {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Latest => f.write_str(LATEST),
            Self::Number(n) => write!(f, "{n}"),
        }
    }
}

/// Node roles, as they appear in `alive/<role>/<node>` and `stats/<role>/<node>`.
pub mod role {
    pub const SAMPLER: &str = "sampler";
    pub const STORE: &str = "store";
    pub const QUERY: &str = "query";
    pub const REVERSE: &str = "reverse";
    pub const CLIENT: &str = "client";
}

/// Key builder for one space.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Keys {
    prefix: String,
}

impl Keys {
    pub fn new(space: &str) -> Result<Self, BadIdentifier> {
        check_identifier("space", space)?;
        Ok(Self {
            prefix: format!("mwb/{space}"),
        })
    }

    /// `mwb/<space>`
    pub fn prefix(&self) -> &str {
        &self.prefix
    }
    /// Everything in the space (recorders).
    pub fn all(&self) -> String {
        format!("{}/**", self.prefix)
    }
    /// Where a client publishes scene revision `revision` (`Scene`); the store keeps every one.
    pub fn scene(&self, revision: u64) -> String {
        format!("{}/scene/{revision}", self.prefix)
    }
    /// Every scene revision (what the store subscribes to).
    pub fn scenes(&self) -> String {
        format!("{}/scene/*", self.prefix)
    }
    /// A scene revision the store holds, or its latest: `q/scene/<rev>`, `q/scene/latest`.
    pub fn scene_query(&self, rev: SceneRev) -> String {
        format!("{}/q/scene/{rev}", self.prefix)
    }
    /// What the store declares for [`scene_query`](Self::scene_query).
    pub fn scene_queries(&self) -> String {
        format!("{}/q/scene/*", self.prefix)
    }
    pub fn job(&self, job: &str) -> String {
        format!("{}/job/{job}", self.prefix)
    }
    /// Every job announcement (not their states: `*` matches one chunk).
    pub fn jobs(&self) -> String {
        format!("{}/job/*", self.prefix)
    }
    pub fn job_state(&self, job: &str) -> String {
        format!("{}/job/{job}/state", self.prefix)
    }
    pub fn job_states(&self) -> String {
        format!("{}/job/*/state", self.prefix)
    }
    /// What store shard `index` holds of a job (`ShardCount`): every shard publishes it, the
    /// authority sums them into the job's state.
    pub fn job_shard(&self, job: &str, index: u32) -> String {
        format!("{}/job/{job}/shard/{index}", self.prefix)
    }
    /// Every shard's count of every job (what the authority subscribes to).
    pub fn job_shards(&self) -> String {
        format!("{}/job/*/shard/*", self.prefix)
    }
    pub fn segment(&self, job: &str, node: &str, counter: u64, seq: u32) -> String {
        format!("{}/seg/{job}/{node}/{counter}/{seq}", self.prefix)
    }
    pub fn segments(&self) -> String {
        format!("{}/seg/**", self.prefix)
    }
    pub fn done(&self, job: &str, node: &str, counter: u64) -> String {
        format!("{}/done/{job}/{node}/{counter}", self.prefix)
    }
    pub fn dones(&self) -> String {
        format!("{}/done/**", self.prefix)
    }
    /// World fetch by dense store index.
    pub fn world(&self, index: u32) -> String {
        format!("{}/q/world/{index}", self.prefix)
    }
    pub fn worlds(&self) -> String {
        format!("{}/q/world/*", self.prefix)
    }
    /// One store shard's browsing queryable for one session (node-query → shard).
    pub fn shard_browse(&self, node: &str, session: &str) -> String {
        format!("{}/q/browse/{node}/{session}", self.prefix)
    }
    /// What a shard declares: every session addressed to it.
    pub fn shard_browse_all(&self, node: &str) -> String {
        format!("{}/q/browse/{node}/*", self.prefix)
    }
    /// Every shard's queryable for one session (node-query's fan-out).
    pub fn shards_browse(&self, session: &str) -> String {
        format!("{}/q/browse/*/{session}", self.prefix)
    }
    /// node-query's browsing API for one session (viewer, `mwb query`).
    pub fn browse(&self, session: &str) -> String {
        format!("{}/browse/{session}", self.prefix)
    }
    /// Where node-query publishes each edit it applied in a session (`EditRecord`, JSON).
    pub fn browse_edits(&self, session: &str) -> String {
        format!("{}/browse/{session}/edit", self.prefix)
    }
    /// What node-query declares.
    pub fn browse_all(&self) -> String {
        format!("{}/browse/*", self.prefix)
    }
    /// The browsing index's paths (store shards' queryable; `PathsRequest` → one `PathBatch`
    /// per shard), for drawing worlds as they arrive.
    pub fn paths(&self) -> String {
        format!("{}/q/paths", self.prefix)
    }
    /// A job the store holds worlds of, open or closed (its scene, for clients that draw or
    /// export its worlds after it closed).
    pub fn held_job(&self, job: &str) -> String {
        format!("{}/q/job/{job}", self.prefix)
    }
    /// What the store declares for [`held_job`](Self::held_job).
    pub fn held_jobs(&self) -> String {
        format!("{}/q/job/*", self.prefix)
    }
    /// Store statistics query.
    pub fn store_stats(&self) -> String {
        format!("{}/q/stats", self.prefix)
    }
    pub fn alive(&self, role: &str, node: &str) -> String {
        format!("{}/alive/{role}/{node}", self.prefix)
    }
    pub fn alive_all(&self) -> String {
        format!("{}/alive/**", self.prefix)
    }
    pub fn alive_role(&self, role: &str) -> String {
        format!("{}/alive/{role}/*", self.prefix)
    }
    pub fn stats(&self, role: &str, node: &str) -> String {
        format!("{}/stats/{role}/{node}", self.prefix)
    }
    pub fn stats_all(&self) -> String {
        format!("{}/stats/**", self.prefix)
    }

    /// The chunks after the prefix, if `key` belongs to this space.
    pub fn split<'k>(&self, key: &'k str) -> Option<Vec<&'k str>> {
        key.strip_prefix(self.prefix.as_str())?
            .strip_prefix('/')
            .map(|rest| rest.split('/').collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identifiers() {
        assert!(check_identifier("job", "tower-1.a_b").is_ok());
        for bad in ["", "a/b", "a*", "$x", "a b", &"x".repeat(65)] {
            assert!(check_identifier("job", bad).is_err(), "{bad}");
        }
        assert!(Keys::new("a/b").is_err());
    }

    #[test]
    fn keys_split_back() {
        let k = Keys::new("demo").unwrap_or_else(|e| panic!("{e}"));
        let seg = k.segment("j1", "n1", 7, 2);
        assert_eq!(seg, "mwb/demo/seg/j1/n1/7/2");
        assert_eq!(k.split(&seg), Some(vec!["seg", "j1", "n1", "7", "2"]));
        assert_eq!(k.split("mwb/other/seg/x"), None);
        assert_eq!(k.job_state("j"), "mwb/demo/job/j/state");
        assert_eq!(k.job_shard("j", 1), "mwb/demo/job/j/shard/1");
        assert_eq!(
            k.split(&k.job_shard("j", 1)),
            Some(vec!["job", "j", "shard", "1"])
        );
        assert_eq!(k.job_shards(), "mwb/demo/job/*/shard/*");
    }

    #[test]
    fn scene_keys() {
        let k = Keys::new("demo").unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(k.scene(3), "mwb/demo/scene/3");
        assert_eq!(k.scenes(), "mwb/demo/scene/*");
        assert_eq!(k.scene_query(SceneRev::Number(12)), "mwb/demo/q/scene/12");
        assert_eq!(k.scene_query(SceneRev::Latest), "mwb/demo/q/scene/latest");
        assert_eq!(k.scene_queries(), "mwb/demo/q/scene/*");
        // A query key reads back as the revision it was built from.
        for rev in [
            SceneRev::Latest,
            SceneRev::Number(0),
            SceneRev::Number(u64::MAX),
        ] {
            assert_eq!(SceneRev::parse(last_chunk(&k.scene_query(rev))), Ok(rev));
        }
        assert_eq!(
            SceneRev::parse(last_chunk(&k.scene(7))),
            Ok(SceneRev::Number(7))
        );
    }

    #[test]
    fn scene_revisions_have_one_spelling() {
        for bad in [
            "",
            "*",
            "**",
            "03",
            "+3",
            "-1",
            "3.0",
            "Latest",
            "18446744073709551616",
        ] {
            let e = SceneRev::parse(bad).err();
            assert_eq!(
                e.as_ref().map(ToString::to_string),
                Some(format!(
                    "scene revision {bad:?} is neither a number nor \"latest\""
                )),
                "{bad}"
            );
        }
    }
}
