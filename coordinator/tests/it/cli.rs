//! The real `coordinator` binary, run in a temporary directory (issue 2's commands).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use crate::support;

fn coordinator(dir: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_coordinator")).args(args).current_dir(dir).output().expect("runs")
}

fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn repo(rel: &str) -> String {
    let p: PathBuf = [env!("CARGO_MANIFEST_DIR"), "..", rel].iter().collect();
    p.canonicalize().unwrap().display().to_string()
}

/// A numpy v1.0 `<f8` file of `(N, 6)` rows, written by hand.
fn write_npy(path: &Path, rows: &[[f64; 6]]) {
    let mut header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({}, 6), }}", rows.len());
    header.push_str(&" ".repeat((64 - (11 + header.len()) % 64) % 64));
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend((header.len() as u16).to_le_bytes());
    out.extend(header.as_bytes());
    out.extend(rows.iter().flatten().flat_map(|v| v.to_le_bytes()));
    std::fs::write(path, out).unwrap();
}

/// A clockwise circle of radius `r` and width `w` with `n` segments.
fn circle_rows(r: f64, w: f64, n: usize) -> Vec<[f64; 6]> {
    (0..=n)
        .map(|i| {
            let a = -std::f64::consts::TAU * (i % n) as f64 / n as f64;
            let (c, s) = (a.cos(), a.sin());
            [r * c, r * s, (r - w / 2.0) * c, (r - w / 2.0) * s, (r + w / 2.0) * c, (r + w / 2.0) * s]
        })
        .collect()
}

#[test]
fn tracks_list_shows_every_world_with_its_figures() {
    let dir = tempfile::tempdir().unwrap();
    let o = coordinator(dir.path(), &["tracks", "list"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(lines.len(), 20, "header + 19 worlds:\n{out}");
    let base = lines.iter().find(|l| l.starts_with("reinvent_base ")).unwrap();
    let cols: Vec<&str> = base.split_whitespace().collect();
    assert_eq!(cols, ["reinvent_base", "17.709", "0.762", "ccw", "asphalt"]);
    assert!(out.contains("reinvent_wood") && out.contains("wood"));
    assert!(out.lines().any(|l| l.starts_with("Straight_track") && l.contains("open")));
    let j = coordinator(dir.path(), &["tracks", "list", "--json"]);
    let v: serde_json::Value = serde_json::from_slice(&j.stdout).unwrap();
    assert_eq!(v.as_array().unwrap().len(), 19);
}

#[test]
fn tracks_show_prints_figures_and_draws_a_png() {
    let dir = tempfile::tempdir().unwrap();
    let o = coordinator(dir.path(), &["tracks", "show", "reInvent2019_track", "--png", "t.png"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("length       23.118 m"), "{out}");
    assert!(out.contains("repeated     rows [39]"), "{out}");
    assert!(out.contains("waypoints    154"), "the repeated row is dropped as DeepRacer drops it: {out}");
    let png = std::fs::read(dir.path().join("t.png")).unwrap();
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    assert!(png.len() > 10_000);
    let bad = coordinator(dir.path(), &["tracks", "show", "no_such_world"]);
    assert!(!bad.status.success());
    assert!(stderr(&bad).contains("no built-in world named 'no_such_world'"), "{}", stderr(&bad));
}

/// Issue 34: `tracks generate` writes a track that imports and drives, and refuses what cannot
/// close.
#[test]
fn tracks_generate_writes_a_track_that_imports_and_drives_and_refuses_what_cannot_close() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let args = ["tracks", "generate", "--seed", "4", "--length", "24", "--out", "g.npy", "--png", "g.png"];
    let o = coordinator(d, &args);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("width        min 1.070 m, mean 1.070 m, max 1.070 m"), "{}", stdout(&o));
    let bytes = std::fs::read(d.join("g.npy")).unwrap();
    assert!(std::fs::metadata(d.join("g.png")).unwrap().len() > 1000);
    // A valid DeepRacer file, the same bytes for the same seed, driven in both directions.
    let i = coordinator(d, &["tracks", "import", "g.npy"]);
    assert!(i.status.success() && stdout(&i).contains("closed       yes (loop)"), "{}{}", stdout(&i), stderr(&i));
    assert!(coordinator(d, &args).status.success());
    assert_eq!(std::fs::read(d.join("g.npy")).unwrap(), bytes);
    for extra in [&[][..], &["--reversed"][..]] {
        let drive = coordinator(d, &[&["drive", "--track", "g.npy", "--laps", "1"][..], extra].concat());
        assert!(stdout(&drive).contains("1 of 1 laps completed"), "{extra:?}: {}{}", stdout(&drive), stderr(&drive));
    }
    // By name, everywhere a world is taken: generated:N is the track of seed N.
    let drive = coordinator(d, &["drive", "--track", "generated:4", "--laps", "1"]);
    assert!(stdout(&drive).contains("1 of 1 laps completed"), "{}{}", stdout(&drive), stderr(&drive));
    // numpy reads it as DeepRacer's tracks are read: rows of centre, inner and outer x, y.
    let check = "import numpy as np\nt = np.load('g.npy')\nassert t.shape[1] == 6 and t.shape[0] > 50, t.shape\n\
                 w = np.linalg.norm(t[:, 2:4] - t[:, 4:6], axis=1)\nassert np.allclose(w, 1.07, atol=1e-6), w\n\
                 assert np.allclose(t[0], t[-1]), 'a loop'\nprint('ok')";
    let o = Command::new(crate::support::python("numpy")).args(["-c", check]).current_dir(d).output().unwrap();
    assert!(stdout(&o).contains("ok"), "{}{}", stdout(&o), stderr(&o));
    // A loop too short for turns the car can take at that width: refused, nothing written.
    let e = coordinator(d, &["tracks", "generate", "--seed", "1", "--length", "5", "--width", "1.5", "--out", "x.npy"]);
    assert!(!e.status.success() && stderr(&e).contains("cannot close with turns the car can take"), "{}", stderr(&e));
    assert!(!d.join("x.npy").exists());
}

/// Issue 34: `tracks raceline` laps faster than the centre and writes what NumPy and Python read.
#[test]
fn tracks_raceline_laps_faster_than_the_centre_and_writes_what_numpy_and_python_read() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let lap = |out: &str, name: &str| -> f64 {
        let line = out.lines().find(|l| l.starts_with(name)).unwrap_or_else(|| panic!("{name}: {out}"));
        let at = line.find(" s a lap").unwrap_or_else(|| panic!("{line}"));
        line[..at].rsplit(' ').next().unwrap().parse().unwrap()
    };
    // A built-in world both ways round, and on a surface of less grip.
    let mut times = Vec::new();
    for args in [&["reinvent_base"][..], &["reinvent_base", "--reversed"], &["reinvent_base", "--surface", "wood"]] {
        let o = coordinator(d, &[&["tracks", "raceline"][..], args, &["--out", "rl"]].concat());
        assert!(o.status.success(), "{args:?}: {}", stderr(&o));
        let out = stdout(&o);
        let (line, centre) = (lap(&out, "racing line"), lap(&out, "centre line"));
        assert!(line < 0.95 * centre, "{args:?}: {line} s against {centre} s\n{out}");
        times.push(line);
    }
    assert!(times[2] > times[0] * 1.1, "less grip, a slower lap: {times:?}");
    // The files: numpy reads the line, CPython runs the list a reward function pastes in.
    let py = crate::support::python("numpy");
    let check = "import numpy as np\nxy = np.load('rl.npy')\nexec(open('rl.py').read())\n\
                 assert xy.shape[1] == 2 and xy.shape[0] == len(racing_track) > 20, (xy.shape, len(racing_track))\n\
                 assert all(len(p) == 4 and 0.1 < p[2] <= 4.0 for p in racing_track)\n\
                 assert np.allclose(xy, [p[:2] for p in racing_track], atol=1e-4)\nprint('ok')";
    let o = Command::new(py).args(["-c", check]).current_dir(d).output().unwrap();
    assert!(stdout(&o).contains("ok"), "{}{}", stdout(&o), stderr(&o));
    assert!(std::fs::metadata(d.join("rl.png")).unwrap().len() > 1000);
    // The action space the line proposes, as DeepRacer's model_metadata.json.
    let meta = policy::ModelMetadata::load(&d.join("rl.model_metadata.json")).unwrap();
    let policy::ActionSpace::Discrete(actions) = &meta.action_space else { panic!("{:?}", meta.action_space) };
    assert_eq!(actions.len(), 7, "{actions:?}");
    // A road narrower than the margins: refused with the row.
    let e = coordinator(d, &["tracks", "raceline", "reinvent_base", "--margin", "0.5"]);
    assert!(!e.status.success() && stderr(&e).contains("no line keeps 0.500 m from both borders"), "{}", stderr(&e));
}

/// Issue 34: `reward export` writes builtins that validate to the builtins' rewards.
#[test]
fn reward_export_writes_builtins_that_validate_to_the_builtins_rewards() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let summary = |o: &Output| -> String {
        assert!(o.status.success(), "{}{}", stdout(o), stderr(o));
        stdout(o).lines().filter(|l| l.contains("mean reward") || l.contains(" calls: ")).collect::<Vec<_>>().join("\n")
    };
    for (name, world) in [("race_line", "reinvent_wood"), ("center_line", "reinvent_base")] {
        let file = format!("{name}.py");
        let e = coordinator(d, &["reward", "export", &format!("builtin:{name}"), "--world", world, "--out", &file]);
        assert!(e.status.success(), "{}", stderr(&e));
        for reversed in [&[][..], &["--reversed"][..]] {
            let check = |r: &str| {
                summary(&coordinator(d, &[&["reward", "validate", r, "--track", world][..], reversed].concat()))
            };
            let (builtin, python) = (check(&format!("builtin:{name}")), check(&file));
            assert_eq!(builtin, python, "{name} {reversed:?}");
            assert!(builtin.contains("900 calls"), "{builtin}");
        }
    }
    let e = coordinator(d, &["reward", "export", "builtin:fastest", "--out", "x.py"]);
    assert!(!e.status.success() && stderr(&e).contains("builtin:fastest: not a built-in reward"), "{}", stderr(&e));
    assert!(!d.join("x.py").exists());
}

#[test]
fn tracks_import_measures_a_users_file_and_refuses_a_broken_one() {
    let dir = tempfile::tempdir().unwrap();
    let (r, w, n) = (2.5, 0.9, 90);
    write_npy(&dir.path().join("my_circle.npy"), &circle_rows(r, w, n));
    let o = coordinator(dir.path(), &["tracks", "import", "my_circle.npy"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    let want = 2.0 * n as f64 * r * (std::f64::consts::PI / n as f64).sin();
    assert!(out.contains(&format!("length       {want:.3} m")), "{want}\n{out}");
    assert!(out.contains("width        min 0.900 m, mean 0.900 m, max 0.900 m"), "{out}");
    assert!(out.contains("direction    cw"), "{out}");
    // A shipped file, imported like a user's.
    let o = coordinator(dir.path(), &["tracks", "import", &repo("tracks/data/Bowtie_track.npy")]);
    assert!(stdout(&o).contains("length       17.428 m"), "{}", stdout(&o));
    // A user's file can be driven on.
    let d = coordinator(dir.path(), &["drive", "--track", "my_circle.npy", "--laps", "1"]);
    assert!(d.status.success() && stdout(&d).contains("1 of 1 laps completed"), "{}{}", stdout(&d), stderr(&d));
    // Broken: a NaN in row 3.
    let mut rows = circle_rows(r, w, n);
    rows[3][1] = f64::NAN;
    write_npy(&dir.path().join("broken.npy"), &rows);
    let b = coordinator(dir.path(), &["tracks", "import", "broken.npy"]);
    assert!(!b.status.success());
    assert!(stderr(&b).contains("broken.npy: row 3 column 1 (center_y) is NaN"), "{}", stderr(&b));
}

/// Issue 51: `reward validate` passes DeepRacer's samples and tells every fault of a broken
/// file on its line.
#[test]
fn reward_validate_passes_deepracers_samples_and_fails_broken_files() {
    let dir = tempfile::tempdir().unwrap();
    for f in
        ["follow_center_line.py", "stay_inside_two_borders.py", "prevent_zig_zag.py", "point_in_the_right_direction.py"]
    {
        let o = coordinator(dir.path(), &["reward", "validate", &repo(&format!("examples/rewards/{f}"))]);
        assert!(o.status.success(), "{f}: {}{}", stdout(&o), stderr(&o));
        assert!(stdout(&o).contains("PASSED") && stdout(&o).contains("min "), "{}", stdout(&o));
    }
    // Each failure on its line (file:line: error: …), as editors read compilers' messages.
    for (f, want) in [
        ("raises_key_error.py", ":3: error: KeyError: 'distance_from_centre'"),
        ("nan_off_track.py", "returned NaN"),
        ("returns_string.py", "(str)"),
        ("too_large.py", "[-1e5, 1e5]"),
        ("syntax_error.py", ":1: error: SyntaxError"),
        ("no_function.py", "error: the file defines no reward_function(params)"),
    ] {
        let o = coordinator(dir.path(), &["reward", "validate", &repo(&format!("tests/data/rewards/{f}"))]);
        assert_eq!(o.status.code(), Some(1), "{f}");
        assert!(stdout(&o).contains("FAILED") && stdout(&o).contains(want), "{f}: {}", stdout(&o));
    }
    // Every finding, not the first: two faults of the calls and an undefined name, each on
    // its line; DeepRacer's refusals are warnings, and a file with only those passes.
    let faults = dir.path().join("faults.py");
    std::fs::write(
        &faults,
        "import os\ndef reward_function(params):\n    if params['is_offtrack']:\n        return params['no_such_key']\n    if params['progress'] > 50:\n        return 1 / 0\n    return 1.0 if params['speed'] < LIMIT else 0.5\n",
    )
    .unwrap();
    let o = coordinator(dir.path(), &["reward", "validate", "faults.py"]);
    let out = stdout(&o);
    assert_eq!(o.status.code(), Some(1), "{out}");
    for want in [
        "faults.py:1: warning: import of os",
        "faults.py:7: error: undefined name 'LIMIT'",
        "FAILED: 1 error, 1 warning",
    ] {
        assert!(out.contains(want), "{want}: {out}");
    }
    std::fs::write(
        &faults,
        "import os\ndef reward_function(params):\n    if params['is_offtrack']:\n        return params['no_such_key']\n    if params['progress'] > 50:\n        return 1 / 0\n    return 1.0\n",
    )
    .unwrap();
    let o = coordinator(dir.path(), &["reward", "validate", "faults.py"]);
    let out = stdout(&o);
    for want in [
        "faults.py:1: warning: import of os",
        "faults.py:4: error: KeyError: 'no_such_key'",
        "faults.py:6: error: ZeroDivisionError: division by zero",
        "FAILED: 2 errors, 1 warning",
        "the first failed call:",
    ] {
        assert!(out.contains(want), "{want}: {out}");
    }
    // The same as one JSON object, what the console's editor marks.
    let o = coordinator(dir.path(), &["reward", "validate", "faults.py", "--json"]);
    let v: serde_json::Value =
        serde_json::from_str(stdout(&o).trim()).unwrap_or_else(|e| panic!("{e}: {}", stdout(&o)));
    assert_eq!(o.status.code(), Some(1));
    assert_eq!(v["ok"], false);
    let lines =
        |k: &str| -> Vec<u64> { v[k].as_array().unwrap().iter().map(|e| e["line"].as_u64().unwrap()).collect() };
    assert_eq!((lines("errors"), lines("warnings")), (vec![4, 6], vec![1]), "{v}");
    assert!(v["rewards"]["calls"].as_u64().unwrap() > 0, "{v}");
    std::fs::write(&faults, "import os\ndef reward_function(params):\n    return 1.0\n").unwrap();
    let o = coordinator(dir.path(), &["reward", "validate", "faults.py"]);
    let out = stdout(&o);
    assert!(o.status.success() && out.contains("PASSED, with 1 warning"), "{out}");
    // issue 31: the object-avoidance sample reads objects_*: validated in a race with boxes
    // it passes; in a time trial (no objects, as DeepRacer would run it) it fails naming why.
    let oa = repo("examples/rewards/object_avoidance.py");
    let o = coordinator(dir.path(), &["reward", "validate", &oa, "--obstacles", "3"]);
    assert!(o.status.success() && stdout(&o).contains("PASSED"), "{}{}", stdout(&o), stderr(&o));
    let o = coordinator(dir.path(), &["reward", "validate", &oa]);
    assert!(o.status.code() == Some(1) && stdout(&o).contains("IndexError"), "{}", stdout(&o));
    // A reward that never returns is stopped at its time limit, naming the file,
    // the step and the line where it was stuck.
    let o = coordinator(
        dir.path(),
        &["reward", "validate", &repo("tests/data/rewards/never_returns.py"), "--time-limit", "0.3"],
    );
    assert_eq!(o.status.code(), Some(1));
    let out = stdout(&o);
    for want in [
        "never_returns.py",
        "did not return within the time limit of 300ms at step",
        "RewardTimeLimit",
        "never_returns.py\", line",
    ] {
        assert!(out.contains(want), "{want}: {out}");
    }
    // A model_metadata.json's discrete actions feed the sampled states.
    std::fs::write(
        dir.path().join("model_metadata.json"),
        r#"{"action_space":[{"steering_angle":-20,"speed":1},{"steering_angle":20,"speed":1}],"sensor":["FRONT_FACING_CAMERA"],"version":"5"}"#,
    )
    .unwrap();
    let o = coordinator(
        dir.path(),
        &[
            "reward",
            "validate",
            &repo("examples/rewards/prevent_zig_zag.py"),
            "--model-metadata",
            "model_metadata.json",
            "--track",
            "Oval_track",
        ],
    );
    assert!(o.status.success(), "{}", stdout(&o));
    assert!(stdout(&o).contains("max 0.8000"), "steering 20 > 15 is penalised: {}", stdout(&o));
}

#[test]
fn drive_prints_each_lap_and_writes_a_simtrace() {
    let dir = tempfile::tempdir().unwrap();
    let o = coordinator(
        dir.path(),
        &[
            "drive",
            "--track",
            "reinvent_base",
            "--laps",
            "2",
            "--reward",
            &repo("examples/rewards/follow_center_line.py"),
            "--simtrace",
            "trace.csv",
            "--png",
            "lap.png",
        ],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    let laps: Vec<&str> = out.lines().filter(|l| l.starts_with("lap ")).collect();
    assert_eq!(laps.len(), 2, "{out}");
    for l in laps {
        assert!(l.contains("lap_complete") && l.contains("progress  100.0 %") && l.contains("off-track  0"), "{l}");
    }
    assert!(out.contains("2 of 2 laps completed"));
    let trace = std::fs::read_to_string(dir.path().join("trace.csv")).unwrap();
    let mut lines = trace.lines();
    assert_eq!(lines.next().unwrap().split(',').count(), 19);
    let first: Vec<&str> = lines.next().unwrap().split(',').collect();
    assert_eq!((first[0], first[1], first[8], first[9], first[15]), ("0", "1.0", "0.0", "False", "prepare"));
    assert!(trace.lines().filter(|l| l.contains(",lap_complete,")).count() == 2);
    assert!(dir.path().join("lap.png").exists());
}

#[test]
fn drive_races_against_the_clock() {
    let dir = tempfile::tempdir().unwrap();
    let o = coordinator(dir.path(), &["drive", "--time-limit", "30"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    let laps = out.lines().filter(|l| l.starts_with("race lap ")).count();
    assert!(laps >= 2, "{out}");
    assert!(out.contains("time_up") && out.contains(&format!("{laps} laps in the timed race")), "{out}");
}

#[test]
fn drive_refuses_a_bad_override_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let o = coordinator(dir.path(), &["drive", "--set", "noise.steerin_deg=0"]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("steerin_deg"), "{}", stderr(&o));
}

/// Issue 29: every binary prints the one exit code table and keeps to it.
#[test]
fn every_binary_prints_the_one_exit_code_table_and_keeps_to_it() {
    // (binary, a runtime failure's arguments): usage errors exit 2, runtime failures 1, and
    // each `--help` ends with the same table.
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing").display().to_string();
    let table: [(&str, Vec<&str>); 4] = [
        ("coordinator", vec!["evaluate", &missing]),
        ("learner", vec!["bench", "--network", "NO_SUCH_NETWORK", "--seconds", "0.1"]),
        ("sim-agent", vec!["handling", "--config", &missing]),
        ("deploy", vec!["--model-dir", &missing, "--trust", &missing]),
    ];
    for (name, failing) in table {
        let bin = support::bin(name);
        let help = Command::new(&bin).arg("--help").output().unwrap();
        assert!(help.status.success(), "{name} --help");
        let text = stdout(&help);
        assert!(text.contains("Exit codes") && text.contains("2  usage"), "{name} --help:\n{text}");
        let usage = Command::new(&bin).arg("--no-such-flag").current_dir(dir.path()).output().unwrap();
        assert_eq!(usage.status.code(), Some(2), "{name} --no-such-flag: {}", stderr(&usage));
        let failed = Command::new(&bin).args(&failing).current_dir(dir.path()).output().unwrap();
        assert_eq!(failed.status.code(), Some(1), "{name} {failing:?}: {}{}", stdout(&failed), stderr(&failed));
        assert!(stderr(&failed).contains("error: "), "{name}: {}", stderr(&failed));
    }
}
