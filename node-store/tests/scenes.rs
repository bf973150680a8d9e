//! Scene revisions in the store over a real zenoh session (peer, no scouting): revisions put on
//! `scene/<rev>` are served on `q/scene/<rev>` and `q/scene/latest` byte for byte; a second,
//! different scene under a held revision, garbage, a wrong hash and a key that is not the
//! scene's revision are dropped and counted; a job's scene is a revision too, and comes back
//! from the journal; an unknown revision gets no answer; only the authority shard answers.

mod common;

use common::{ask, close, put, session, until};
use mwb_core::keys::{Keys, SceneRev};
use mwb_proto::v1::{Job, Message, Scene};
use mwb_store::{ShardSpec, StoreConfig, StoreHandle};
use std::path::Path;
use std::time::Duration;

const SPACE: &str = "scenetest";
/// Long enough for a store on the same session to answer; what a test waits for "no answer".
const SHORT: Duration = Duration::from_millis(500);

fn keys() -> Keys {
    Keys::new(SPACE).unwrap_or_else(|e| panic!("{e}"))
}

fn scene(revision: u64, toml: &str) -> Scene {
    Scene {
        revision,
        name: format!("edit-{revision}"),
        toml: toml.into(),
        content_hash: mwb_core::content_hash(toml),
    }
}

async fn store(s: &zenoh::Session, journal: Option<&Path>, shard: ShardSpec) -> StoreHandle {
    common::start_store(
        s,
        StoreConfig {
            space: SPACE.into(),
            journal: journal.map(Path::to_owned),
            shard,
            ..Default::default()
        },
    )
    .await
}

async fn put_scene(s: &zenoh::Session, scene: &Scene) {
    put(s, keys().scene(scene.revision), scene.encode_to_vec()).await;
}

/// The answers to `q/scene/<rev>`.
async fn ask_scene(s: &zenoh::Session, rev: SceneRev) -> Vec<Result<Vec<u8>, String>> {
    ask(s, keys().scene_query(rev), Duration::from_secs(3)).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn revisions_are_served_by_number_and_the_latest_byte_for_byte() {
    let s = session().await;
    let st = store(&s, None, ShardSpec::default()).await;
    let (one, two) = (scene(1, "a = 1\n"), scene(2, "a = 2\n"));
    put_scene(&s, &one).await;
    put_scene(&s, &two).await;
    until("two revisions", || st.scene_count() == 2).await;

    assert_eq!(
        ask_scene(&s, SceneRev::Latest).await,
        vec![Ok(two.encode_to_vec())]
    );
    assert_eq!(
        ask_scene(&s, SceneRev::Number(1)).await,
        vec![Ok(one.encode_to_vec())]
    );
    assert_eq!(
        ask_scene(&s, SceneRev::Number(2)).await,
        vec![Ok(two.encode_to_vec())]
    );
    assert_eq!(st.stats().malformed, 0);
    st.stop();
    close(s).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_different_scene_under_a_held_revision_is_refused_and_counted_the_first_stays() {
    let s = session().await;
    let st = store(&s, None, ShardSpec::default()).await;
    let first = scene(1, "mine = true\n");
    put_scene(&s, &first).await;
    until("revision 1", || st.scene_count() == 1).await;
    // Another client that picked the same number loses the race.
    put_scene(&s, &scene(1, "theirs = true\n")).await;
    until("the conflict to be counted", || st.stats().malformed == 1).await;
    // The same scene again is no conflict (a repeated put).
    put_scene(&s, &first).await;
    let next = scene(2, "theirs = true\n");
    put_scene(&s, &next).await;
    until("revision 2", || st.scene_count() == 2).await;
    assert_eq!(st.stats().malformed, 1);
    assert_eq!(
        ask_scene(&s, SceneRev::Number(1)).await,
        vec![Ok(first.encode_to_vec())]
    );
    assert_eq!(st.scene(SceneRev::Latest), Some(next));
    st.stop();
    close(s).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn garbage_a_wrong_hash_and_a_key_that_is_not_the_revision_are_counted() {
    let s = session().await;
    let st = store(&s, None, ShardSpec::default()).await;
    let k = keys();
    // Not a Scene.
    put(&s, k.scene(5), vec![0x0a, 0xff, 0xff]).await;
    // A content_hash that is not the toml's.
    let wrong = Scene {
        content_hash: 0xdead_beef,
        ..scene(6, "a = 6\n")
    };
    put_scene(&s, &wrong).await;
    // Revision 7 put on scene/8, and on a key that is not a number.
    put(&s, k.scene(8), scene(7, "a = 7\n").encode_to_vec()).await;
    put(
        &s,
        format!("{}/scene/latest", k.prefix()),
        scene(7, "a = 7\n").encode_to_vec(),
    )
    .await;
    // Revision 0, under its own key.
    put_scene(&s, &scene(0, "a = 0\n")).await;
    // Applied in order after the others: once it is held, all of them were seen.
    put_scene(&s, &scene(9, "a = 9\n")).await;
    until("revision 9", || st.scene_count() == 1).await;
    assert_eq!(st.stats().malformed, 5, "{:?}", st.stats());
    for rev in [0, 5, 6, 7, 8] {
        assert_eq!(st.scene(SceneRev::Number(rev)), None, "{rev}");
    }
    st.stop();
    close(s).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_jobs_scene_and_a_put_scene_come_back_from_the_journal() {
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let journal = dir.path().join("journal");
    let k = keys();
    let three = scene(3, "a = 3\n");
    let job = Job {
        id: "edited".into(),
        revision: 1,
        target_worlds: 4,
        scene: Some(three.clone()),
        ..Default::default()
    };
    let s = session().await;
    let st = store(&s, Some(&journal), ShardSpec::default()).await;
    put(&s, k.job(&job.id), job.encode_to_vec()).await;
    until("the job", || st.job_state("edited").is_some()).await;
    assert_eq!(
        ask_scene(&s, SceneRev::Number(3)).await,
        vec![Ok(three.encode_to_vec())]
    );
    // A revision only put, carried by no job, is journaled too.
    let four = scene(4, "a = 4\n");
    put_scene(&s, &four).await;
    until("revision 4", || st.scene_count() == 2).await;
    // The job, its state and the put scene reach the journal.
    until("the journal's commit", || {
        st.journal_counters().is_some_and(|c| c.messages >= 3)
    })
    .await;
    st.stop();
    close(s).await;

    let s = session().await;
    let st = store(&s, Some(&journal), ShardSpec::default()).await;
    assert_eq!(
        ask_scene(&s, SceneRev::Number(3)).await,
        vec![Ok(three.encode_to_vec())]
    );
    for rev in [SceneRev::Number(4), SceneRev::Latest] {
        assert_eq!(
            ask_scene(&s, rev).await,
            vec![Ok(four.encode_to_vec())],
            "{rev}"
        );
    }
    assert_eq!(st.scene_count(), 2);
    st.stop();
    close(s).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unknown_revision_gets_no_answer_and_a_key_that_names_none_an_error() {
    let s = session().await;
    let st = store(&s, None, ShardSpec::default()).await;
    // Nothing held: not even a latest.
    assert_eq!(
        ask(&s, keys().scene_query(SceneRev::Latest), SHORT).await,
        vec![]
    );
    put_scene(&s, &scene(1, "a = 1\n")).await;
    until("revision 1", || st.scene_count() == 1).await;
    assert_eq!(
        ask(&s, keys().scene_query(SceneRev::Number(2)), SHORT).await,
        vec![]
    );
    let answers = ask(&s, format!("{}/q/scene/newest", keys().prefix()), SHORT).await;
    assert_eq!(
        answers,
        vec![Err(
            "scene revision \"newest\" is neither a number nor \"latest\"".to_owned()
        )]
    );
    st.stop();
    close(s).await;
}

/// Scene revisions are job-level: only shard 0 keeps and serves them, so `latest` has one
/// answer.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn only_the_authority_shard_keeps_and_serves_revisions() {
    let s = session().await;
    let authority = store(&s, None, ShardSpec { index: 0, count: 2 }).await;
    let other = store(&s, None, ShardSpec { index: 1, count: 2 }).await;
    let one = scene(1, "a = 1\n");
    put_scene(&s, &one).await;
    until("revision 1", || authority.scene_count() == 1).await;
    assert_eq!(
        ask_scene(&s, SceneRev::Latest).await,
        vec![Ok(one.encode_to_vec())]
    );
    assert_eq!(other.scene_count(), 0);
    authority.stop();
    other.stop();
    close(s).await;
}
