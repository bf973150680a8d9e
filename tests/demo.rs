//! `mwb demo` end to end, in process: embedded peer session on loopback, a store, two samplers.

use mwb::bus::BusArgs;
use mwb::demo::{DemoOptions, run_demo};
use std::time::Duration;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn demo_samples_and_verifies_every_world() {
    let bus = BusArgs {
        connect: vec![],
        listen: vec![],
        config: None,
        mode: None,
        space: format!("demotest{}", std::process::id()),
        multicast: false,
    };
    let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let recording = dir.path().join("demo.mcap");
    let opts = DemoOptions {
        scene: "tumble".into(),
        worlds: 12,
        samplers: 2,
        memory_cap_bytes: 256 << 20,
        show_progress: false,
        motion: Default::default(),
        stay: false,
        viewer: false,
        record: Some(recording.clone()),
    };
    let s = tokio::time::timeout(Duration::from_secs(120), run_demo(&bus, &opts))
        .await
        .unwrap_or_else(|_| panic!("demo timed out"))
        .unwrap_or_else(|e| panic!("{e:#}"));
    assert_eq!(s.worlds, 12);
    assert_eq!(s.crc_valid_worlds, 12);
    assert_eq!(s.bodies, 5);
    assert!(s.impacts_per_world > 0.0 && s.bytes_per_world > 0.0);
    assert!(s.frames_per_world > 1.0);

    // `--record`: the recording reads back whole and holds the job and every world.
    let back = mwb_record::read_recording(&recording).unwrap_or_else(|e| panic!("{e}"));
    assert!(back.error.is_none(), "{:?}", back.error);
    assert!(back.stats.complete);
    let count = |f: mwb_record::Family| back.messages.iter().filter(|m| m.family == f).count();
    assert_eq!(count(mwb_record::Family::Job), 1);
    // A sampler may finish a world after the job reached its target (the store counts it and
    // keeps 12): the recording holds every summary that was put.
    assert!(count(mwb_record::Family::Done) >= 12);
    assert!(count(mwb_record::Family::Segment) >= 12);
    assert_eq!(s.recorded_messages, Some(back.messages.len() as u64));
}
