//! The reverse benchmark, opt-in (release):
//! `CARGO_TARGET_DIR=/tmp/tgt-lcp cargo test --release -p mwb-reverse --test bench -- --ignored --nocapture`

use mwb_reverse::{BenchOptions, bench};

#[test]
#[ignore = "benchmark: minutes in release; run with --ignored --nocapture"]
fn reverse_bench() {
    let b = match bench(&BenchOptions::default()) {
        Ok(b) => b,
        Err(e) => panic!("{e}"),
    };
    eprintln!("{b:#?}");
    assert!(b.forward_step_us > 0.0 && b.backward_step_us > 0.0);
}
