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
    let opts = DemoOptions {
        scene: "tumble".into(),
        worlds: 12,
        samplers: 2,
        memory_cap_bytes: 256 << 20,
        show_progress: false,
        motion: Default::default(),
        stay: false,
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
}
