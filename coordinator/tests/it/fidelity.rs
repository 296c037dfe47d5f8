//! The fidelity check. A DeepRacer reward function records the `params` it is
//! given while `coordinator drive` laps every shipped track, both ways round; an independent
//! implementation in Python with shapely (`scripts/fidelity_check.py`, the way DeepRacer's
//! simapp computes them) recomputes every geometric param from the recorded positions and
//! must agree to 1e-9. Drift in the track geometry, the waypoints, the wheels or the
//! progress rule fails here. See docs/simulator.md.

use std::path::{Path, PathBuf};
use std::process::Command;

use crate::support::python;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap().to_path_buf()
}

/// A DeepRacer reward function that appends each call's params to a JSON-lines file.
const RECORDER: &str = r#"
import json, os
_out = open(os.environ["PARAMS_DUMP"], "a")

def reward_function(params):
    _out.write(json.dumps(params) + "\n")
    _out.flush()
    return 1.0
"#;

/// Drive, record, check; the check's last line.
fn check(dir: &Path, track: &str, reversed: bool, extra: &[&str]) -> String {
    let dump = dir.join(format!("{track}-{reversed}.jsonl"));
    let mut args = vec!["drive", "--track", track, "--reward", "recorder.py"];
    if reversed {
        args.push("--reversed");
    }
    args.extend(extra);
    let o = Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .current_dir(dir)
        .args(&args)
        .env("PARAMS_DUMP", &dump)
        .output()
        .unwrap();
    assert!(o.status.success(), "{track}: {}", String::from_utf8_lossy(&o.stderr));
    let mut cmd = Command::new(python("shapely"));
    cmd.arg(repo().join("scripts/fidelity_check.py")).arg(repo().join(format!("tracks/data/{track}.npy"))).arg(&dump);
    if reversed {
        cmd.arg("--reversed");
    }
    let c = cmd.output().unwrap();
    let out = String::from_utf8_lossy(&c.stdout).to_string();
    assert!(
        c.status.success(),
        "{track} reversed={reversed}: shapely disagrees:\n{out}{}",
        String::from_utf8_lossy(&c.stderr)
    );
    out.lines().last().unwrap_or_default().to_string()
}

/// Issue 12: params of driven laps agree with Shapely on every shipped track.
#[test]
fn params_of_driven_laps_agree_with_shapely_on_every_shipped_track() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("recorder.py"), RECORDER).unwrap();
    let tracks: Vec<String> = std::fs::read_dir(repo().join("tracks/data"))
        .unwrap()
        .filter_map(|e| e.unwrap().file_name().to_str()?.strip_suffix(".npy").map(str::to_string))
        .collect();
    assert_eq!(tracks.len(), 19);
    for track in &tracks {
        for reversed in [false, true] {
            let last = check(dir.path(), track, reversed, &["--laps", "1"]);
            assert!(last.starts_with("OK: "), "{track}: {last}");
            let steps: usize = last[4..].split(' ').next().unwrap().parse().unwrap();
            assert!(steps > 30, "{track}: a lap has more steps than {steps}");
        }
    }
    // Three laps at up to 4 m/s: lap boundaries (progress back to 0) in the record too.
    let last = check(dir.path(), "reInvent2019_track", false, &["--laps", "3", "--max-speed", "4", "--seed", "3"]);
    assert!(last.starts_with("OK: "), "{last}");
}
