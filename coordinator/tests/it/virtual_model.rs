//! DeepRacer's whole models both ways, checked by TensorFlow itself (the car side's Python,
//! target/pyenv-car): `export --virtual-dir` gives a checkpoint `tf.train.load_checkpoint`
//! lists with rl_coach's names and shapes and whose tensors are Paddock's, bit for bit;
//! checkpoints TensorFlow writes, rl_coach's variables for each network, sensor set and
//! algorithm saved as rl_coach's saver saves them, come in through `import` with TensorFlow's
//! outputs; a model goes out, in and out again as the same bytes; the folder passes the checks
//! DRoA's import page and its handler run; and a clone of an imported model trains on with its
//! own value network.

use coordinator::virtual_model;
use policy::coach::{self, SacCritics};
use policy::{ActorCritic, Head, Manifest, ModelMetadata, TrainingAlgorithm};
use rand::{Rng, SeedableRng};
use sha2::Digest;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

fn car_python() -> PathBuf {
    std::env::var_os("PADDOCK_CAR_PYTHON").map(PathBuf::from).unwrap_or_else(|| {
        panic!("PADDOCK_CAR_PYTHON is not set: run `./paddock test`, which makes target/pyenv-car with TensorFlow")
    })
}

fn coordinator(args: &[&str], dir: &Path) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_coordinator")).args(args).current_dir(dir).output().unwrap();
    (out.status.success(), String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr))
}

fn ok(args: &[&str], dir: &Path) -> String {
    let (good, text) = coordinator(args, dir);
    assert!(good, "coordinator {args:?}: {text}");
    text
}

const DISCRETE: &str = r#"[{"steering_angle": -30, "speed": 1.0}, {"steering_angle": -10, "speed": 2.0},
    {"steering_angle": 0, "speed": 3.0}, {"steering_angle": 10, "speed": 2.0}, {"steering_angle": 30, "speed": 1.0}]"#;
const CONTINUOUS: &str = r#"{"steering_angle": {"low": -30, "high": 30}, "speed": {"low": 0.5, "high": 3.5}}"#;

/// The four models the issue names: SHALLOW discrete, DEEP continuous, stereo + LiDAR, SAC.
fn cases() -> Vec<(&'static str, ModelMetadata)> {
    let meta = |network: &str, sensors: &str, algo: &str, space: &str| {
        let kind = if space.trim_start().starts_with('[') { "discrete" } else { "continuous" };
        let text = format!(
            r#"{{"action_space": {space}, "sensor": {sensors}, "neural_network": "{network}", "training_algorithm": "{algo}", "action_space_type": "{kind}", "version": "5"}}"#
        );
        ModelMetadata::parse(&text, "case").unwrap()
    };
    vec![
        (
            "shallow_discrete",
            meta("DEEP_CONVOLUTIONAL_NETWORK_SHALLOW", r#"["FRONT_FACING_CAMERA"]"#, "clipped_ppo", DISCRETE),
        ),
        (
            "deep_continuous",
            meta("DEEP_CONVOLUTIONAL_NETWORK", r#"["FRONT_FACING_CAMERA"]"#, "clipped_ppo", CONTINUOUS),
        ),
        (
            "stereo_lidar",
            meta("DEEP_CONVOLUTIONAL_NETWORK_SHALLOW", r#"["STEREO_CAMERAS", "LIDAR"]"#, "clipped_ppo", DISCRETE),
        ),
        ("sac", meta("DEEP_CONVOLUTIONAL_NETWORK_SHALLOW", r#"["FRONT_FACING_CAMERA"]"#, "sac", CONTINUOUS)),
    ]
}

/// A model folder of random weights for `meta` (SAC's critics beside it), as a run would
/// leave one, with the run's reward function and hyperparameters beside it.
fn model_folder(run: &Path, meta: &ModelMetadata, seed: u64) -> (ActorCritic, Option<SacCritics>) {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut model = ActorCritic::new(meta, 0, &mut rng);
    if let Head::Gaussian { log_std } = &mut model.head {
        *log_std = [-0.7, 0.1];
    }
    for net in [&mut model.pi, &mut model.v] {
        for p in &mut net.params {
            *p += rng.random_range(-0.01..0.01);
        }
    }
    let manifest = Manifest {
        format: "paddock-model-1".into(),
        policy_version: 12,
        parent: None,
        weights_sha256: String::new(),
        obs_size: model.obs_size(),
        observation: serde_json::json!({"kind": "camera"}),
        training: serde_json::json!({"worlds": ["reInvent2019_track"], "iteration": 12, "env_steps": 4321,
            "hyperparameters": {"num_episodes_between_training": if meta.training_algorithm == TrainingAlgorithm::Sac { 1 } else { 20 }}}),
    };
    policy::folder::save(&run.join("model"), meta, &model, &manifest).unwrap();
    std::fs::write(run.join("model_metadata.json"), meta.to_json()).unwrap();
    std::fs::write(run.join("reward_function.py"), "def reward_function(params):\n    return 1.0\n").unwrap();
    let critics = (meta.training_algorithm == TrainingAlgorithm::Sac).then(|| {
        let embed = policy::model::sac_q_embedder(meta, 0, &mut rng);
        let w = embed.as_ref().map_or(0, |e| e.out_size());
        let c = SacCritics {
            embed,
            q1: policy::model::sac_q_head(w, &mut rng),
            q2: policy::model::sac_q_head(w, &mut rng),
        };
        std::fs::write(
            run.join("model").join(virtual_model::CRITICS_FILE),
            virtual_model::critics_bytes(&c, &model.v, 0.2f32.ln()),
        )
        .unwrap();
        c
    });
    (model, critics)
}

/// Lists a checkpoint as TensorFlow reads it: every variable's shape and the sha256 of its
/// float32 bytes.
const TF_LISTS: &str = r#"
import hashlib, json, sys, numpy as np, tensorflow as tf
out = {}
for prefix in sys.argv[1:]:
    r = tf.train.load_checkpoint(prefix)
    shapes = r.get_variable_to_shape_map()
    dtypes = r.get_variable_to_dtype_map()
    out[prefix] = {n: [list(shapes[n]), dtypes[n].name, hashlib.sha256(np.ascontiguousarray(r.get_tensor(n)).astype("<f4").tobytes()).hexdigest()] for n in shapes}
print(json.dumps(out))
"#;

/// A variable as TensorFlow lists it: shape, dtype, sha256 of its bytes.
type Listed = (Vec<usize>, String, String);

/// Issue 53: TensorFlow lists Paddock's checkpoint with rl_coach's names and shapes and
/// reads Paddock's weights bit for bit, for every network the issue names.
#[test]
fn tensorflow_reads_paddocks_checkpoint_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("list.py"), TF_LISTS).unwrap();
    let mut prefixes = Vec::new();
    let mut expected = BTreeMap::new();
    for (name, meta) in cases() {
        let run = d.join(name);
        let (model, critics) = model_folder(&run, &meta, 3);
        ok(&["export", &format!("{name}/model"), "--virtual-dir", &format!("{name}-droa")], d);
        let ckpt = d.join(format!("{name}-droa/model/12_Step-4321.ckpt"));
        assert!(policy::tfckpt::index_path(&ckpt).is_file(), "{name}: {}", ckpt.display());
        prefixes.push(ckpt.display().to_string());
        let mine = coach::to_checkpoint(&meta, &model, critics.as_ref()).unwrap();
        expected.insert(ckpt.display().to_string(), (name, mine));
    }
    let out = Command::new(car_python()).arg(d.join("list.py")).args(&prefixes).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let listed: BTreeMap<String, BTreeMap<String, Listed>> = serde_json::from_slice(&out.stdout).unwrap();
    for (prefix, (name, mine)) in &expected {
        let tf = &listed[prefix];
        let tf_names: Vec<&String> = tf.keys().collect();
        let my_names: Vec<&String> = mine.keys().collect();
        assert_eq!(tf_names, my_names, "{name}: the variables");
        for (var, t) in mine {
            let (shape, dtype, sha) = &tf[var];
            assert_eq!(shape, &t.shape, "{name}: {var}'s shape");
            assert_eq!(dtype, "float32", "{name}: {var}");
            assert_eq!(sha, &format!("{:x}", sha2::Sha256::digest(&t.bytes)), "{name}: {var}'s bytes");
        }
        // rl_coach's names: the policy under network_1 (PPO) or the policy agent (SAC).
        let policy_scope = if name == &"sac" {
            "main_level/agent/policy/online/network_0/"
        } else {
            "main_level/agent/main/online/network_1/"
        };
        assert!(mine.keys().any(|k| k.starts_with(policy_scope)), "{name}");
    }
}

/// Builds rl_coach's variables for each case (its scopes and layer names, written here from
/// rl_coach's code, not from Paddock's), random weights, runs the networks on the inputs,
/// and saves the variables as rl_coach's saver does (`tf.compat.v1.train.Saver` over the
/// trainable variables of the online networks: `.index`, `.data-00000-of-00001`, `.meta`)
/// into deepracer-for-cloud's model folder layout.
const TF_WRITES: &str = r#"
import json, os, sys, numpy as np, tensorflow as tf
tf.compat.v1.disable_eager_execution()
tf.compat.v1.disable_resource_variables()
CAMERA = {
    "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW": [("conv", 32, 8, 4), ("conv", 64, 4, 2), ("conv", 64, 3, 1)],
    "DEEP_CONVOLUTIONAL_NETWORK": [("conv", 32, 5, 2), ("conv", 32, 3, 1), ("conv", 64, 3, 2), ("conv", 64, 3, 1), ("dense", 64)],
}
MIDDLEWARE = {"DEEP_CONVOLUTIONAL_NETWORK_SHALLOW": [512], "DEEP_CONVOLUTIONAL_NETWORK": [512]}
LIDAR = [("dense", 256), ("dense", 256)]
for case in json.load(open(sys.argv[1])):
    meta = case["metadata"]
    rng = np.random.default_rng(case["seed"])
    def var(name, shape, std=None):
        fan_in = int(np.prod(shape[:-1])) if len(shape) > 1 else 1
        s = std if std is not None else (2.0 / fan_in) ** 0.5
        return tf.compat.v1.get_variable(name, initializer=(rng.standard_normal(shape) * s).astype("float32"))
    def dense(h, n, scope, act):
        with tf.compat.v1.variable_scope(scope):
            k = var("kernel", [int(h.shape[-1]), n])
            b = var("bias", [n], 0.1)
        y = tf.tensordot(h, k, [[len(h.shape) - 1], [0]]) + b
        return tf.nn.relu(y) if act else y
    def embedder(x, layers, image):
        h = x / 255.0 if image else x
        for i, l in enumerate(layers):
            if l[0] == "conv":
                with tf.compat.v1.variable_scope("Conv2d_%d" % (2 * i)):
                    k = var("kernel", [l[2], l[2], int(h.shape[-1]), l[1]])
                    b = var("bias", [l[1]], 0.1)
                h = tf.nn.relu(tf.nn.conv2d(h, k, [1, l[3], l[3], 1], "VALID") + b)
            else:
                h = dense(h, l[1], "Dense_%d" % (2 * i), True)
        return tf.reshape(h, [-1, int(np.prod(h.shape[1:]))])
    g = tf.Graph()
    with g.as_default():
        ph = {i["sensor"]: tf.compat.v1.placeholder("float32", [None] + i["shape"]) for i in case["inputs"]}
        feed = {ph[i["sensor"]]: np.fromfile(i["file"], dtype="<f4").reshape([-1] + i["shape"]) for i in case["inputs"]}
        def embedders():
            outs = []
            for s in sorted(ph):
                with tf.compat.v1.variable_scope(s):
                    if "LIDAR" in s:
                        outs.append(embedder(ph[s], LIDAR, False))
                    else:
                        outs.append(embedder(ph[s], CAMERA[meta["neural_network"]], True))
            return tf.concat(outs, 1) if len(outs) > 1 else outs[0]
        def network(scope, head, middleware=True):
            with tf.compat.v1.variable_scope(scope):
                h = embedders()
                if middleware:
                    for j, n in enumerate(MIDDLEWARE[meta["neural_network"]]):
                        h = dense(h, n, "middleware_fc_embedder/Dense_%d" % (2 * j), True)
                var("gradients_from_head_0-0_rescalers", [], 0.0)
                return head(h)
        outputs = {}
        def v_head(h):
            outputs["value"] = dense(h, 1, "v_values_head_0/output", False)
        if meta["training_algorithm"] == "clipped_ppo":
            network("main_level/agent/main/online/network_0", v_head)
            def ppo_head(h):
                if isinstance(meta["action_space"], list):
                    outputs["policy"] = tf.nn.softmax(dense(h, len(meta["action_space"]), "ppo_head_0/policy_fc", False))
                else:
                    outputs["policy"] = dense(h, 2, "ppo_head_0/policy_mean", False)
                    outputs["log_std"] = var("ppo_head_0/policy_log_std", [1, 2], 0.3)
            network("main_level/agent/main/online/network_1", ppo_head)
        else:
            def sac_head(h):
                with tf.compat.v1.variable_scope("sac_policy_head_0"):
                    h = dense(h, 256, "dense", True)
                    outputs["policy"] = dense(h, 2, "policy_mean", False)
                    outputs["log_std"] = dense(h, 2, "dense_1", False)
            network("main_level/agent/policy/online/network_0", sac_head)
            actions = tf.constant(np.fromfile(case["actions"], dtype="<f4").reshape([-1, 2]))
            def q_head(h):
                with tf.compat.v1.variable_scope("q_values_head_0"):
                    for q in ["q1", "q2"]:
                        with tf.compat.v1.variable_scope(q + "_head"):
                            x = tf.concat([h, actions], -1)
                            x = dense(x, 256, "dense", True)
                            x = dense(x, 256, "dense_1", True)
                            outputs[q] = dense(x, 1, q + "_output", False)
            network("main_level/agent/q/online/network_0", q_head, middleware=False)
            network("main_level/agent/v/online/network_0", v_head)
        with tf.compat.v1.Session(graph=g) as sess:
            sess.run(tf.compat.v1.global_variables_initializer())
            for v in tf.compat.v1.trainable_variables():
                if v.name.endswith("rescalers:0"):
                    sess.run(v.assign(1.0))
            for k, t in outputs.items():
                sess.run(t, feed).astype("<f4").tofile(os.path.join(case["out"], k + ".bin"))
            model = os.path.join(case["folder"], "model")
            os.makedirs(model, exist_ok=True)
            saver = tf.compat.v1.train.Saver([v for v in tf.compat.v1.trainable_variables() if "main_level/" in v.name and "/target" not in v.name])
            name = "7_Step-2100.ckpt"
            saver.save(sess, os.path.join(model, name))
    # deepracer-for-cloud's layout: the metadata in model/, the rest at the root and in ip/.
    open(os.path.join(model, ".coach_checkpoint"), "w").write(name)
    json.dump({"best_checkpoint": {"name": name, "avg_eval_metric": 41.0, "time_stamp": 1.0},
               "last_checkpoint": {"name": name, "avg_eval_metric": 41.0, "time_stamp": 1.0}},
              open(os.path.join(model, "deepracer_checkpoints.json"), "w"))
    json.dump(meta, open(os.path.join(model, "model_metadata.json"), "w"))
    os.makedirs(os.path.join(case["folder"], "ip"), exist_ok=True)
    json.dump({"batch_size": 64, "lr": 0.0003, "num_epochs": 3, "discount_factor": 0.99, "beta_entropy": 0.01,
               "num_episodes_between_training": 1 if meta["training_algorithm"] == "sac" else 20, "loss_type": "huber", "sac_alpha": 0.2},
              open(os.path.join(case["folder"], "ip", "hyperparameters.json"), "w"))
    open(os.path.join(case["folder"], "reward_function.py"), "w").write("def reward_function(params):\n    return float(params['speed'])\n")
    open(os.path.join(case["folder"], "training_params.yaml"), "w").write(
        "WORLD_NAME: reInvent2019_track\nTRACK_DIRECTION_CLOCKWISE: false\nRACE_TYPE: TIME_TRIAL\n")
    print(case["name"], sorted(os.listdir(model)))
"#;

fn write_floats(path: &Path, x: &[f32]) {
    std::fs::write(path, x.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>()).unwrap();
}

fn floats(path: &Path) -> Vec<f32> {
    std::fs::read(path).unwrap().chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
}

fn close(what: &str, got: &[f32], want: &[f32]) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    for (i, (a, b)) in got.iter().zip(want).enumerate() {
        assert!((a - b).abs() <= 1e-5 * (1.0 + b.abs()), "{what} [{i}]: Paddock {a}, TensorFlow {b}");
    }
}

/// Issue 53: checkpoints TensorFlow writes for SHALLOW discrete, DEEP continuous, stereo +
/// LiDAR and SAC import with TensorFlow's outputs, policy and value (and SAC's Q heads), to
/// 1e-5; a clone of one trains on with its own value network.
#[test]
fn checkpoints_tensorflow_writes_import_with_its_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("write.py"), TF_WRITES).unwrap();
    let batch = 3;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
    let mut spec = Vec::new();
    let mut inputs_of = BTreeMap::new();
    for (k, (name, meta)) in cases().into_iter().enumerate() {
        let out = d.join(format!("{name}-tf"));
        std::fs::create_dir_all(&out).unwrap();
        let inputs = policy::model::inputs(&meta, 0);
        // Each input's values: grey levels for a camera, ranges for the LiDAR.
        let mut per_input = Vec::new();
        let mut files = Vec::new();
        for (i, (sensor, shape)) in inputs.iter().enumerate() {
            let n = shape.size();
            let v: Vec<f32> = if sensor.is_primary() {
                (0..batch * n)
                    .map(|j| ((j / 160 + j % 160) % 256) as f32 * 0.6 + rng.random_range(0.0..100.0))
                    .collect()
            } else {
                (0..batch * n).map(|_| rng.random_range(0.15..1.0)).collect()
            };
            let file = out.join(format!("x{i}.bin"));
            write_floats(&file, &v);
            let dims: Vec<usize> = match *shape {
                policy::nn::InputShape::Image(h, w, c) => vec![h, w, c],
                policy::nn::InputShape::Flat(n) => vec![n],
            };
            files.push(serde_json::json!({"sensor": sensor.name(), "shape": dims, "file": file}));
            per_input.push((n, v));
        }
        // A sample is its inputs side by side, in the network's input order.
        let mut x = Vec::new();
        for b in 0..batch {
            for (n, v) in &per_input {
                x.extend_from_slice(&v[b * n..(b + 1) * n]);
            }
        }
        // SAC's Q heads: actions in the environment's units.
        let actions: Vec<f32> =
            (0..batch).flat_map(|_| [rng.random_range(-30.0..30.0), rng.random_range(0.5..3.5)]).collect();
        write_floats(&out.join("actions.bin"), &actions);
        inputs_of.insert(name, (x, actions));
        let meta_json: serde_json::Value = serde_json::from_str(&meta.to_json()).unwrap();
        spec.push(serde_json::json!({"name": name, "seed": 100 + k, "metadata": meta_json, "inputs": files,
            "out": out, "folder": d.join(format!("{name}-drfc")), "actions": out.join("actions.bin")}));
    }
    std::fs::write(d.join("cases.json"), serde_json::to_string(&spec).unwrap()).unwrap();
    let out = Command::new(car_python()).arg(d.join("write.py")).arg(d.join("cases.json")).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let said = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(said.contains("7_Step-2100.ckpt.meta") && said.contains("7_Step-2100.ckpt.data-00000-of-00001"), "{said}");
    for (name, meta) in cases() {
        // Paddock's writer gives TensorFlow's files byte for byte: the same table, blocks,
        // restarts, separators, checksums and footer, and the data in the same order.
        let prefix = d.join(format!("{name}-drfc/model/7_Step-2100.ckpt"));
        let (index, data) = policy::tfckpt::encode(&policy::tfckpt::read(&prefix).unwrap());
        assert!(
            index == std::fs::read(policy::tfckpt::index_path(&prefix)).unwrap(),
            "{name}: the index differs from TensorFlow's"
        );
        assert!(
            data == std::fs::read(policy::tfckpt::data_path(&prefix)).unwrap(),
            "{name}: the data differs from TensorFlow's"
        );
        let said = ok(&["import", &format!("{name}-drfc"), "--out", &format!("{name}-in")], d);
        assert!(said.contains("checkpoint 7_Step-2100.ckpt"), "{said}");
        let f = policy::folder::load(&d.join(format!("{name}-in"))).unwrap();
        let (x, actions) = &inputs_of[name];
        let tf = d.join(format!("{name}-tf"));
        let mut tape = policy::nn::Tape::default();
        f.model.pi.forward(x, batch, &mut tape, faer::Par::Seq);
        let pi = tape.output().to_vec();
        f.model.v.forward(x, batch, &mut tape, faer::Par::Seq);
        close(&format!("{name}: value"), tape.output(), &floats(&tf.join("value.bin")));
        match f.model.head {
            Head::Categorical(k) => {
                let p: Vec<f32> =
                    pi.chunks(k).flat_map(|r| policy::model::log_softmax(r).into_iter().map(f32::exp)).collect();
                close(&format!("{name}: probabilities"), &p, &floats(&tf.join("policy.bin")));
            }
            Head::Gaussian { log_std } => {
                close(&format!("{name}: means"), &pi, &floats(&tf.join("policy.bin")));
                close(&format!("{name}: log-std"), &log_std, &floats(&tf.join("log_std.bin")));
            }
            Head::Squashed { .. } => {
                let means: Vec<f32> = pi.chunks(4).flat_map(|r| r[..2].to_vec()).collect();
                let log_std: Vec<f32> = pi.chunks(4).flat_map(|r| r[2..].to_vec()).collect();
                close(&format!("{name}: means"), &means, &floats(&tf.join("policy.bin")));
                close(&format!("{name}: log-stds"), &log_std, &floats(&tf.join("log_std.bin")));
                // The Q heads, through the critics the folder keeps, on Paddock's [-1, 1] actions.
                let (c, _) = virtual_model::read_critics(&d.join(format!("{name}-in")), &meta, f.model.obs_size())
                    .unwrap()
                    .expect("SAC's critics are kept");
                let e = c.embed.as_ref().unwrap();
                e.forward(x, batch, &mut tape, faer::Par::Seq);
                let emb = tape.output().to_vec();
                let w = e.out_size();
                let mut qin = Vec::new();
                for b in 0..batch {
                    qin.extend_from_slice(&emb[b * w..(b + 1) * w]);
                    qin.push((actions[2 * b] - 0.0) / 30.0);
                    qin.push((actions[2 * b + 1] - 2.0) / 1.5);
                }
                for (q, net) in [("q1", &c.q1), ("q2", &c.q2)] {
                    net.forward(&qin, batch, &mut tape, faer::Par::Seq);
                    close(&format!("{name}: {q}"), tape.output(), &floats(&tf.join(format!("{q}.bin"))));
                }
            }
        }
    }
    // A clone of the imported model trains on with the value network it brought: no warm-up.
    let said = ok(&["clone", "shallow_discrete-in", "--out", "cloned"], d);
    assert!(!said.contains("value tower is new"), "{said}");
    let h = std::fs::read_to_string(d.join("cloned/hyperparameters.json")).unwrap();
    assert!(h.contains("\"value_warmup_updates\": 0"), "{h}");
    assert!(h.contains("\"num_episodes_between_training\": 20"), "the imported hyperparameters: {h}");
    // SAC's critics go along with the clone.
    ok(&["clone", "sac-in", "--out", "sac-cloned"], d);
    assert!(d.join("sac-cloned/model").join(virtual_model::CRITICS_FILE).is_file());
}

/// The entries two archives hold differently.
fn differing(a: &[u8], b: &[u8]) -> Vec<String> {
    let entries = |x: &[u8]| -> BTreeMap<String, Vec<u8>> {
        let mut t = tar::Archive::new(flate2::read::GzDecoder::new(x));
        t.entries()
            .unwrap()
            .map(|e| {
                let mut e = e.unwrap();
                let mut v = Vec::new();
                std::io::Read::read_to_end(&mut e, &mut v).unwrap();
                (e.path().unwrap().display().to_string(), v)
            })
            .collect()
    };
    let (x, y) = (entries(a), entries(b));
    x.keys().chain(y.keys()).filter(|k| x.get(*k) != y.get(*k)).cloned().collect()
}

/// Issue 53: a model trained here goes out whole and comes back, and its clone trains on
/// with the value network it brought: the first update's value network explains the returns
/// as the trained one did, where a fresh value network (the run's own first update) explains
/// nearly none of them.
#[test]
fn a_clone_of_a_whole_import_trains_on_with_its_value_network() {
    let (run, _) = crate::support::camera_run();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("reward_function.py"), "def reward_function(params):\n    return 1.0\n").unwrap();
    let model = run.join("model").display().to_string();
    ok(&["export", &model, "--virtual-dir", "droa", "--reward-function", "reward_function.py"], d);
    assert_eq!(droa_import_problem(&d.join("droa"), "droa"), None);
    ok(&["import", "droa", "--out", "whole"], d);
    let said = ok(&["clone", "whole", "--out", "cloned"], d);
    assert!(!said.contains("value tower is new"), "{said}");
    ok(
        &["train", "--out", "cloned", "--resume", "--world", "reinvent_base", "--sensor", "camera", "--envs", "16"]
            .into_iter()
            .chain([
                "--max-episodes",
                "20",
                "--target-laps",
                "0",
                "--verify-trials",
                "0",
                "--trials",
                "1",
                "--minutes",
                "5",
            ])
            .collect::<Vec<_>>(),
        d,
    );
    let first = |path: &Path| -> serde_json::Value {
        let text = std::fs::read_to_string(path).unwrap();
        serde_json::from_str(text.lines().next().expect("an update")).unwrap()
    };
    let fresh = first(&run.join("metrics.jsonl"))["explained_variance"].as_f64().unwrap();
    let carried = first(&d.join("cloned/metrics.jsonl"))["explained_variance"].as_f64().unwrap();
    println!("explained variance of the first update: the clone's {carried}, a fresh value network's {fresh}");
    // What the clone trained goes back out with the files it was imported with (the reward
    // function too) and the checkpoints numbered on from the imported one.
    let imported = std::fs::read_to_string(d.join("whole/deepracer/checkpoint")).unwrap();
    ok(&["export", "cloned/model", "--virtual-dir", "again"], d);
    assert_eq!(droa_import_problem(&d.join("again"), "again"), None);
    let again = std::fs::read_to_string(d.join("again/model/.coach_checkpoint")).unwrap();
    let number = |n: &str| n.split('_').next().unwrap().parse::<u64>().unwrap();
    assert!(number(&again) > number(&imported), "{again} after {imported}");
    assert!(
        carried > 0.15 && carried > fresh + 0.1,
        "explained variance: the clone's first update {carried}, a fresh value network's {fresh}"
    );
}

/// Issue 53: a model exported, imported and exported again is the same bytes, archive and
/// folder alike.
#[test]
fn export_import_export_is_the_same_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    for (name, meta) in cases().into_iter().filter(|(n, _)| *n != "deep_continuous") {
        model_folder(&d.join(name), &meta, 5);
        let first = format!("virtualmodel-{name}.tar.gz");
        ok(&["export", &format!("{name}/model"), "--virtual", &first], d);
        let said = ok(&["import", &first, "--out", &format!("{name}-in"), "--checkpoint", "best"], d);
        assert!(said.contains("checkpoint 12_Step-4321.ckpt"), "{said}");
        let second = format!("again-{name}.tar.gz");
        ok(&["export", &format!("{name}-in"), "--virtual", &second, "--virtual-dir", &format!("again-{name}")], d);
        let (a, b) = (std::fs::read(d.join(&first)).unwrap(), std::fs::read(d.join(&second)).unwrap());
        assert!(a == b, "{name}: the second export differs from the first: {:?}", differing(&a, &b));
        // The unpacked folder imports as the archive does.
        ok(&["import", &format!("again-{name}"), "--out", &format!("{name}-dir-in")], d);
        let (x, y) = (
            policy::folder::load(&d.join(format!("{name}-in"))).unwrap(),
            policy::folder::load(&d.join(format!("{name}-dir-in"))).unwrap(),
        );
        assert_eq!(x.model, y.model);
    }
}

/// The checks DRoA's Import model page and its handler run on a folder
/// (`ImportModel.tsx validateFiles`, `importModel.ts`, `validation.ts validateTrackConfig`,
/// the model validator's files), written here from DRoA's code: the first problem, if any.
fn droa_import_problem(root: &Path, model_name: &str) -> Option<String> {
    droa_import_check(root, model_name).err()
}

fn droa_import_check(root: &Path, model_name: &str) -> Result<(), String> {
    fn walk(d: &Path, out: &mut Vec<PathBuf>) {
        for e in std::fs::read_dir(d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() { walk(&p, out) } else { out.push(p) }
        }
    }
    let json = |rel: &str| -> Result<serde_json::Value, String> {
        let b = std::fs::read(root.join(rel)).map_err(|e| format!("{rel}: {e}"))?;
        serde_json::from_slice(&b).map_err(|e| format!("{rel}: {e}"))
    };
    let mut files = Vec::new();
    walk(root, &mut files);
    let size: u64 = files.iter().map(|f| f.metadata().unwrap().len()).sum();
    if size > 1 << 30 {
        return Err("over MAX_FOLDER_SIZE".into());
    }
    for required in ["model_metadata.json", "reward_function.py", "training_params.yaml", "hyperparameters.json"] {
        if !files.iter().any(|f| f.file_name().unwrap() == required) {
            return Err(format!("missing {required}"));
        }
    }
    if model_name.is_empty()
        || model_name.len() > 64
        || !model_name.chars().all(|c| c.is_ascii_alphanumeric() || c == '-')
    {
        return Err(format!("model name {model_name}"));
    }
    let meta = json("model_metadata.json")?;
    let algo = meta["training_algorithm"].as_str().unwrap_or("clipped_ppo");
    let space = &meta["action_space"];
    if algo == "sac" && space.is_array() {
        return Err("SAC with a discrete action space".into());
    }
    if space.is_object() {
        for k in ["speed", "steering_angle"] {
            let (lo, hi) = (space[k]["low"].as_f64(), space[k]["high"].as_f64());
            if !matches!((lo, hi), (Some(l), Some(h)) if l < h) {
                return Err(format!("{k}: low < high expected"));
            }
        }
    } else if !space.is_array() {
        return Err("action_space is neither a list nor a range".into());
    }
    let h = json("ip/hyperparameters.json")?;
    for k in [
        "batch_size",
        "num_epochs",
        "stack_size",
        "lr",
        "beta_entropy",
        "e_greedy_value",
        "epsilon_steps",
        "discount_factor",
        "loss_type",
        "num_episodes_between_training",
        "exploration_type",
        "sac_alpha",
    ] {
        if h.get(k).is_none() {
            return Err(format!("hyperparameters: no {k}"));
        }
    }
    if algo == "sac" && h["num_episodes_between_training"] != 1 {
        return Err("SAC needs num_episodes_between_training 1".into());
    }
    let y: serde_yaml::Value =
        serde_yaml::from_slice(&std::fs::read(root.join("training_params.yaml")).map_err(|e| e.to_string())?)
            .map_err(|e| format!("training_params.yaml: {e}"))?;
    let world = y["WORLD_NAME"].as_str().ok_or("training_params.yaml: no WORLD_NAME")?;
    if world.ends_with("_cw") || world.ends_with("_ccw") {
        return Err(format!("WORLD_NAME {world} carries a direction"));
    }
    let clockwise = y["TRACK_DIRECTION_CLOCKWISE"]
        .as_bool()
        .ok_or("training_params.yaml: TRACK_DIRECTION_CLOCKWISE is not a boolean")?;
    virtual_model::droa_direction_ok(world, clockwise)?;
    for (k, allowed) in [
        ("BODY_SHELL_TYPE", &["deepracer", "f1_2021", "f1_car"][..]),
        ("CAR_COLOR", &["Black", "Grey", "Blue", "Red", "Orange", "White", "Purple"][..]),
    ] {
        if let Some(v) = y.get(k)
            && !allowed.contains(&v.as_str().unwrap_or(""))
        {
            return Err(format!("{k} {v:?}"));
        }
    }
    // The model validator: the metadata in model/ with its sensor and version, a sensor it
    // validates, the checkpoint .coach_checkpoint names (and deepracer_checkpoints.json's).
    let m = json("model/model_metadata.json")?;
    let sensors: Vec<&str> = m["sensor"]
        .as_array()
        .ok_or("model/model_metadata.json: no sensor")?
        .iter()
        .filter_map(|s| s.as_str())
        .collect();
    if m.get("version").is_none() {
        return Err("model/model_metadata.json: no version".into());
    }
    for s in &sensors {
        if ![
            "FRONT_FACING_CAMERA",
            "observation",
            "STEREO_CAMERAS",
            "LIDAR",
            "SECTOR_LIDAR",
            "DISCRETIZED_SECTOR_LIDAR",
        ]
        .contains(s)
        {
            return Err(format!("sensor {s}: the model validator takes none such"));
        }
    }
    let name = std::fs::read_to_string(root.join("model/.coach_checkpoint"))
        .map_err(|e| format!("model/.coach_checkpoint: {e}"))?;
    let c = json("model/deepracer_checkpoints.json")?;
    let best = c["best_checkpoint"]["name"].as_str().ok_or("no best_checkpoint")?;
    let last = c["last_checkpoint"]["name"].as_str().ok_or("no last_checkpoint")?;
    for n in [name.as_str(), best, last] {
        for ext in ["index", "data-00000-of-00001"] {
            if !root.join(format!("model/{n}.{ext}")).is_file() {
                return Err(format!("no model/{n}.{ext}"));
            }
        }
    }
    Ok(())
}

/// Issue 53: the exported folder passes DRoA's import checks, and what DRoA cannot take is
/// refused naming what and why, with nothing written.
#[test]
fn the_exported_folder_passes_droas_import_checks() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (_, meta) = cases().remove(0);
    model_folder(&d.join("run"), &meta, 1);
    ok(&["export", "run/model", "--virtual-dir", "my-model"], d);
    assert_eq!(droa_import_problem(&d.join("my-model"), "my-model"), None);
    // Each rule the mirror checks fails a folder that breaks it.
    let broken = |edit: &dyn Fn(&Path)| {
        let _ = std::fs::remove_dir_all(d.join("broken"));
        ok(&["export", "run/model", "--virtual-dir", "broken"], d);
        edit(&d.join("broken"));
        droa_import_problem(&d.join("broken"), "broken")
    };
    assert!(broken(&|p| std::fs::remove_file(p.join("reward_function.py")).unwrap()).is_some());
    assert!(
        broken(&|p| std::fs::write(
            p.join("training_params.yaml"),
            "WORLD_NAME: reinvent_base\nTRACK_DIRECTION_CLOCKWISE: true\n"
        )
        .unwrap())
        .is_some()
    );
    assert!(broken(&|p| std::fs::remove_file(p.join("model/12_Step-4321.ckpt.index")).unwrap()).is_some());
    // A direction DRoA lacks on that track, a track it lacks, and head-to-bot are refused.
    for (args, want) in [
        (vec!["--track", "reinvent_base", "--clockwise"], "not available clockwise"),
        (vec!["--track", "reinvent_wood"], "DRoA has no track reinvent_wood"),
    ] {
        let mut a = vec!["export", "run/model", "--virtual-dir", "refused"];
        a.extend(args);
        let (good, text) = coordinator(&a, d);
        assert!(!good && text.contains(want), "{want}: {text}");
        assert!(!d.join("refused").exists());
    }
    std::fs::create_dir_all(d.join("run/model/deepracer")).unwrap();
    std::fs::write(
        d.join("run/model/deepracer/training_params.yaml"),
        "WORLD_NAME: reInvent2019_track\nRACE_TYPE: HEAD_TO_BOT\n",
    )
    .unwrap();
    let (good, text) = coordinator(&["export", "run/model", "--virtual", "h2b.tar.gz"], d);
    assert!(!good && text.contains("no HEAD_TO_BOT race"), "{text}");
    assert!(!d.join("h2b.tar.gz").exists());
    // An existing folder is refused before anything is written.
    let (good, text) = coordinator(
        &["export", "run/model", "--virtual", "x.tar.gz", "--virtual-dir", "my-model", "--deepracer-for-cloud"],
        d,
    );
    assert!(!good && text.contains("my-model exists"), "{text}");
    assert!(!d.join("x.tar.gz").exists());
}

/// Issue 53: a damaged checkpoint in a model folder is refused naming the file, and nothing
/// is written.
#[test]
fn a_damaged_checkpoint_is_refused_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (_, meta) = cases().remove(0);
    model_folder(&d.join("run"), &meta, 1);
    ok(&["export", "run/model", "--virtual-dir", "m"], d);
    let data = d.join("m/model/12_Step-4321.ckpt.data-00000-of-00001");
    let mut bytes = std::fs::read(&data).unwrap();
    bytes[1000] ^= 0x10;
    std::fs::write(&data, &bytes).unwrap();
    let (good, text) = coordinator(&["import", "m", "--out", "in"], d);
    assert!(
        !good && text.contains("12_Step-4321.ckpt.data-00000-of-00001") && text.contains("checksum mismatch"),
        "{text}"
    );
    assert!(!d.join("in").exists());
    // Inside an archive, the archive and the entry are named.
    let gz =
        flate2::write::GzEncoder::new(std::fs::File::create(d.join("m.tar.gz")).unwrap(), flate2::Compression::fast());
    let mut tar = tar::Builder::new(gz);
    tar.append_dir_all("", d.join("m")).unwrap();
    tar.into_inner().unwrap().finish().unwrap();
    let (good, text) = coordinator(&["import", "m.tar.gz", "--out", "in"], d);
    assert!(!good && text.contains("m.tar.gz: model/12_Step-4321.ckpt.data-00000-of-00001"), "{text}");
    assert!(text.contains("checksum mismatch") && !text.contains("/tmp/"), "{text}");
    assert!(!d.join("in").exists());
    std::fs::write(d.join("m/model/12_Step-4321.ckpt.index"), b"short").unwrap();
    let (good, text) = coordinator(&["import", "m", "--out", "in"], d);
    assert!(!good && text.contains("12_Step-4321.ckpt.index") && text.contains("too short"), "{text}");
    let (good, text) = coordinator(&["import", "m", "--out", "in", "--checkpoint", "3"], d);
    assert!(!good && text.contains("no checkpoint number 3"), "{text}");
    assert!(!d.join("in").exists());
}
