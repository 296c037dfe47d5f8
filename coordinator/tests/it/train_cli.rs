//! `coordinator train`, `evaluate` and `clone`, run as a user would.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use crate::support;
use crate::support::need_root;

fn coordinator(dir: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_coordinator")).args(args).current_dir(dir).output().expect("runs")
}

fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

fn repo(rel: &str) -> String {
    let p: PathBuf = [env!("CARGO_MANIFEST_DIR"), "..", rel].iter().collect();
    p.canonicalize().unwrap().display().to_string()
}

/// Issue 8: `train` stops on a stop condition with its reason and an evaluated model.
#[test]
fn train_stops_on_a_stop_condition_with_its_reason_and_an_evaluated_model() {
    // Each rule is tested through a whole run in learner/tests/it/run_scripted.rs and each flag
    // against its rule in `train`'s unit tests; here one of them end to end: the reason is
    // printed and kept in summary.json, and the final model is evaluated and saved.
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let args = ["train", "--world", "reinvent_base", "--target-laps", "0", "--minutes", "2", "--max-episodes", "60"];
    let o = coordinator(d, &[&args[..], &["--out", "run"]].concat());
    let want = "60 episodes reached";
    assert!(o.status.success(), "{args:?}: {}", text(&o));
    assert!(text(&o).contains(want), "{args:?}: want {want:?}\n{}", text(&o));
    assert!(text(&o).contains("best model: "), "the final model was evaluated: {}", text(&o));
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("run/summary.json")).unwrap()).unwrap();
    assert!(summary["stop_reason"].as_str().unwrap().contains(want), "{summary}");
    assert!(d.join("run/model/model.safetensors").exists(), "{args:?}");
}

#[test]
fn train_then_evaluate_then_clone_and_resume() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let o = coordinator(d, &["train", "--world", "reinvent_base", "--minutes", "2", "--out", "run1"]);
    assert!(o.status.success(), "{}", text(&o));
    let out = text(&o);
    // The default stop: 3/3 in two evaluations in a row, then 10 of 10 in the second's
    // checkpoint's verification.
    assert!(out.contains("target laps reached and verified"), "{out}");
    assert!(out.contains("verify v") && out.contains("10/10"), "{out}");
    assert!(out.contains("evaluation progress 100.0 %"), "{out}");
    for f in [
        "model/model.safetensors",
        "model/model_metadata.json",
        "model/manifest.json",
        "checkpoints/deepracer_checkpoints.json",
        "metrics.jsonl",
        "hyperparameters.json",
        "model_metadata.json",
        "sim.toml",
        "summary.json",
    ] {
        assert!(d.join("run1").join(f).exists(), "{f} missing");
    }
    let metrics = std::fs::read_to_string(d.join("run1/metrics.jsonl")).unwrap();
    let first: serde_json::Value = serde_json::from_str(metrics.lines().next().unwrap()).unwrap();
    for k in [
        "mean_reward",
        "mean_progress",
        "episodes",
        "steps",
        "policy_loss",
        "value_loss",
        "entropy",
        "approx_kl",
        "clip_fraction",
        "explained_variance",
        "samples_per_s",
        "lr",
        "resident_mb",
    ] {
        assert!(first.get(k).is_some(), "metrics lack {k}: {first}");
    }

    let e = coordinator(d, &["evaluate", "run1/model", "--world", "reinvent_base", "--trials", "3"]);
    assert!(e.status.success(), "{}", text(&e));
    let eout = text(&e);
    assert_eq!(eout.lines().filter(|l| l.starts_with("trial ")).count(), 3, "{eout}");
    assert!(eout.contains("3 of 3 laps completed"), "{eout}");
    // One table over several worlds.
    let e = coordinator(
        d,
        &["evaluate", "run1/model", "--world", "reinvent_base", "--world", "reinvent_wood", "--trials", "2"],
    );
    assert!(e.status.success(), "{}", text(&e));
    let eout = text(&e);
    let table = eout.lines().filter(|l| l.starts_with("reinvent_base ") || l.starts_with("reinvent_wood ")).count();
    assert_eq!(table, 2, "{eout}");

    // An existing run folder is never overwritten by accident.
    let again = coordinator(d, &["train", "--minutes", "1", "--out", "run1"]);
    assert!(!again.status.success() && text(&again).contains("--resume"), "{}", text(&again));

    // Clone with a lower learning rate, then go on training from those weights.
    let c = coordinator(d, &["clone", "run1/model", "--out", "run2", "--lr", "0.0001"]);
    assert!(c.status.success(), "{}", text(&c));
    let manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("run2/model/manifest.json")).unwrap()).unwrap();
    assert!(manifest["parent"]["weights_sha256"].as_str().unwrap().len() == 64);
    let hyper: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("run2/hyperparameters.json")).unwrap()).unwrap();
    assert_eq!(hyper["lr"], 0.0001);
    let parent_version = manifest["policy_version"].as_u64().unwrap();
    let r = coordinator(d, &["train", "--world", "reinvent_wood", "--minutes", "1", "--out", "run2", "--resume"]);
    assert!(r.status.success(), "{}", text(&r));
    let resumed: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("run2/checkpoints/deepracer_checkpoints.json")).unwrap())
            .unwrap();
    assert!(resumed["last_checkpoint"]["policy_version"].as_u64().unwrap() > parent_version, "{resumed}");

    // A clone whose action space differs is refused, with the reason.
    std::fs::write(
        d.join("five.json"),
        r#"{"action_space":[{"steering_angle":-30,"speed":1},{"steering_angle":0,"speed":1},{"steering_angle":30,"speed":1}],"sensor":["STATE_VECTOR"],"neural_network":"PADDOCK_MLP","version":"5"}"#,
    )
    .unwrap();
    let bad = coordinator(d, &["clone", "run1/model", "--out", "run3", "--model-metadata", "five.json"]);
    assert!(!bad.status.success());
    assert!(text(&bad).contains("output layer would no longer match"), "{}", text(&bad));
    assert!(!d.join("run3").exists());
}

/// Issue 33: a device that is not one is refused before training.
#[test]
fn a_device_that_is_not_one_is_refused_before_training() {
    let dir = tempfile::tempdir().unwrap();
    let o = coordinator(dir.path(), &["train", "--out", "run", "--device", "cuda"]);
    assert!(
        !o.status.success() && text(&o).contains("`cuda` is not a device: expected auto, cpu or gpu"),
        "{}",
        text(&o)
    );
    assert!(!dir.path().join("run").exists(), "nothing was trained or written");
}

/// Issue 55: bf16 products are the CPU's: a run that asks for them is refused before training
/// on the GPU, and on a CPU without AVX-512 BF16.
#[test]
fn bf16_products_are_refused_where_they_cannot_be_made() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("bf16.json"), r#"{"precision": "bf16"}"#).unwrap();
    let o = coordinator(dir.path(), &["train", "--out", "run", "--hyperparameters", "bf16.json", "--device", "gpu"]);
    let want = if policy::nn::Precision::bf16_available() {
        "precision \"bf16\" is the CPU's (faer's products in bf16); the GPU's update is f32"
    } else {
        "precision \"bf16\" needs a CPU with AVX-512 BF16"
    };
    assert!(!o.status.success() && text(&o).contains(want), "{}", text(&o));
    assert!(!dir.path().join("run/checkpoints").exists(), "nothing was trained");
}

#[test]
fn train_refuses_a_raising_reward_before_training() {
    let dir = tempfile::tempdir().unwrap();
    let o = coordinator(
        dir.path(),
        &["train", "--reward", &repo("tests/data/rewards/raises_key_error.py"), "--out", "run"],
    );
    assert!(!o.status.success());
    let out = text(&o);
    assert!(out.contains("KeyError: 'distance_from_centre'") && out.contains("Traceback"), "{out}");
    assert!(!dir.path().join("run").exists(), "nothing was trained or written");
}

#[test]
fn train_reads_deepracer_files_and_rejects_bad_ones_by_key() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(
        d.join("hyperparameters.json"),
        r#"{"batch_size": 64, "lr": 0.0003, "num_epochs": 3, "learning_rate_typo": 1}"#,
    )
    .unwrap();
    let o = coordinator(d, &["train", "--hyperparameters", "hyperparameters.json", "--minutes", "1", "--out", "run"]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("unknown key 'learning_rate_typo'"), "{}", text(&o));
    std::fs::write(d.join("bad.json"), r#"{"batch_size": "sixty-four"}"#).unwrap();
    let b = coordinator(d, &["train", "--hyperparameters", "bad.json", "--out", "run_bad"]);
    assert!(!b.status.success() && text(&b).contains("bad.json: key 'batch_size'"), "{}", text(&b));
    std::fs::write(
        d.join("lidar.json"),
        r#"{"action_space":[{"steering_angle":0,"speed":1}],"sensor":["FRONT_FACING_CAMERA","DISCRETIZED_SECTOR_LIDAR"],
            "lidar_config":{"num_sectors":5},"version":"5"}"#,
    )
    .unwrap();
    let c = coordinator(d, &["train", "--model-metadata", "lidar.json", "--out", "run_cam"]);
    let out = text(&c);
    assert!(
        !c.status.success()
            && out.contains("lidar.json: field 'lidar_config.num_sectors' is 5: 64 % Number of sector (n) must be 0!"),
        "{out}"
    );
    assert!(!d.join("run_cam").exists(), "nothing was trained or written");
}

/// deepracer-for-cloud's `defaults/model_metadata_sac.json`, on the state vector.
const SAC_METADATA: &str = r#"{"action_space":{"speed":{"high":2,"low":1},"steering_angle":{"high":30,"low":-30}},
    "sensor":["STATE_VECTOR"],"neural_network":"PADDOCK_MLP","training_algorithm":"sac",
    "action_space_type":"continuous","version":"4"}"#;

/// deepracer-for-cloud's `defaults/hyperparameters.json`, unchanged.
const DRFC_HYPERPARAMETERS: &str = r#"{"batch_size": 64, "beta_entropy": 0.01, "discount_factor": 0.99,
    "e_greedy_value": 0.05, "epsilon_steps": 10000, "exploration_type": "categorical", "loss_type": "huber",
    "lr": 0.0003, "num_episodes_between_training": 20, "num_epochs": 10, "stack_size": 1,
    "term_cond_avg_score": 350.0, "term_cond_max_episodes": 1000, "sac_alpha": 0.2}"#;

fn metrics(path: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

/// Issue 32: SAC trains to laps and a resumed run goes on with its critics and memory.
#[test]
fn sac_trains_to_laps_and_a_resumed_run_goes_on_with_its_critics_and_memory() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("model_metadata_sac.json"), SAC_METADATA).unwrap();
    std::fs::write(d.join("hyperparameters.json"), DRFC_HYPERPARAMETERS).unwrap();
    let files = ["--model-metadata", "model_metadata_sac.json", "--hyperparameters", "hyperparameters.json"];
    let o = coordinator(
        d,
        &[&["train"][..], &files[..], &["--target-laps", "3", "--target-evals", "1", "--minutes", "3", "--out", "run"]]
            .concat(),
    );
    let out = text(&o);
    assert!(o.status.success() && out.contains("target laps reached"), "{out}");
    // The keys SAC does not read are named once, never silently taken.
    assert!(out.contains("num_epochs (clipped PPO's, not used by SAC)"), "{out}");
    let run = d.join("run");
    let model_meta = std::fs::read_to_string(run.join("model/model_metadata.json")).unwrap();
    assert!(model_meta.contains("\"training_algorithm\": \"sac\""), "{model_meta}");
    let first = metrics(&run.join("metrics.jsonl"));
    for m in &first {
        // Flow control: one gradient step per new transition (DeepRacer's ratio).
        let sac = &m["sac"];
        assert_eq!(m["gradient_steps"], sac["new_transitions"], "{m}");
        assert!(
            sac["q_loss"].as_f64().unwrap().is_finite() && (sac["alpha"].as_f64().unwrap() - 0.2).abs() < 1e-6,
            "{m}"
        );
    }
    let kept = first.last().unwrap()["sac"]["replay"].as_u64().unwrap();
    let last_ckpt = std::fs::read_dir(run.join("checkpoints"))
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| p.is_dir())
        .max()
        .unwrap();
    assert!(last_ckpt.join("sac.safetensors").exists(), "the critics beside the checkpoint's model");
    assert!(run.join("replay.safetensors").exists(), "the replay memory kept at the end");
    // The run stops on its verified checkpoint; an update made while that was being verified
    // has a record but no checkpoint, and the resumed run makes it again.
    let at: usize = last_ckpt.file_name().unwrap().to_str().unwrap()["ckpt_".len()..].parse().unwrap();
    assert!(at >= 1 && at <= first.len(), "checkpoint {at} of {} updates", first.len());
    // The resumed run's first update finds the whole memory the run kept at its end (the new
    // episodes on top), and trains with its critics.
    let o = coordinator(
        d,
        &[&["train"][..], &files[..], &["--resume", "--max-episodes", "20", "--minutes", "1", "--out", "run"]].concat(),
    );
    assert!(o.status.success(), "{}", text(&o));
    let resumed = metrics(&run.join("metrics.jsonl"));
    assert_eq!(resumed[..at], first[..at], "the records up to the checkpoint are kept as they were");
    assert_eq!(resumed[at]["iteration"], at as u64 + 1, "{}", resumed[at]);
    let next = &resumed[at]["sac"];
    assert_eq!(next["replay"].as_u64().unwrap(), kept + next["new_transitions"].as_u64().unwrap(), "{next}");
}

/// Issue 32: SAC with a discrete action space gets DeepRacer's error.
#[test]
fn sac_with_a_discrete_action_space_gets_deepracers_error() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(
        d.join("discrete_sac.json"),
        r#"{"action_space":[{"steering_angle":0,"speed":1}],"sensor":["STATE_VECTOR"],"training_algorithm":"sac"}"#,
    )
    .unwrap();
    let o = coordinator(d, &["train", "--model-metadata", "discrete_sac.json", "--out", "run"]);
    let out = text(&o);
    assert!(!o.status.success() && out.contains("defining SACActionSpaceConfig"), "{out}");
    assert!(!d.join("run").exists());
}

/// Issue 31: a DeepRacer-for-Cloud run.env trains its race with its custom files.
#[test]
fn a_deepracer_for_cloud_run_env_trains_its_race_with_its_custom_files() {
    // deepracer-for-cloud's layout: run.env, and custom_files/ beside it.
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::create_dir_all(d.join("exp/custom_files")).unwrap();
    std::fs::write(
        d.join("exp/run.env"),
        "DR_WORLD_NAME=reinvent_wood\nDR_RACE_TYPE=OBJECT_AVOIDANCE\nDR_OA_NUMBER_OF_OBSTACLES=2\n\
         DR_OA_RANDOMIZE_OBSTACLE_LOCATIONS=False\nDR_ENABLE_DOMAIN_RANDOMIZATION=False\n",
    )
    .unwrap();
    std::fs::copy(repo("examples/rewards/object_avoidance.py"), d.join("exp/custom_files/reward_function.py")).unwrap();
    std::fs::write(d.join("exp/custom_files/hyperparameters.json"), r#"{"batch_size": 64, "typo_key": 1}"#).unwrap();
    let o = coordinator(
        d,
        &[
            "train",
            "--run-env",
            "exp/run.env",
            "--target-laps",
            "0",
            "--max-episodes",
            "40",
            "--minutes",
            "1",
            "--out",
            "run",
        ],
    );
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("reinvent_wood") && t.contains("reward_function.py"), "the world and the reward: {t}");
    assert!(t.contains("unknown key 'typo_key'"), "custom_files/hyperparameters.json was read: {t}");
    let sim = std::fs::read_to_string(d.join("run/sim.toml")).unwrap();
    assert!(sim.contains("race_type = \"object_avoidance\"") && sim.contains("number_of_obstacles = 2"), "{sim}");
    assert!(sim.contains("randomize_obstacle_locations = false"), "{sim}");
    // Flags win over the file; a bad key in it is refused naming it.
    std::fs::write(d.join("exp/bad.env"), "DR_RACE_TYPE=DRAG_RACE\n").unwrap();
    let b = coordinator(d, &["train", "--run-env", "exp/bad.env", "--out", "run_bad"]);
    assert!(!b.status.success() && text(&b).contains("exp/bad.env: DR_RACE_TYPE is \"DRAG_RACE\""), "{}", text(&b));
}

/// Issue 5: a camera model learns to lap from pixels.
#[test]
fn a_camera_model_learns_to_lap_from_pixels() {
    // DeepRacer's SHALLOW network on 160x120 grayscale frames rendered on lavapipe, Paddock's
    // default hyperparameters; training stops at the second of two checkpoints in a row that
    // lapped 3/3, once it laps 10 of 10 in its verification. The run is the one the
    // car-in-the-loop test drives with (support::camera_run).
    let (run, log) = support::camera_run();
    assert!(log.contains("target laps reached and verified"), "{log}");
    let meta = std::fs::read_to_string(run.join("model/model_metadata.json")).unwrap();
    assert!(meta.contains("FRONT_FACING_CAMERA") && meta.contains("DEEP_CONVOLUTIONAL_NETWORK_SHALLOW"), "{meta}");
    // An independent evaluation: the model raced against its own DeepRacer archive (issue 34),
    // a trial ending at the first off-track as `evaluate`'s do.
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let model = run.join("model").display().to_string();
    let x = coordinator(d, &["export", &model, "--car", "pixels.tar.gz"]);
    assert!(x.status.success(), "{}", text(&x));
    let args = ["race", &model, "pixels.tar.gz", "--trials", "3", "--seed", "2", "--resets", "0", "--out", "race"];
    let e = coordinator(d, &args);
    let t = text(&e);
    assert!(e.status.success(), "{t}");
    let laps =
        |name: &str| t.lines().filter(|l| l.trim_start().starts_with(name) && l.contains("lap_complete")).count();
    assert!(laps("run ") >= 2, "the camera model laps in an independent evaluation too:\n{t}");
    // The archive is the same policy: the same trials, lap for lap.
    let trials = |name: &str| -> Vec<String> {
        t.lines()
            .filter(|l| l.trim_start().starts_with(name))
            .map(|l| l.trim_start()[name.len()..].trim().to_string())
            .collect()
    };
    assert_eq!(trials("run "), trials("pixels "), "{t}");
    let board: Vec<&str> = t.lines().skip_while(|l| !l.starts_with("RANK")).skip(1).take(2).collect();
    assert!(
        board.len() == 2 && board.iter().any(|l| l.contains(" run ")) && board.iter().any(|l| l.contains(" pixels ")),
        "{t}"
    );
    // The page: the leaderboard, each model's fastest lap on the track and its camera strip.
    let page = std::fs::read_to_string(d.join("race/race.html")).unwrap();
    for (i, name) in board.iter().map(|l| l.split_whitespace().nth(1).unwrap()).enumerate() {
        for (suffix, width) in [("lap", 300), ("camera", 160 * 10)] {
            let file = format!("{}-{name}-{suffix}.png", i + 1);
            assert!(page.contains(&file), "{file}: {page}");
            let img = image::open(d.join("race").join(&file)).unwrap();
            assert!(img.width() >= width, "{file}: {}", img.width());
        }
    }
    assert!(page.contains("<td>run</td>") && page.contains("<td>pixels</td>"), "{page}");
}

/// A small tmpfs, unmounted when dropped.
struct SmallDisk(PathBuf);

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.0).output();
    }
}

/// Issue 10: a full disk is reported and the last checkpoint stays whole as root.
#[test]
fn a_full_disk_is_reported_and_the_last_checkpoint_stays_whole_as_root() {
    need_root("mounting a small tmpfs");
    let dir = tempfile::tempdir().unwrap();
    let mnt = dir.path().join("small");
    std::fs::create_dir(&mnt).unwrap();
    // Room for the run's inputs and a few checkpoints of the state model, not for all of them.
    let o = Command::new("mount").args(["-t", "tmpfs", "-o", "size=800k", "tmpfs"]).arg(&mnt).output().unwrap();
    assert!(o.status.success(), "mount a small tmpfs: {}", String::from_utf8_lossy(&o.stderr));
    let _disk = SmallDisk(mnt.clone());
    let o = coordinator(
        dir.path(),
        &[
            "train",
            "--world",
            "reinvent_base",
            "--minutes",
            "0.2",
            "--target-laps",
            "0",
            "--checkpoint-seconds",
            "1",
            "--out",
            "small/run",
        ],
    );
    let t = text(&o);
    // Training went on to its stop, and said what it could not write.
    assert_eq!(o.status.code(), Some(3), "{t}");
    assert!(t.contains("stopped after") && t.contains("write(s) to the run folder failed"), "{t}");
    assert!(t.contains("No space left on device"), "{t}");
    // The checkpoint a restart resumes from is whole, and nothing half-written is left.
    let index: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(mnt.join("run/checkpoints/deepracer_checkpoints.json")).unwrap())
            .unwrap();
    let last = index["last_checkpoint"]["name"].as_str().unwrap();
    policy::folder::load(&mnt.join("run/checkpoints").join(last)).unwrap();
    for e in std::fs::read_dir(mnt.join("run/checkpoints")).unwrap().flatten() {
        assert!(!e.file_name().to_string_lossy().contains(".tmp-"), "{:?} left behind", e.path());
    }
}
