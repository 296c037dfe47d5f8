//! `learner bench` (the real binary) measures the training step and its GEMM
//! ceiling in rounds taken in turn, and reports the step's reach as the median of the rounds'
//! ratios with their range. Nothing here asserts a speed: only that the figures are there
//! and hang together.

use std::process::Command;

/// Issue 8: the bench reports the step's reach as the median of rounds taken in turn.
#[test]
fn the_bench_reports_the_steps_reach_as_the_median_of_rounds_taken_in_turn() {
    let o = Command::new(env!("CARGO_BIN_EXE_learner"))
        .args(["bench", "--network", "MLP", "--seconds", "0.2", "--threads", "1"])
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout).to_string();
    assert!(o.status.success(), "{out}\n{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.contains("medians of 5 rounds taken in turn"), "{out}");
    let row = out.lines().find(|l| l.contains("in the step's shapes (the ceiling)")).expect("the ceiling's row");
    // "… reaches M %: the median of the rounds' ratios, LO-HI %)"
    let number = |s: &str| s.trim().parse::<f64>().unwrap_or_else(|_| panic!("a number in {row:?}: {s:?}"));
    let after = row.split("reaches ").nth(1).expect("the reach");
    let m = number(after.split(" %").next().unwrap());
    let range = after.split("ratios, ").nth(1).expect("the range").split(" %").next().unwrap();
    let (lo, hi) = range.split_once('-').expect("LO-HI");
    let (lo, hi) = (number(lo), number(hi));
    assert!(lo > 0.0 && lo <= m && m <= hi, "{row}");
}
