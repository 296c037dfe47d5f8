//! Every decoder and file parser, fuzzed for a bounded number of cases.
//!
//! cargo-fuzz needs a nightly toolchain; this is the stable counterpart, with `proptest`:
//! each target gets random bytes and mutations of valid inputs (bytes flipped, inserted,
//! dropped; truncated; text spliced), and must return a value or an error: never panic. The
//! test binary's allocator is `cap`'s, limited to [`HEAP_LIMIT`]: an input that makes a parser
//! allocate beyond it (a length prefix taken at its word) aborts the run. Cases per target:
//! `PADDOCK_FUZZ_CASES` (default 20 000, about two seconds here: CI's bound on time).

use cap::Cap;
use proptest::prelude::*;
use protocol::exchange::{self as ex, JobView};
use protocol::{Actions, decode, encode};
use std::alloc::System;
use std::path::Path;

#[global_allocator]
static ALLOC: Cap<System> = Cap::new(System, HEAP_LIMIT);

/// The whole test process's heap: far above what any target needs for these small inputs.
const HEAP_LIMIT: usize = 1 << 30;

fn cases() -> u32 {
    std::env::var("PADDOCK_FUZZ_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(20_000)
}

fn config() -> ProptestConfig {
    ProptestConfig { cases: cases(), failure_persistence: None, ..ProptestConfig::default() }
}

/// A mutation of one of `seeds`: flips, insertions, removals and a truncation.
fn mutated(seeds: Vec<Vec<u8>>) -> impl Strategy<Value = Vec<u8>> {
    let n = seeds.len();
    (
        0..n,
        prop::collection::vec((any::<prop::sample::Index>(), any::<u8>(), 0..3u8), 0..12),
        prop::option::of(any::<prop::sample::Index>()),
    )
        .prop_map(move |(i, edits, cut)| {
            let mut b = seeds[i].clone();
            for (at, byte, kind) in edits {
                if b.is_empty() {
                    b.push(byte);
                    continue;
                }
                let k = at.index(b.len());
                match kind {
                    0 => b[k] = byte,
                    1 => b.insert(k, byte),
                    _ => {
                        b.remove(k);
                    }
                }
            }
            if let Some(c) = cut {
                let k = c.index(b.len() + 1);
                b.truncate(k);
            }
            b
        })
}

/// Random bytes or a mutation of a seed.
fn inputs(seeds: Vec<Vec<u8>>) -> impl Strategy<Value = Vec<u8>> {
    prop_oneof![prop::collection::vec(any::<u8>(), 0..512), mutated(seeds)]
}

fn text(seeds: &[&str]) -> impl Strategy<Value = String> {
    inputs(seeds.iter().map(|s| s.as_bytes().to_vec()).collect()).prop_map(|b| String::from_utf8_lossy(&b).into_owned())
}

fn repo(p: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(p)
}

fn trajectory(world: &str, steps: usize) -> policy::Trajectory {
    policy::Trajectory {
        world: world.into(),
        env: 1,
        episode: 2,
        policy_version: 3,
        obs: vec![0.5; steps * 3],
        choices: vec![policy::Choice::Discrete(1); steps],
        logp: vec![-1.0; steps],
        values: vec![0.25; steps],
        rewards: vec![1.0; steps],
        done: true,
        progress: 40.0,
        lap_complete: false,
        track_len: 17.6,
        // The steps' sim-trace columns are decoded (and fuzzed) too.
        trace: (0..steps)
            .map(|i| policy::StepTrace {
                x: i as f64 * 0.1,
                y: 1.0,
                progress: i as f32,
                closest_waypoint: i as u32,
                status: policy::EpisodeStatus::InProgress,
                tstamp: i as f64 / 15.0,
                wall_clock: 1.8e9,
                ..Default::default()
            })
            .collect(),
    }
}

/// Valid encodings of every message the roles receive, to mutate.
fn message_seeds() -> Vec<Vec<u8>> {
    let t = trajectory("reinvent_wood", 4);
    // Grey levels: their observations travel as bytes.
    let grey = policy::Trajectory { obs: (0..12).map(|i| (i * 20) as f32).collect(), ..t.clone() };
    let e = policy::exchange::Experience {
        worker: "a1".into(),
        seq: 1,
        credit: (3, 1),
        trajectories: vec![t.clone(), grey],
        env_steps: 8,
        seconds: 0.5,
        frame: None,
    };
    let c = policy::exchange::Credit { version: 4, round: 2, episodes: [("a1".to_string(), 10u64)].into() };
    let parts = model_parts();
    vec![
        encode(&ex::experience_to_wire("job1", &e, 3)),
        encode(&ex::credit_to_wire("job1", &c)),
        encode(&ex::frame_to_wire(
            "job1",
            "a1",
            &policy::exchange::Frame {
                world: "reinvent_wood".into(),
                width: 4,
                height: 2,
                gray: vec![7; 8],
                policy_version: 2,
                step: 3,
            },
        )),
        encode(&ex::parts_to_wire("job1", 3, &parts)),
        encode(&ex::share_to_wire("job1", "l1", 9, 4, &[1.0, 2.0], &[3.0])),
        // Mostly +0.0: its factors travel sparse (a mask and the kept values).
        encode(&ex::share_to_wire(
            "job1",
            "l1",
            9,
            5,
            &[1.0],
            &[0.0, 0.0, 0.0, 4.0, 0.0, 0.0, 0.0, 0.0, 0.0, -0.0, 0.0],
        )),
        encode(&protocol::JobRequest { protocol_version: protocol::PROTOCOL_VERSION, ..Default::default() }),
        encode(&protocol::CarStatus {
            protocol_version: protocol::PROTOCOL_VERSION,
            car_id: "car".into(),
            ..Default::default()
        }),
    ]
}

/// Decode `bytes` as every message type, and check what decodes against a job.
fn every_message(bytes: &[u8]) {
    let worlds = vec!["reinvent_wood".to_string()];
    let view = JobView { job_id: "job1", obs_size: 3, worlds: &worlds, actions: Actions::Discrete(4) };
    let _ = decode::<protocol::AgentInfo>(bytes);
    let _ = decode::<protocol::Assignment>(bytes);
    let _ = decode::<protocol::AssignmentTable>(bytes);
    let _ = decode::<protocol::LearnerStatus>(bytes);
    let _ = decode::<protocol::JobRequest>(bytes);
    let _ = decode::<protocol::JobReply>(bytes);
    let _ = decode::<protocol::AgentReport>(bytes);
    let _ = decode::<protocol::TeamJoin>(bytes);
    let _ = decode::<protocol::CarStatus>(bytes);
    let _ = decode::<protocol::CarControl>(bytes);
    let _ = decode::<protocol::JobPromote>(bytes);
    if let Ok(m) = decode::<protocol::ExperienceBatch>(bytes) {
        let _ = ex::experience_from_wire(m, &view, "a1");
    }
    if let Ok(m) = decode::<protocol::CameraFrame>(bytes) {
        let _ = ex::frame_from_wire(m, "job1", "a1");
    }
    if let Ok(m) = decode::<protocol::Credit>(bytes) {
        let _ = ex::credit_from_wire(m, "job1");
    }
    if let Ok(m) = decode::<protocol::EvalRequest>(bytes) {
        let _ = ex::eval_request_from_wire(m, &view, "a1");
    }
    if let Ok(m) = decode::<protocol::EvalReport>(bytes) {
        let _ = ex::eval_report_from_wire(m, &view, "a1");
    }
    if let Ok(m) = decode::<protocol::PolicyUpdate>(bytes) {
        if let Ok(parts) = ex::policy_parts(&m) {
            let _ = parts.decode(Path::new("fuzz"));
        }
        let _ = ex::policy_from_wire(m, &view);
    }
    if let Ok(m) = decode::<protocol::TeamPlan>(bytes) {
        let _ = ex::team_plan_from_wire(m, &view);
    }
    if let Ok(m) = decode::<protocol::GradShare>(bytes) {
        let _ = ex::share_from_wire(m, "job1", "l1");
    }
    if let Ok(m) = decode::<protocol::Job>(bytes) {
        let _ = protocol::job::check(&m, "job1");
    }
}

fn cdr_seeds() -> Vec<Vec<u8>> {
    use protocol::ros::{self, CompressedImage, Header, Image, Layout, RawFrame, Servo, Time};
    let jpeg = RawFrame::Compressed(CompressedImage {
        header: Header::default(),
        format: "jpeg".into(),
        data: serde_bytes::ByteBuf::from(vec![0xff, 0xd8, 0xff, 0xd9]),
    });
    let raw = RawFrame::Raw(Image {
        header: Header::default(),
        height: 2,
        width: 2,
        encoding: "bgr8".into(),
        is_bigendian: 0,
        step: 6,
        data: serde_bytes::ByteBuf::from(vec![7u8; 12]),
    });
    let servo = Servo { angle: 0.5, throttle: -0.25 };
    vec![
        ros::encode_sensor(vec![jpeg], &[0.5, 2.0], Layout::Community),
        ros::encode_sensor(vec![raw], &[], Layout::Aws),
        ros::encode_servo(servo, Layout::Community, Time::from_secs_f64(1.5), 3, &Header::default()),
        ros::encode_servo(servo, Layout::Aws, Time::from_secs_f64(1.5), 3, &Header::default()),
    ]
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn issue_10_fuzz_protobuf_messages(bytes in inputs(message_seeds())) {
        every_message(&bytes);
    }

    #[test]
    fn issue_10_fuzz_the_cars_cdr_messages(bytes in inputs(cdr_seeds())) {
        use protocol::ros::{self, Layout};
        for layout in [Layout::Community, Layout::Aws] {
            let _ = ros::decode_sensor(&bytes, layout);
            let _ = ros::decode_servo(&bytes, layout);
        }
    }

    #[test]
    fn issue_10_fuzz_track_npy_files(bytes in inputs(vec![
        std::fs::read(repo("tracks/data/reinvent_base.npy")).unwrap(),
        std::fs::read(repo("tracks/data/Oval_track.npy")).unwrap(),
    ])) {
        if let Ok(rows) = tracks::parse_track_npy(&bytes, "fuzz.npy") {
            let _ = tracks::npy::validate_rows(&rows);
        }
    }

    #[test]
    fn issue_10_fuzz_model_metadata_json(t in text(&[
        r#"{"action_space":[{"steering_angle":-30,"speed":0.6},{"steering_angle":30,"speed":1.2}],"sensor":["FRONT_FACING_CAMERA"],"neural_network":"DEEP_CONVOLUTIONAL_NETWORK_SHALLOW","training_algorithm":"clipped_ppo","action_space_type":"discrete","version":"5"}"#,
        r#"{"action_space":{"steering_angle":{"high":30,"low":-30},"speed":{"high":4,"low":0.5}},"sensor":["STATE_VECTOR"],"action_space_type":"continuous","version":"5"}"#,
    ])) {
        let _ = policy::ModelMetadata::parse(&t, "model_metadata.json");
    }

    #[test]
    fn issue_10_fuzz_hyperparameters_json(t in text(&[
        r#"{"batch_size":64,"beta_entropy":0.01,"discount_factor":0.999,"e_greedy_value":0.05,"epsilon_steps":10000,"exploration_type":"categorical","loss_type":"huber","lr":0.0003,"num_episodes_between_training":20,"num_epochs":10,"stack_size":1,"term_cond_avg_score":350.0,"term_cond_max_episodes":1000}"#,
    ])) {
        let _ = learner::hyperparams::Hyperparameters::parse(&t, "hyperparameters.json");
    }

    #[test]
    fn issue_10_fuzz_job_toml(t in text(&[
        "worlds = [\"reinvent_carpet\", \"reinvent_concrete\"]\nout = \"run\"\nenvs_per_agent = 8\n[stop]\nminutes = 5\n",
        "worlds = [\"reinvent_wood\"]\nreward = \"builtin:center_line\"\n[sim]\ncontrol_hz = 15.0\nreward_time_limit = 0.5\n",
    ])) {
        let _ = coordinator::jobspec::parse(&t, Path::new("."), "job.toml", "fuzz");
    }

    #[test]
    fn issue_10_fuzz_car_toml(t in text(&[&std::fs::read_to_string(repo("deploy/car.toml")).unwrap()])) {
        let _ = policy::car::CarConfig::parse(&t, "car.toml");
    }

    #[test]
    fn issue_10_fuzz_sim_config_toml(t in text(&[&std::fs::read_to_string(repo("config/default.toml")).unwrap()])) {
        let _ = toml::from_str::<sim_agent::SimConfig>(&t);
    }
}

/// A small state-vector model's parts: in the model update seed and the model-folder target.
fn model_parts() -> policy::ModelParts {
    let meta = policy::ModelMetadata::default_state_vector();
    let model =
        policy::ActorCritic::new(&meta, 3, &mut <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(1));
    let manifest = policy::Manifest {
        format: "paddock-model-1".into(),
        policy_version: 3,
        parent: None,
        weights_sha256: String::new(),
        obs_size: 3,
        observation: serde_json::json!({}),
        training: serde_json::json!({}),
    };
    policy::ModelParts::new(&meta, &model, &manifest, None)
}

proptest! {
    #![proptest_config(config())]

    /// A model folder whose weights file is damaged or forged but whose manifest names its
    /// checksum (so the bytes reach the safetensors parser and the tensor checks).
    #[test]
    fn issue_10_fuzz_model_folder_weights(bytes in inputs(vec![model_parts().weights])) {
        let parts = model_parts();
        let mut manifest: serde_json::Value = serde_json::from_str(&parts.manifest_json).unwrap();
        manifest["weights_sha256"] = policy::folder::sha256_hex(&bytes).into();
        let _ = policy::folder::from_parts(&parts.metadata_json, &manifest.to_string(), &bytes, Path::new("fuzz"));
    }
}

/// The allocator's limit is real: a request beyond it fails (and the run would abort).
#[test]
fn the_heap_limit_is_in_force() {
    assert_eq!(ALLOC.limit(), HEAP_LIMIT);
    assert!(ALLOC.allocated() < HEAP_LIMIT / 4, "the fuzz targets' baseline");
    let mut v: Vec<u8> = Vec::new();
    assert!(v.try_reserve_exact(HEAP_LIMIT).is_err(), "a reservation beyond the limit is refused");
}
