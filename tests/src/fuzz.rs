//! The fuzz targets: one function per decoder or file parser that takes outside input, each
//! fed arbitrary bytes; it must return (a value or an error), never panic, hang or allocate
//! without bound. `fuzz/` runs them under libFuzzer (`cargo fuzz`, through `coordinator bench
//! fuzz`); the suite replays their kept corpus and any crash they found
//! (`tests/tests/it/fuzz_corpus.rs`). [`seeds`] gives each target valid inputs to
//! start from.

use protocol::exchange::{self as ex, JobView};
use protocol::{Actions, decode, encode};
use std::path::{Path, PathBuf};

/// Every target's name (its folder under `fuzz/corpus/` and its `fuzz/fuzz_targets/` file).
pub const TARGETS: [&str; 13] = [
    "protobuf",
    "cdr",
    "npy",
    "model_metadata",
    "hyperparameters",
    "job_toml",
    "car_toml",
    "sim_config",
    "safetensors",
    "tf_graph",
    "model_archive",
    "signature",
    "tf_checkpoint",
];

/// Run `target` on `data`; false for a name that is not a target.
pub fn run(target: &str, data: &[u8]) -> bool {
    match target {
        "protobuf" => protobuf(data),
        "cdr" => cdr(data),
        "npy" => npy(data),
        "model_metadata" => model_metadata(data),
        "hyperparameters" => hyperparameters(data),
        "job_toml" => job_toml(data),
        "car_toml" => car_toml(data),
        "sim_config" => sim_config(data),
        "safetensors" => safetensors(data),
        "tf_graph" => tf_graph(data),
        "model_archive" => model_archive(data),
        "signature" => signature(data),
        "tf_checkpoint" => tf_checkpoint(data),
        _ => return false,
    }
    true
}

/// The repository's root (the track files and example configurations the seeds are made of).
pub fn repo(p: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(p)
}

fn text(data: &[u8]) -> Option<&str> {
    std::str::from_utf8(data).ok()
}

/// Every message the roles receive, decoded from `data`, and what decodes checked against a
/// job as its receiver does.
pub fn protobuf(data: &[u8]) {
    let worlds = vec!["reinvent_wood".to_string()];
    let view = JobView { job_id: "job1", obs_size: 3, worlds: &worlds, actions: Actions::Discrete(4) };
    let _ = decode::<protocol::AgentInfo>(data);
    let _ = decode::<protocol::Assignment>(data);
    let _ = decode::<protocol::AssignmentTable>(data);
    let _ = decode::<protocol::LearnerStatus>(data);
    let _ = decode::<protocol::JobRequest>(data);
    let _ = decode::<protocol::JobReply>(data);
    let _ = decode::<protocol::AgentReport>(data);
    let _ = decode::<protocol::TeamJoin>(data);
    let _ = decode::<protocol::TeamMemory>(data);
    let _ = decode::<protocol::CarStatus>(data);
    let _ = decode::<protocol::CarControl>(data);
    let _ = decode::<protocol::CarAssign>(data);
    let _ = decode::<protocol::JobPromote>(data);
    if let Ok(m) = decode::<protocol::ExperienceBatch>(data) {
        let _ = ex::experience_from_wire(m, &view, "a1");
    }
    if let Ok(m) = decode::<protocol::CameraFrame>(data) {
        let _ = ex::frame_from_wire(m, "job1", "a1");
    }
    if let Ok(m) = decode::<protocol::Credit>(data) {
        let _ = ex::credit_from_wire(m, "job1");
    }
    if let Ok(m) = decode::<protocol::EvalRequest>(data) {
        let _ = ex::eval_request_from_wire(m, &view, "a1");
    }
    if let Ok(m) = decode::<protocol::EvalReport>(data) {
        let _ = ex::eval_report_from_wire(m, &view, "a1");
    }
    if let Ok(m) = decode::<protocol::PolicyUpdate>(data) {
        if let Ok(parts) = ex::policy_parts(&m) {
            let _ = parts.decode(Path::new("fuzz"));
        }
        let _ = ex::policy_from_wire(m, &view);
    }
    if let Ok(m) = decode::<protocol::TeamPlan>(data) {
        let _ = ex::team_plan_from_wire(m, &view);
    }
    if let Ok(m) = decode::<protocol::GradShare>(data) {
        let _ = ex::share_from_wire(m, "job1", "l1");
    }
    if let Ok(m) = decode::<protocol::Job>(data) {
        let _ = protocol::job::check(&m, "job1");
    }
    let _ = protocol::job::decode_record(data);
}

/// The car's ROS 2 messages (CDR): camera frames and servo commands, both layouts.
pub fn cdr(data: &[u8]) {
    use protocol::ros::{self, Layout};
    for layout in [Layout::Community, Layout::Aws] {
        let _ = ros::decode_sensor(data, layout);
        let _ = ros::decode_servo(data, layout);
    }
}

/// A track's `.npy` file, and its rows' checks.
pub fn npy(data: &[u8]) {
    if let Ok(rows) = tracks::parse_track_npy(data, "fuzz.npy") {
        let _ = tracks::npy::validate_rows(&rows);
    }
}

/// DeepRacer's `model_metadata.json`.
pub fn model_metadata(data: &[u8]) {
    if let Some(t) = text(data) {
        let _ = policy::ModelMetadata::parse(t, "model_metadata.json");
    }
}

/// DeepRacer's `hyperparameters.json`.
pub fn hyperparameters(data: &[u8]) {
    if let Some(t) = text(data) {
        let _ = learner::hyperparams::Hyperparameters::parse(t, "hyperparameters.json");
    }
}

/// A job spec (TOML); the files it names are looked for in the repository's root.
pub fn job_toml(data: &[u8]) {
    if let Some(t) = text(data) {
        let _ = coordinator::jobspec::parse(t, &repo("."), "job.toml", "fuzz");
    }
}

/// The car's `car.toml`.
pub fn car_toml(data: &[u8]) {
    if let Some(t) = text(data) {
        let _ = policy::car::CarConfig::parse(t, "car.toml");
    }
}

/// The simulator's configuration (TOML).
pub fn sim_config(data: &[u8]) {
    if let Some(t) = text(data) {
        let _ = toml::from_str::<sim_agent::SimConfig>(t);
    }
}

/// A small state-vector model's parts (the model seeds).
pub fn model_parts() -> policy::ModelParts {
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

/// A model's `model.safetensors` whose manifest names its checksum (so that the bytes reach
/// the safetensors parser and the tensor checks).
pub fn safetensors(data: &[u8]) {
    let parts = model_parts();
    let mut manifest: serde_json::Value = serde_json::from_str(&parts.manifest_json).expect("JSON");
    manifest["weights_sha256"] = policy::folder::sha256_hex(data).into();
    let _ = policy::folder::from_parts(&parts.metadata_json, &manifest.to_string(), data, Path::new("fuzz"));
}

fn small_camera() -> policy::ModelMetadata {
    policy::ModelMetadata::default_camera()
}

/// A frozen TensorFlow graph (`model.pb`), as `import` reads a bare one.
pub fn tf_graph(data: &[u8]) {
    let _ = policy::tfgraph::read(data, &small_camera(), 1);
}

/// DeepRacer's model archive (`.tar.gz`), as `import` and the car read one.
pub fn model_archive(data: &[u8]) {
    if let Ok(p) = policy::carpkg::unpack(data, "fuzz.tar.gz") {
        let _ = p.model("fuzz.tar.gz", 1);
    }
}

/// A TensorFlow checkpoint, as `import` reads a DeepRacer model's: the input is the index's
/// length (4 bytes, little-endian), the index, then the data file; what decodes is read as
/// rl_coach's variables of a camera model.
pub fn tf_checkpoint(data: &[u8]) {
    let Some(n) = data.get(..4).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize) else { return };
    let rest = &data[4..];
    let (index, values) = rest.split_at(n.min(rest.len()));
    let Ok(ckpt) = policy::tfckpt::decode(index, values, "fuzz.index", "fuzz.data") else { return };
    // The network is built (millions of weights drawn) only for a checkpoint that has every
    // variable it needs with its shape; the names and shapes are worked out once.
    static VARIABLES: std::sync::OnceLock<Vec<(String, Vec<usize>)>> = std::sync::OnceLock::new();
    let vars = VARIABLES.get_or_init(|| policy::coach::variables(&small_camera()).unwrap_or_default());
    let fits = vars
        .iter()
        .filter(|(n, _)| !n.ends_with("_rescalers"))
        .all(|(n, s)| ckpt.get(n).is_some_and(|t| &t.shape == s));
    if fits {
        let _ = policy::coach::from_checkpoint(&ckpt, &small_camera());
    }
}

/// A checkpoint's fuzz input ([`tf_checkpoint`]): rl_coach's names of a camera model, every
/// tensor cut to a few values.
pub fn small_checkpoint() -> Vec<u8> {
    let Ok(vars) = policy::coach::variables(&small_camera()) else { return vec![] };
    let ckpt: policy::tfckpt::Checkpoint = vars
        .into_iter()
        .map(|(name, shape)| {
            let n = shape.iter().product::<usize>().min(3);
            (name, policy::tfckpt::Tensor::float(vec![n], &vec![0.5; n]))
        })
        .collect();
    let (index, data) = policy::tfckpt::encode(&ckpt);
    [(index.len() as u32).to_le_bytes().to_vec(), index, data].concat()
}

/// A model's `signature.json` and its check against a trusted key.
pub fn signature(data: &[u8]) {
    let Some(t) = text(data) else { return };
    let Ok(sig) = serde_json::from_str::<policy::signature::ModelSignature>(t) else { return };
    let mut trust = policy::signature::TrustedKeys::default();
    trust.add("fuzz", &policy::signature::Signer::from_seed([9; 32]));
    let _ = trust.verify(&sig, b"weights", "{}", "{}");
    let _ = trust.add_hex("fuzz", &sig.public_key);
}

/// DeepRacer's graph of a camera model with every tensor cut to its first few values: the
/// real graph's nodes, names and shapes in a few kilobytes (the whole one is 23 MB, too big
/// to mutate).
pub fn small_graph() -> Vec<u8> {
    use policy::tfgraph::pb::attr_value::Value;
    use prost::Message;
    let meta = small_camera();
    let model = policy::ActorCritic::new(
        &meta,
        policy::model::input_size(&meta, 0),
        &mut <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(2),
    );
    let Ok(mut g) = policy::tfgraph::graph(&model, &meta) else { return vec![] };
    for n in &mut g.node {
        for a in n.attr.values_mut() {
            if let Some(Value::Tensor(t)) = &mut a.value {
                t.tensor_content.truncate(16);
                t.float_val.truncate(4);
            }
        }
    }
    g.encode_to_vec()
}

/// Valid inputs of `target` to start from (empty for an unknown name).
pub fn seeds(target: &str) -> Vec<Vec<u8>> {
    let read = |p: &str| std::fs::read(repo(p)).unwrap_or_default();
    let texts = |v: &[&str]| v.iter().map(|s| s.as_bytes().to_vec()).collect();
    match target {
        "protobuf" => message_seeds(),
        "cdr" => cdr_seeds(),
        "npy" => vec![read("tracks/data/reinvent_base.npy"), read("tracks/data/Oval_track.npy")],
        "model_metadata" => texts(&[
            r#"{"action_space":[{"steering_angle":-30,"speed":0.6},{"steering_angle":30,"speed":1.2}],"sensor":["FRONT_FACING_CAMERA"],"neural_network":"DEEP_CONVOLUTIONAL_NETWORK_SHALLOW","training_algorithm":"clipped_ppo","action_space_type":"discrete","version":"5"}"#,
            r#"{"action_space":{"steering_angle":{"high":30,"low":-30},"speed":{"high":4,"low":0.5}},"sensor":["STATE_VECTOR"],"action_space_type":"continuous","version":"5"}"#,
            r#"{"action_space":{"steering_angle":{"high":30,"low":-30},"speed":{"high":4,"low":0.5}},"sensor":["STEREO_CAMERAS","LIDAR"],"training_algorithm":"sac","action_space_type":"continuous","version":"5"}"#,
        ]),
        "hyperparameters" => texts(&[
            r#"{"batch_size":64,"beta_entropy":0.01,"discount_factor":0.999,"e_greedy_value":0.05,"epsilon_steps":10000,"exploration_type":"categorical","loss_type":"huber","lr":0.0003,"num_episodes_between_training":20,"num_epochs":10,"stack_size":1,"term_cond_avg_score":350.0,"term_cond_max_episodes":1000}"#,
        ]),
        "job_toml" => texts(&[
            "worlds = [\"reinvent_carpet\", \"reinvent_concrete\"]\nout = \"run\"\nenvs_per_agent = 8\n[stop]\nminutes = 5\n",
            "worlds = [\"reinvent_wood\"]\nreward = \"builtin:center_line\"\n[sim]\ncontrol_hz = 15.0\nreward_time_limit = 0.5\n[schedule]\nadaptive = false\n",
        ]),
        "car_toml" => vec![read("deploy/car.toml")],
        "sim_config" => vec![read("config/default.toml")],
        "safetensors" => vec![model_parts().weights],
        "tf_graph" => vec![small_graph()],
        "model_archive" => {
            let meta = serde_json::to_vec(&serde_json::json!({
                "action_space": [{"steering_angle": -30, "speed": 1}, {"steering_angle": 30, "speed": 1}],
                "sensor": ["FRONT_FACING_CAMERA"],
                "neural_network": "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW",
                "version": "5"
            }))
            .unwrap_or_default();
            let mut tar = tar::Builder::new(Vec::new());
            for (name, bytes) in [("model_metadata.json", meta), ("agent/model.pb", small_graph())] {
                let mut h = tar::Header::new_gnu();
                h.set_size(bytes.len() as u64);
                h.set_mode(0o644);
                h.set_cksum();
                let _ = tar.append_data(&mut h, name, bytes.as_slice());
            }
            vec![tar.into_inner().unwrap_or_default()]
        }
        "tf_checkpoint" => vec![small_checkpoint()],
        "signature" => {
            let s = policy::signature::Signer::from_seed([9; 32]);
            vec![serde_json::to_vec(&s.sign(b"weights", "{}", "{}")).unwrap_or_default()]
        }
        _ => vec![],
    }
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

/// Valid encodings of every message the roles receive.
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
    let c = policy::exchange::Credit {
        version: 4,
        round: 2,
        episodes: [("a1".to_string(), 10u64)].into(),
        checks_closed_through: 3,
    };
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
        encode(&protocol::AgentReport {
            protocol_version: protocol::PROTOCOL_VERSION,
            job_id: "job1".into(),
            agent_id: "a1".into(),
            refused: vec![protocol::DropCount { reason: "signature: x".into(), count: 3 }],
            ..Default::default()
        }),
    ]
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
