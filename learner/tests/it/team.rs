//! Learners on several machines. Three `learner` processes share PPO's updates, or SAC's,
//! over Zenoh on loopback (the real binary, the real team code): the team's update is one
//! learner's on the whole batch (to float rounding), and every member ends with the leader's
//! state bit for bit (SAC's: its replay memory too, which the members took over when they
//! joined).

use std::process::Command;

/// Issue 8: three learner processes make one learner's update.
#[test]
fn three_learner_processes_make_one_learners_update() {
    let o = Command::new(env!("CARGO_BIN_EXE_learner"))
        .args([
            "bench",
            "--network",
            "MLP",
            "--learners",
            "3",
            "--check",
            "--team-only",
            "--seconds",
            "0.5",
            "--epochs",
            "1",
        ])
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout).to_string();
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(o.status.success(), "{out}\n{err}");
    assert!(out.contains("check passed"), "{out}");
    assert_eq!(out.matches("check: member bench-learner-").count(), 2, "{out}");
    assert!(out.contains("3 learner processes × 1 thread"), "{out}");
}

/// Issue 32: three learner processes make one SAC learner's updates from the leader's memory.
#[test]
fn three_learner_processes_make_one_sac_learners_updates_from_the_leaders_memory() {
    let o = Command::new(env!("CARGO_BIN_EXE_learner"))
        .args(["bench", "--network", "MLP", "--sac", "--learners", "3", "--check", "--team-only"])
        .args(["--seconds", "0.5", "--epochs", "1"])
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout).to_string();
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(o.status.success(), "{out}\n{err}");
    assert!(out.contains("whole SAC updates") && out.contains("replay memory to the members"), "{out}");
    assert!(out.contains("check passed"), "{out}");
    assert_eq!(out.matches("check: member bench-learner-").count(), 2, "{out}");
}
