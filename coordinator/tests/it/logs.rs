//! A run folder's logs read by tools nobody here wrote: the DeepRacer community's
//! `deepracer-utils` (sim-trace and metrics JSON, in deepracer-for-cloud's layout) and
//! Foxglove's `mcap` reader (the run's `trace.mcap`), both from PyPI (`PADDOCK_PYTHON`).
//! Counts and values are checked against what the run itself recorded (`metrics.jsonl`,
//! `evaluations.jsonl`).

use std::path::Path;
use std::process::Command;

use crate::support::python;

const READ: &str = r#"
import json, sys, os, collections
import numpy as np
from deepracer.logs import DeepRacerLog
from deepracer.logs.metrics import TrainingMetrics
from mcap.reader import make_reader

run = sys.argv[1]
out = {}
log = DeepRacerLog(model_folder=run)
out["folder_type"] = log.fh.type.name
log.load_training_trace()
df = log.dataframe()
out["rows"] = int(len(df))
out["episodes"] = int(df["unique_episode"].nunique())
out["iterations"] = int(df["iteration"].nunique())
out["workers"] = int(df["worker"].nunique())
out["reward_sum"] = float(df["reward"].sum())
out["columns"] = list(df.columns)
ends = df[df["done"] == True]
out["done_rows"] = int(len(ends))
out["statuses"] = sorted(set(df["episode_status"]))
out["max_progress"] = float(df["progress"].max())
out["action_space"] = log.action_space() is not None
out["hyperparameters"] = log.hyperparameters()["batch_size"]

log2 = DeepRacerLog(model_folder=run)
log2.load_evaluation_trace()
ev = log2.dataframe()
out["eval_rows"] = int(len(ev))
out["eval_streams"] = int(ev["stream"].nunique())
last = ev.sort_values(["stream", "episode", "steps"]).groupby(["stream", "episode"]).tail(1)
out["eval_trials"] = int(len(last))
out["eval_final_progress"] = [float(p) for p in last["progress"]]

tm = TrainingMetrics(None, fname=os.path.join(run, "metrics", "TrainingMetrics.json"))
m = tm.metrics
out["metrics_training"] = int((m["phase"] == "training").sum())
out["metrics_evaluation"] = int((m["phase"] == "evaluation").sum())
out["metrics_reward"] = float(m[m["phase"] == "training"]["reward"].sum())

counts = collections.Counter()
schemas = {}
first_pose = None
with open(os.path.join(run, "trace.mcap"), "rb") as f:
    reader = make_reader(f)
    for schema, channel, message in reader.iter_messages():
        counts[channel.topic] += 1
        schemas[channel.topic] = schema.name
        if channel.topic == "/training/pose" and first_pose is None:
            first_pose = json.loads(message.data)
out["mcap"] = dict(counts)
out["mcap_schemas"] = schemas
out["first_pose_frame"] = first_pose["frame_id"]
print(json.dumps(out))
"#;

fn lines(path: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

/// Issue 11: deepracer-utils and MCAP read a training run.
#[test]
fn deepracer_utils_and_mcap_read_a_training_run() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let out = Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .args(["train", "--world", "reinvent_base", "--seed", "1", "--out"])
        .arg(&run)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let script = dir.path().join("read.py");
    std::fs::write(&script, READ).unwrap();
    let py = Command::new(python("deepracer-utils and mcap"))
        .arg(&script)
        .arg(&run)
        .env("AWS_DEFAULT_REGION", "us-east-1")
        .output()
        .unwrap();
    assert!(py.status.success(), "{}", String::from_utf8_lossy(&py.stderr));
    let stdout = String::from_utf8_lossy(&py.stdout);
    let got: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();

    // What the run recorded itself.
    let metrics = lines(&run.join("metrics.jsonl"));
    let evals = lines(&run.join("evaluations.jsonl"));
    let steps: u64 = metrics.iter().map(|m| m["steps"].as_u64().unwrap()).sum();
    let episodes: u64 = metrics.iter().map(|m| m["episodes"].as_u64().unwrap()).sum();
    let reward: f64 =
        metrics.iter().map(|m| m["mean_reward"].as_f64().unwrap() * m["episodes"].as_f64().unwrap()).sum();
    assert!(metrics.len() >= 2 && !evals.is_empty(), "a run with updates and evaluations");

    // deepracer-utils: a DRfC folder, one row per step trained on, one done row per episode.
    assert_eq!(got["folder_type"], "DRFC_MODEL_MULTIPLE_WORKERS", "{got}");
    assert_eq!(got["rows"].as_u64().unwrap(), steps, "{got}");
    assert_eq!(got["done_rows"].as_u64().unwrap(), episodes, "{got}");
    assert_eq!(got["episodes"].as_u64().unwrap(), episodes, "{got}");
    assert_eq!(got["iterations"].as_u64().unwrap(), metrics.len() as u64, "{got}");
    assert_eq!(got["workers"], 1);
    assert!((got["reward_sum"].as_f64().unwrap() - reward).abs() <= 1e-3 * reward.abs().max(1.0), "{got} vs {reward}");
    assert!(got["max_progress"].as_f64().unwrap() <= 100.0 + 1e-9);
    assert_eq!(got["action_space"], true, "model/model_metadata.json read");
    assert_eq!(got["hyperparameters"], 64, "ip/hyperparameters.json read");
    for s in got["statuses"].as_array().unwrap() {
        assert!(
            ["prepare", "in_progress", "off_track", "reversed", "immobilized", "lap_complete"]
                .contains(&s.as_str().unwrap()),
            "{s}"
        );
    }

    // Evaluations: one stream per evaluation per world, each trial's last row its progress.
    let trials: u64 = evals.iter().map(|e| e["trials"].as_u64().unwrap()).sum();
    assert_eq!(got["eval_streams"].as_u64().unwrap(), evals.len() as u64, "{got}");
    assert_eq!(got["eval_trials"].as_u64().unwrap(), trials, "{got}");
    // One world: an evaluation's mean progress is the mean of its trials' last rows.
    let recorded: f64 = evals.iter().map(|e| e["progress"].as_f64().unwrap() * e["trials"].as_f64().unwrap()).sum();
    let read: f64 = got["eval_final_progress"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).sum();
    assert!((read - recorded).abs() < 1e-2 * trials as f64, "{read} vs {recorded}");

    // DeepRacer's metrics JSON: every training episode, every evaluation trial.
    assert_eq!(got["metrics_training"].as_u64().unwrap(), episodes, "{got}");
    assert_eq!(got["metrics_evaluation"].as_u64().unwrap(), trials, "{got}");
    assert!(
        (got["metrics_reward"].as_f64().unwrap() - reward).abs() <= episodes as f64 * 0.5 + 1e-6,
        "rounded per episode"
    );

    // MCAP: a pose and a step message per step trained on, one figures message per update.
    let m = &got["mcap"];
    assert_eq!(m["/training/pose"].as_u64().unwrap(), steps, "{got}");
    assert_eq!(m["/training/step"].as_u64().unwrap(), steps, "{got}");
    assert_eq!(m["/learner/iteration"].as_u64().unwrap(), metrics.len() as u64, "{got}");
    assert_eq!(m["/learner/evaluation"].as_u64().unwrap(), evals.len() as u64, "{got}");
    assert_eq!(m["/track"], 1);
    assert!(m["/evaluation/pose"].as_u64().unwrap() > 0);
    assert_eq!(got["mcap_schemas"]["/training/pose"], "foxglove.PoseInFrame");
    assert_eq!(got["mcap_schemas"]["/track"], "foxglove.SceneUpdate");
    assert_eq!(got["first_pose_frame"], "track");
}

/// Fraction of a PNG's pixels that are not white.
fn inked(png: &Path) -> f64 {
    let img = image::open(png).unwrap_or_else(|e| panic!("{}: {e}", png.display())).to_rgb8();
    let ink = img.pixels().filter(|p| p.0 != [255, 255, 255]).count();
    ink as f64 / (img.width() * img.height()) as f64
}

/// Issue 11: `report` draws a run folder and refuses a folder that is not one.
#[test]
fn report_draws_a_run_folder_and_refuses_a_folder_that_is_not_one() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let coordinator = env!("CARGO_BIN_EXE_coordinator");
    let out = Command::new(coordinator)
        .args(["train", "--world", "reinvent_base", "--seed", "2", "--out"])
        .arg(&run)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let out = Command::new(coordinator).arg("report").arg(&run).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(String::from_utf8_lossy(&out.stdout).contains("index.html"));
    let report = run.join("report");
    let html = std::fs::read_to_string(report.join("index.html")).unwrap();
    for chart in
        ["reward", "progress", "evaluations", "racing-line-reinvent_base", "reward-map-reinvent_base", "actions"]
    {
        let svg = std::fs::read_to_string(report.join(format!("{chart}.svg"))).unwrap();
        assert!(svg.starts_with("<svg") && svg.contains("<text"), "{chart}.svg: an SVG with its labels");
        let ink = inked(&report.join(format!("{chart}.png")));
        assert!(ink > 0.01 && ink < 0.9, "{chart}.png: drawn, not blank or solid ({ink:.3})");
        assert!(html.contains(&format!("src=\"{chart}.svg\"")), "the page shows {chart}");
    }
    assert!(html.contains("<th>batch_size</th><td>64</td>"), "the page lists the hyperparameters");
    assert!(html.contains("best model</th><td>iteration"), "the page names the best model");

    // A folder that is not a run: a clear error naming it.
    let out = Command::new(coordinator).arg("report").arg(dir.path()).output().unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("not a run folder") && err.contains(&dir.path().display().to_string()), "{err}");
}

/// Issue 11: `train` stops at a plateau when asked and says so.
#[test]
fn train_stops_at_a_plateau_when_asked_and_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    // The state vector laps within seconds; without a lap target it would train 2 minutes.
    let out = Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .args(["train", "--world", "reinvent_base", "--seed", "3", "--target-laps", "0", "--minutes", "2"])
        .args(["--stop-on-plateau", "2", "--out"])
        .arg(&run)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}{}", String::from_utf8_lossy(&out.stderr));
    assert!(
        stdout.contains("stopped after") && stdout.contains("plateau: evaluation progress has not improved for 2"),
        "{stdout}"
    );
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("summary.json")).unwrap()).unwrap();
    assert!(summary["stop_reason"].as_str().unwrap().starts_with("plateau"), "{summary}");
    assert!(summary["seconds"].as_f64().unwrap() < 100.0, "stopped early: {summary}");
    let evals = lines(&run.join("evaluations.jsonl"));
    assert!(evals.iter().any(|e| e["trend"].as_str().unwrap().starts_with("plateau")), "recorded per evaluation");
}
