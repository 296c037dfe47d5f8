//! What the coordinator's integration tests share: the role binaries, a free port, the tests'
//! Python, the root check, and one camera model trained from pixels.
//!
//! Training SHALLOW from pixels until it laps takes a minute or more; the tests that need such
//! a model (it learns to lap; `deploy` drives the simulated car with it) share one run
//! folder, trained on first use and kept under `target/tmp`. It is keyed by the coordinator
//! binary (its size and modification time), so a rebuilt coordinator trains afresh, and made
//! under a lock file and renamed into place whole, so a test that died half-way leaves nothing
//! another would take for a model.

use std::path::PathBuf;
use std::process::Command;

/// A role binary (`learner`, `sim-agent`, `deploy`, `coordinator`), built beside this test's
/// `coordinator` (`cargo test --workspace` and `./paddock test` build every binary).
pub fn bin(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_coordinator")).with_file_name(name)
}

/// A loopback port free now (for a role to listen on), picked as the launchers pick theirs.
pub fn free_port() -> u16 {
    coordinator::supervise::free_port().unwrap()
}

/// The tests' Python environment (`PADDOCK_PYTHON`, made by `./paddock test`), holding `what`.
pub fn python(what: &str) -> PathBuf {
    std::env::var_os("PADDOCK_PYTHON").map(PathBuf::from).unwrap_or_else(|| {
        panic!("PADDOCK_PYTHON is not set: run `./paddock test`, which makes target/pyenv with {what}")
    })
}

/// Tests that need root end in `_as_root`: `./paddock test` leaves them out without root and
/// says so; run any other way without root, they fail saying why (never a silent pass).
pub fn need_root(what: &str) {
    let root = std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with("Uid:")).map(|l| l.split_whitespace().nth(1) == Some("0")))
        .unwrap_or(false);
    assert!(root, "{what} needs root: run the tests as root, or `./paddock test`, which skips this test and says so");
}

/// The shared camera run: `coordinator train --sensor camera` on reinvent_base until two
/// versions in a row lap 3/3 and the second laps 10 of 10 in its verification (at most 15
/// minutes). Returns the run folder and what
/// `train` printed. Panics, with that output, when the training fails.
pub fn camera_run() -> (PathBuf, String) {
    let coordinator = PathBuf::from(env!("CARGO_BIN_EXE_coordinator"));
    let meta = std::fs::metadata(&coordinator).expect("the coordinator binary");
    let stamp = meta.modified().ok().and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok()).unwrap_or_default();
    let key = format!("{:x}-{:x}", meta.len(), stamp.as_nanos());
    let root = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("camera-run");
    std::fs::create_dir_all(&root).unwrap();
    let lock = std::fs::File::create(root.join("lock")).unwrap();
    lock.lock().expect("lock the camera run's folder");
    let done = root.join(&key);
    let log = done.join("train.log");
    if !log.exists() {
        // Runs for older binaries are not wanted any more.
        for e in std::fs::read_dir(&root).unwrap().flatten() {
            if e.path().is_dir() {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
        let work = root.join(format!("{key}.tmp"));
        std::fs::create_dir_all(&work).unwrap();
        let o = Command::new(&coordinator)
            .args(["train", "--sensor", "camera", "--world", "reinvent_base", "--envs", "16"])
            // Two lapping checkpoints in a row (the car in the loop drives both), the second
            // verified. With 3 epochs an update (Paddock's default) the first lapping
            // checkpoints come sooner, and the streak alone once stopped at a model that
            // lapped 1 of 3 in train_cli's race. Every version is evaluated (`train`'s
            // default).
            .args(["--minutes", "15", "--target-evals", "2"])
            .args(["--out", "run"])
            .current_dir(&work)
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&o.stdout).to_string() + &String::from_utf8_lossy(&o.stderr);
        assert!(o.status.success(), "the camera run failed:\n{text}");
        std::fs::write(work.join("train.log"), &text).unwrap();
        std::fs::rename(&work, &done).unwrap();
    }
    (done.join("run"), std::fs::read_to_string(log).unwrap())
}
