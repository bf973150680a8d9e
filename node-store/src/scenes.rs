//! Scene revisions (pure): every revision of a space's scene the store has been given, by
//! number, never overwritten.
//!
//! Clients publish an edited scene on `scene/<rev>` with the next number (latest + 1) and then
//! ask `q/scene/<rev>` whether the store holds *their* scene under it: two clients that picked
//! the same number race, the first offer is kept, and the loser sees another scene and retries
//! with the next number. A job carries its scene, so revisions also come back from jobs (and
//! with them from the store's journal).
//!
//! ```
//! use mwb_proto::v1::Scene;
//! use mwb_store::scenes::{Offered, SceneRefusal, SceneRevisions};
//!
//! let scene = |revision: u64, toml: &str| Scene {
//!     revision,
//!     name: "tower".into(),
//!     toml: toml.into(),
//!     content_hash: mwb_core::content_hash(toml),
//! };
//! let mut revs = SceneRevisions::default();
//! assert_eq!(revs.offer(scene(1, "a = 1")), Ok(Offered::New));
//! assert_eq!(revs.offer(scene(1, "a = 1")), Ok(Offered::Same));
//! assert!(matches!(
//!     revs.offer(scene(1, "a = 2")),
//!     Err(SceneRefusal::Conflict { revision: 1, .. })
//! ));
//! assert_eq!(revs.offer(scene(2, "a = 2")), Ok(Offered::New));
//! assert_eq!(revs.latest().map(|s| s.toml.as_str()), Some("a = 2"));
//! assert_eq!(revs.get(1).map(|s| s.toml.as_str()), Some("a = 1"));
//! ```

use mwb_core::keys::SceneRev;
use mwb_proto::v1::{Message, Scene};
use std::collections::BTreeMap;

/// What an accepted offer did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Offered {
    /// A revision not held before: kept.
    New,
    /// The revision is held with this text (a repeated put, a job of that revision); the
    /// scene held is kept as it is (its name too).
    Same,
}

/// Why a scene is not kept.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SceneRefusal {
    #[error("scene revision: 0 is not a revision (they start at 1)")]
    RevisionZero,
    #[error(
        "scene revision {revision}: content_hash {claimed:016x} is not the hash of its toml \
         ({actual:016x})"
    )]
    WrongHash {
        revision: u64,
        claimed: u64,
        actual: u64,
    },
    /// The first scene of a revision stays; a different one under the same number is refused.
    #[error(
        "scene revision {revision}: already held with other text (held content_hash \
         {held_hash:016x}, offered {offered_hash:016x}); the first is kept"
    )]
    Conflict {
        revision: u64,
        held_hash: u64,
        offered_hash: u64,
    },
}

/// Why a put on `scene/<rev>` carries no scene.
#[derive(Debug, thiserror::Error)]
pub enum ScenePutError {
    #[error("scene put on {key}: payload is not a Scene")]
    Decode {
        key: String,
        #[source]
        source: prost::DecodeError,
    },
    #[error("scene put on {key}: the key's revision {value:?} is not a number")]
    Key { key: String, value: String },
    #[error(
        "scene put on {key}: the key names revision {key_revision}, the scene's revision is {revision}"
    )]
    Mismatch {
        key: String,
        key_revision: u64,
        revision: u64,
    },
}

/// The scene of a put on `key` (`…/scene/<rev>`), if its payload decodes and its revision is the
/// key's (a plain decimal number; `latest` is for queries only). The content is checked by
/// [`SceneRevisions::offer`].
pub fn scene_from_put(key: &str, payload: &[u8]) -> Result<Scene, ScenePutError> {
    let chunk = mwb_core::keys::last_chunk(key);
    let Ok(SceneRev::Number(key_revision)) = SceneRev::parse(chunk) else {
        return Err(ScenePutError::Key {
            key: key.to_owned(),
            value: chunk.to_owned(),
        });
    };
    let scene = Scene::decode(payload).map_err(|source| ScenePutError::Decode {
        key: key.to_owned(),
        source,
    })?;
    if scene.revision != key_revision {
        return Err(ScenePutError::Mismatch {
            key: key.to_owned(),
            key_revision,
            revision: scene.revision,
        });
    }
    Ok(scene)
}

/// Every scene revision held, by number. Nothing is ever replaced or removed.
#[derive(Debug, Clone, Default)]
pub struct SceneRevisions {
    by_revision: BTreeMap<u64, Scene>,
}

impl SceneRevisions {
    /// Keeps `scene` under its revision unless the revision is 0, its `content_hash` is not
    /// [`mwb_core::content_hash`] of its `toml`, or the revision is held with another text
    /// (the texts compared, not only their hashes; a name is not content).
    pub fn offer(&mut self, scene: Scene) -> Result<Offered, SceneRefusal> {
        if scene.revision == 0 {
            return Err(SceneRefusal::RevisionZero);
        }
        let actual = mwb_core::content_hash(&scene.toml);
        if scene.content_hash != actual {
            return Err(SceneRefusal::WrongHash {
                revision: scene.revision,
                claimed: scene.content_hash,
                actual,
            });
        }
        match self.by_revision.get(&scene.revision) {
            Some(held) if held.toml == scene.toml => Ok(Offered::Same),
            Some(held) => Err(SceneRefusal::Conflict {
                revision: scene.revision,
                held_hash: held.content_hash,
                offered_hash: scene.content_hash,
            }),
            None => {
                self.by_revision.insert(scene.revision, scene);
                Ok(Offered::New)
            }
        }
    }

    /// Revision `revision`, if held.
    pub fn get(&self, revision: u64) -> Option<&Scene> {
        self.by_revision.get(&revision)
    }

    /// The highest revision held (revisions a job brought may leave gaps below it).
    pub fn latest(&self) -> Option<&Scene> {
        self.by_revision.values().next_back()
    }

    /// What a `q/scene/<rev>` query names.
    pub fn at(&self, rev: SceneRev) -> Option<&Scene> {
        match rev {
            SceneRev::Latest => self.latest(),
            SceneRev::Number(n) => self.get(n),
        }
    }

    /// Revisions held.
    pub fn len(&self) -> usize {
        self.by_revision.len()
    }

    pub fn is_empty(&self) -> bool {
        self.by_revision.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(revision: u64, toml: &str) -> Scene {
        Scene {
            revision,
            name: "tower".into(),
            toml: toml.into(),
            content_hash: mwb_core::content_hash(toml),
        }
    }

    #[test]
    fn every_revision_is_kept_and_the_highest_is_latest() {
        let mut revs = SceneRevisions::default();
        assert!(revs.is_empty() && revs.latest().is_none());
        for (rev, text) in [(2, "b = 2"), (1, "a = 1"), (5, "e = 5")] {
            assert_eq!(revs.offer(scene(rev, text)), Ok(Offered::New), "{rev}");
        }
        assert_eq!(revs.len(), 3);
        assert_eq!(revs.get(1), Some(&scene(1, "a = 1")));
        assert_eq!(revs.get(2), Some(&scene(2, "b = 2")));
        assert_eq!(revs.get(3), None, "a gap stays a gap");
        assert_eq!(revs.latest(), Some(&scene(5, "e = 5")));
        assert_eq!(revs.at(SceneRev::Latest), revs.latest());
        assert_eq!(revs.at(SceneRev::Number(2)), revs.get(2));
        assert_eq!(revs.at(SceneRev::Number(4)), None);
    }

    #[test]
    fn the_same_scene_again_is_accepted_and_changes_nothing() {
        let mut revs = SceneRevisions::default();
        assert_eq!(revs.offer(scene(1, "a = 1")), Ok(Offered::New));
        assert_eq!(revs.offer(scene(1, "a = 1")), Ok(Offered::Same));
        assert_eq!(revs.len(), 1);
    }

    #[test]
    fn a_different_scene_under_a_held_revision_is_refused_and_the_first_stays() {
        let mut revs = SceneRevisions::default();
        let first = scene(1, "a = 1");
        assert_eq!(revs.offer(first.clone()), Ok(Offered::New));
        let other = scene(1, "a = 2");
        let e = revs.offer(other.clone());
        assert_eq!(
            e,
            Err(SceneRefusal::Conflict {
                revision: 1,
                held_hash: first.content_hash,
                offered_hash: other.content_hash,
            })
        );
        let message = e.err().map(|e| e.to_string()).unwrap_or_default();
        assert!(
            message.contains(&format!("{:016x}", first.content_hash))
                && message.contains(&format!("{:016x}", other.content_hash)),
            "{message}"
        );
        // The same text under another name is the same revision; the first name stays.
        let renamed = Scene {
            name: "renamed".into(),
            ..first.clone()
        };
        assert_eq!(revs.offer(renamed), Ok(Offered::Same));
        assert_eq!(revs.get(1), Some(&first));
        assert_eq!(revs.len(), 1);
    }

    #[test]
    fn revision_zero_and_a_wrong_hash_are_refused_naming_the_field() {
        let mut revs = SceneRevisions::default();
        let e = revs.offer(scene(0, "a = 1"));
        assert_eq!(e, Err(SceneRefusal::RevisionZero));
        assert!(format!("{}", SceneRefusal::RevisionZero).contains("revision"));
        let wrong = Scene {
            content_hash: 0x1234,
            ..scene(3, "a = 1")
        };
        let e = revs.offer(wrong);
        let message = e.as_ref().err().map(|e| e.to_string()).unwrap_or_default();
        assert!(
            matches!(
                e,
                Err(SceneRefusal::WrongHash {
                    revision: 3,
                    claimed: 0x1234,
                    ..
                })
            ),
            "{e:?}"
        );
        assert!(
            message.contains("content_hash 0000000000001234"),
            "{message}"
        );
        assert!(revs.is_empty());
    }

    #[test]
    fn a_put_is_read_only_under_its_own_revision() {
        let s = scene(4, "a = 1");
        let bytes = s.encode_to_vec();
        let got = scene_from_put("mwb/x/scene/4", &bytes);
        assert_eq!(got.ok(), Some(s));
        for key in ["mwb/x/scene/5", "mwb/x/scene/04"] {
            assert!(scene_from_put(key, &bytes).is_err(), "{key}");
        }
        assert!(matches!(
            scene_from_put("mwb/x/scene/5", &bytes),
            Err(ScenePutError::Mismatch {
                key_revision: 5,
                revision: 4,
                ..
            })
        ));
        assert!(matches!(
            scene_from_put("mwb/x/scene/latest", &bytes),
            Err(ScenePutError::Key { .. })
        ));
        assert!(matches!(
            scene_from_put("mwb/x/scene/4", &[0x0a, 0xff]),
            Err(ScenePutError::Decode { .. })
        ));
    }
}
