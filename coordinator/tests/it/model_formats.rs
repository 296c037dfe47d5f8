//! A model's policy in the formats other runtimes load, checked by runtimes nobody here
//! wrote: `export --onnx` in onnxruntime (after `onnx.checker`); `export --car` (DeepRacer's
//! archive) in TensorFlow as deepracer-utils loads it, through the community car's TFLite
//! conversion, and in OpenVINO; and a graph TensorFlow itself froze, brought in by `import`.

use policy::{ActorCritic, Manifest, ModelMetadata, ModelParts};
use rand::{Rng, SeedableRng};
use std::process::Command;

use crate::support::python;

const RUN: &str = r#"
import sys, numpy as np, onnx, onnxruntime as ort
path, out = sys.argv[1], sys.argv[2]
m = onnx.load(path)
onnx.checker.check_model(m, full_check=True)
sess = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
# Each input: its name, its values' file, its shape (batch first).
feed = {sys.argv[k]: np.fromfile(sys.argv[k + 1], dtype="<f4").reshape([int(s) for s in sys.argv[k + 2].split(",")])
        for k in range(3, len(sys.argv), 3)}
assert sorted(feed) == sorted(i.name for i in sess.get_inputs()), [i.name for i in sess.get_inputs()]
names = [o.name for o in sess.get_outputs()]
res = sess.run(None, feed)
np.concatenate([r.reshape(-1) for r in res]).astype("<f4").tofile(out)
print(",".join(names))
"#;

fn check(meta: &ModelMetadata, obs_size: usize, seed: u64) {
    let obs_size = policy::model::input_size(meta, obs_size);
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let model = ActorCritic::new(meta, obs_size, &mut rand_chacha::ChaCha8Rng::seed_from_u64(seed));
    let manifest = Manifest {
        format: "paddock-model-1".into(),
        policy_version: 7,
        parent: None,
        weights_sha256: String::new(),
        obs_size,
        observation: serde_json::json!({}),
        training: serde_json::json!({}),
    };
    ModelParts::new(meta, &model, &manifest, None).write(&d.join("model")).unwrap();
    let onnx = d.join("policy.onnx");
    let out = Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .args(["export"])
        .arg(d.join("model"))
        .arg("--onnx")
        .arg(&onnx)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    // Sample inputs: grey frames (or state vectors, or LiDAR readings) with structure, batch of 3.
    let batch = 3;
    let inputs = policy::model::inputs(meta, obs_size);
    let x = observations(&inputs, batch, seed + 1);
    let script = d.join("run.py");
    std::fs::write(&script, RUN).unwrap();
    let got_path = d.join("y.bin");
    let mut cmd = Command::new(python("onnx and onnxruntime"));
    cmd.arg(&script).arg(&onnx).arg(&got_path);
    for ((sensor, _), (file, dims)) in inputs.iter().zip(input_files(&inputs, &x, batch, &d.join("x"))) {
        let name = if inputs.len() == 1 { "observation" } else { sensor.name() };
        let dims: Vec<String> = dims.iter().map(|d| d.to_string()).collect();
        cmd.arg(name).arg(&file).arg(dims.join(","));
    }
    let out = cmd.output().unwrap();
    assert!(out.status.success(), "onnxruntime: {}", String::from_utf8_lossy(&out.stderr));
    let names = String::from_utf8_lossy(&out.stdout).trim().to_string();
    let got: Vec<f32> = std::fs::read(&got_path)
        .unwrap()
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    // Paddock's own forward pass.
    let mut tape = policy::nn::Tape::default();
    model.pi.forward(&x, batch, &mut tape, faer::Par::Seq);
    let logits = tape.output().to_vec();
    let n = logits.len();
    let scale = logits.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-3);
    for (i, (a, b)) in got[..n].iter().zip(&logits).enumerate() {
        assert!((a - b).abs() <= 1e-4 * scale + 1e-6, "logit {i}: onnxruntime {a}, Paddock {b}");
    }
    if let policy::Head::Categorical(k) = model.head {
        assert_eq!(names, "logits,probabilities");
        for r in 0..batch {
            let p = policy::model::log_softmax(&logits[r * k..(r + 1) * k]);
            for j in 0..k {
                let (a, b) = (got[n + r * k + j], p[j].exp());
                assert!((a - b).abs() < 1e-5, "probability {r},{j}: {a} vs {b}");
            }
        }
    } else if let policy::Head::Squashed { .. } = model.head {
        // SAC: the simulator's deterministic action, tanh of the means.
        assert_eq!(names, "logits,action");
        for r in 0..batch {
            for j in 0..2 {
                let (a, b) = (got[n + r * 2 + j], logits[r * 4 + j].tanh());
                assert!((a - b).abs() < 1e-5, "action {r},{j}: {a} vs {b}");
            }
        }
    } else {
        assert_eq!(names, "logits");
    }
}

/// Issue 9: ONNX export matches Paddock's forward pass in onnxruntime.
#[test]
fn onnx_export_matches_paddocks_forward_pass_in_onnxruntime() {
    // DeepRacer's SHALLOW camera network, discrete actions.
    check(&ModelMetadata::default_camera(), 120 * 160, 3);
    // The deeper camera network with a continuous action space.
    let text = r#"{"action_space": {"steering_angle": {"low": -30, "high": 30}, "speed": {"low": 0.5, "high": 3}},
        "sensor": ["FRONT_FACING_CAMERA"], "neural_network": "DEEP_CONVOLUTIONAL_NETWORK", "training_algorithm": "clipped_ppo",
        "action_space_type": "continuous", "version": "5"}"#;
    let meta = ModelMetadata::parse(text, "continuous").unwrap();
    check(&meta, 120 * 160, 4);
    // The state-vector model.
    check(&ModelMetadata::default_state_vector(), 20, 5);
}

/// Issue 32: ONNX export of a SAC model gives the simulator's action in onnxruntime.
#[test]
fn onnx_export_of_a_sac_model_gives_the_simulators_action_in_onnxruntime() {
    let text = r#"{"action_space": {"steering_angle": {"low": -30, "high": 30}, "speed": {"low": 1, "high": 2}},
        "sensor": ["FRONT_FACING_CAMERA"], "neural_network": "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW",
        "training_algorithm": "sac", "action_space_type": "continuous", "version": "4"}"#;
    check(&ModelMetadata::parse(text, "sac").unwrap(), 120 * 160, 6);
}

/// Issue 31: ONNX export of camera and LiDAR models takes an input per sensor in onnxruntime.
#[test]
fn onnx_export_of_camera_and_lidar_models_takes_an_input_per_sensor_in_onnxruntime() {
    // The camera first (FRONT_FACING_CAMERA < SECTOR_LIDAR), and the LiDAR first
    // (DISCRETIZED_SECTOR_LIDAR < FRONT_FACING_CAMERA, LIDAR < STEREO_CAMERAS).
    for (sensors, extra) in [
        (r#""FRONT_FACING_CAMERA", "SECTOR_LIDAR""#, ""),
        (
            r#""FRONT_FACING_CAMERA", "DISCRETIZED_SECTOR_LIDAR""#,
            r#", "lidar_config": {"num_sectors": 4, "num_values_per_sector": 3}"#,
        ),
        (r#""STEREO_CAMERAS", "LIDAR""#, ""),
    ] {
        let text = format!(
            r#"{{"action_space": [{{"steering_angle": -20, "speed": 1}}, {{"steering_angle": 20, "speed": 1}}],
            "sensor": [{sensors}], "neural_network": "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW", "version": "5"{extra}}}"#
        );
        let meta = ModelMetadata::parse(&text, "m.json").unwrap();
        check(&meta, 0, 6);
    }
}

// ---------------------------------------------------------------------------------------
// DeepRacer's model archive, against the car side's own tools (target/pyenv-car).

fn car_python() -> std::path::PathBuf {
    std::env::var_os("PADDOCK_CAR_PYTHON").map(std::path::PathBuf::from).unwrap_or_else(|| {
        panic!("PADDOCK_CAR_PYTHON is not set: run `./paddock test`, which makes target/pyenv-car with TensorFlow and OpenVINO")
    })
}

/// Unpacks the archive as the car's loader does, then runs its graph in TensorFlow
/// (deepracer-utils' loader), converts it as deepracer-custom-car does (TFLite, FP16) and runs
/// that, and runs it in OpenVINO: each result into OUT.<engine>.bin.
const CAR_SIDE: &str = r#"
import atexit, json, os, shutil, sys, tarfile, tempfile, numpy as np
# One process for every case (TensorFlow and OpenVINO load once): each case is an archive,
# its outputs' prefix, the output node, and its inputs (placeholder, values' file, shape with
# the batch first).
cases = json.load(open(sys.argv[1]))
import tensorflow as tf
import openvino as ov
for case in cases:
    archive, out, outp = case["archive"], case["out"], case["output"]
    ins = [(i["placeholder"], np.fromfile(i["file"], dtype="<f4").reshape(i["shape"])) for i in case["inputs"]]
    batch = ins[0][1].shape[0]
    work = tempfile.mkdtemp()
    # The unpacked archive and OpenVINO's model (hundreds of MB for a DEEPER network) go when
    # the script ends, whatever its outcome.
    atexit.register(shutil.rmtree, work, True)
    with tarfile.open(archive) as t:
        names = t.getnames()
        t.extractall(work)
    pbs = [os.path.join(r, f) for r, _, fs in os.walk(work) for f in fs if f.endswith(".pb")]
    assert len(pbs) == 1 and os.path.isfile(os.path.join(work, "model_metadata.json")), names
    pb = pbs[0]
    g = tf.compat.v1.GraphDef()
    g.ParseFromString(open(pb, "rb").read())
    with tf.Graph().as_default() as graph:
        tf.compat.v1.import_graph_def(g, name="")
        with tf.compat.v1.Session(graph=graph) as sess:
            y = sess.run(outp + ":0", {name + ":0": x for name, x in ins})
    y.astype("<f4").tofile(out + ".tf.bin")
    # deepracer-custom-car's model optimizer node, with its arguments (TFLITE engine).
    conv = tf.compat.v1.lite.TFLiteConverter.from_frozen_graph(
        graph_def_file=pb, input_arrays=[name for name, _ in ins], output_arrays=[outp],
        input_shapes={name: [1] + list(x.shape[1:]) for name, x in ins})
    conv.allow_custom_ops = True
    conv.optimizations = [tf.lite.Optimize.DEFAULT]
    conv.target_spec.supported_types = [tf.float16]
    lite = conv.convert()
    it = tf.lite.Interpreter(model_content=lite)
    it.allocate_tensors()
    slots = {d["name"]: d["index"] for d in it.get_input_details()}
    rows = []
    for i in range(batch):
        for name, x in ins:
            it.set_tensor(slots[name], x[i:i + 1])
        it.invoke()
        rows.append(it.get_tensor(it.get_output_details()[0]["index"]).copy())
    np.concatenate(rows).astype("<f4").tofile(out + ".tflite.bin")
    # OpenVINO, as the car's OV 2024 engine converts it (the names it finds carry ":0"; FP16
    # weights), on the CPU.
    m = ov.convert_model(pb, input=[(name + ":0", [1] + list(x.shape[1:])) for name, x in ins], output=outp + ":0")
    ov.save_model(m, os.path.join(work, "model.xml"), compress_to_fp16=True)
    c = ov.Core().compile_model(os.path.join(work, "model.xml"), "CPU")
    rows = [c({name + ":0": x[i:i + 1] for name, x in ins})[c.output(0)] for i in range(batch)]
    np.concatenate(rows).astype("<f4").tofile(out + ".openvino.bin")
    shutil.rmtree(work, True)
    print(case["name"] + ": " + " ".join(names))
"#;
fn floats(path: &std::path::Path) -> Vec<f32> {
    std::fs::read(path).unwrap().chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
}

fn write_floats(path: &std::path::Path, x: &[f32]) {
    std::fs::write(path, x.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>()).unwrap();
}

/// Camera frames with structure (0–255), `batch` of them.
fn frames(batch: usize, size: usize, seed: u64) -> Vec<f32> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    (0..batch * size).map(|i| ((i / 160 + i % 160) % 256) as f32 * 0.7 + rng.random_range(0.0..60.0)).collect()
}

/// Paddock's output for DeepRacer's `policy` node: probabilities, or the means.
fn paddock_policy(model: &ActorCritic, x: &[f32], batch: usize) -> Vec<f32> {
    let mut tape = policy::nn::Tape::default();
    model.pi.forward(x, batch, &mut tape, faer::Par::Seq);
    let y = tape.output().to_vec();
    match model.head {
        policy::Head::Categorical(k) => {
            y.chunks(k).flat_map(|r| policy::model::log_softmax(r).into_iter().map(f32::exp)).collect()
        }
        // SAC's frozen `policy`: the two means (DeepRacer's graph has no log-stds).
        policy::Head::Squashed { .. } => y.chunks(4).flat_map(|r| r[..2].to_vec()).collect(),
        _ => y,
    }
}

fn coordinator(args: &[&std::ffi::OsStr], dir: &std::path::Path) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_coordinator")).args(args).current_dir(dir).output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "coordinator {args:?}: {text}");
    text
}

/// Issue 30: the car archive runs in TensorFlow TFLite and OpenVINO as Paddock does and comes back
/// whole.
#[test]
fn the_car_archive_runs_in_tensorflow_tflite_and_openvino_as_paddock_does_and_comes_back_whole() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let stereo = r#"{"action_space": [{"steering_angle": -20, "speed": 1}, {"steering_angle": 0, "speed": 2},
        {"steering_angle": 20, "speed": 1}, {"steering_angle": 0, "speed": 1}],
        "sensor": ["STEREO_CAMERAS"], "neural_network": "DEEP_CONVOLUTIONAL_NETWORK_DEEP", "training_algorithm": "clipped_ppo",
        "action_space_type": "discrete", "version": "5"}"#;
    let lidar = r#"{"action_space": [{"steering_angle": -20, "speed": 1}, {"steering_angle": 0, "speed": 2}, {"steering_angle": 20, "speed": 1}],
        "sensor": ["FRONT_FACING_CAMERA", "SECTOR_LIDAR"], "neural_network": "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW", "training_algorithm": "clipped_ppo",
        "action_space_type": "discrete", "version": "5"}"#;
    let stereo_lidar = r#"{"action_space": {"steering_angle": {"low": -30, "high": 30}, "speed": {"low": 0.5, "high": 3}},
        "sensor": ["STEREO_CAMERAS", "LIDAR"], "neural_network": "DEEP_CONVOLUTIONAL_NETWORK", "training_algorithm": "clipped_ppo",
        "action_space_type": "continuous", "version": "5"}"#;
    let sac = r#"{"action_space": {"steering_angle": {"low": -30, "high": 30}, "speed": {"low": 1, "high": 2}},
        "sensor": ["FRONT_FACING_CAMERA"], "neural_network": "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW", "training_algorithm": "sac",
        "action_space_type": "continuous", "version": "4"}"#;
    let cases = [
        ("shallow", ModelMetadata::default_camera()),
        // DEEP, continuous, with stereo cameras and a LiDAR below; DEEPER, discrete, stereo here.
        ("deeper", ModelMetadata::parse(stereo, "deeper").unwrap()),
        // Camera + LiDAR (issue 31): a placeholder per sensor, the embeddings merged.
        ("lidar", ModelMetadata::parse(lidar, "lidar").unwrap()),
        ("stereo-lidar", ModelMetadata::parse(stereo_lidar, "stereo-lidar").unwrap()),
        // SAC (issue 32): the `policy` network's names, the pre-tanh means out.
        ("sac", ModelMetadata::parse(sac, "sac").unwrap()),
    ];
    let script = d.join("car_side.py");
    std::fs::write(&script, CAR_SIDE).unwrap();
    // Every case's model, archive and inputs first; then the car's engines on all of them in
    // one Python process; then each case's outputs against Paddock's and its import back.
    let batch = 3;
    let mut made = Vec::new();
    let mut jobs = Vec::new();
    for (name, meta) in cases {
        let inputs = policy::model::inputs(&meta, 0);
        let size = policy::model::input_size(&meta, 0);
        let model = ActorCritic::new(&meta, size, &mut rand_chacha::ChaCha8Rng::seed_from_u64(7));
        let manifest = Manifest {
            format: "paddock-model-1".into(),
            policy_version: 3,
            parent: None,
            weights_sha256: String::new(),
            obs_size: size,
            observation: serde_json::json!({"kind": "camera"}),
            training: serde_json::json!({}),
        };
        let folder = d.join(name);
        ModelParts::new(&meta, &model, &manifest, None).write(&folder).unwrap();
        let archive = d.join(format!("{name}.tar.gz"));
        let said = coordinator(&["export".as_ref(), folder.as_os_str(), "--car".as_ref(), archive.as_os_str()], d);
        assert!(said.contains(&format!("a car lists it as '{name}'")), "{said}");
        // Camera frames and LiDAR readings (0/1 sectors or 0.15-1 m), each input to its file.
        let x = observations(&inputs, batch, 11);
        let names = policy::tfgraph::Names::of(&meta).unwrap();
        let files = input_files(&inputs, &x, batch, &d.join(name));
        let ins: Vec<serde_json::Value> = (names.inputs.iter().zip(files))
            .map(|(placeholder, (file, shape))| serde_json::json!({"placeholder": placeholder, "file": file, "shape": shape}))
            .collect();
        jobs.push(serde_json::json!({"name": name, "archive": archive, "out": d.join(name), "output": names.output, "inputs": ins}));
        made.push((name, meta, model, x, archive));
    }
    let cases_file = d.join("cases.json");
    std::fs::write(&cases_file, serde_json::to_vec(&jobs).unwrap()).unwrap();
    let out = Command::new(car_python()).arg(&script).arg(&cases_file).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let printed = String::from_utf8_lossy(&out.stdout).to_string();
    for (name, meta, model, x, archive) in made {
        assert!(printed.contains(&format!("{name}: agent/model.pb model_metadata.json")), "{name}: {printed}");
        let want = paddock_policy(&model, &x, batch);
        // TensorFlow in float32 matches closely; TFLite's FP16 weights and OpenVINO's FP16 IR
        // within what the car's half precision allows (and choose the same action).
        for (engine, tol) in [("tf", 1e-4f32), ("tflite", 2e-2), ("openvino", 2e-2)] {
            let got = floats(&d.join(format!("{name}.{engine}.bin")));
            assert_eq!(got.len(), want.len(), "{name} {engine}");
            let scale = want.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-3);
            for (i, (a, b)) in got.iter().zip(&want).enumerate() {
                assert!((a - b).abs() <= tol * scale + 1e-6, "{name} {engine} output {i}: {a}, Paddock {b}");
            }
        }
        // And back: the archive imports to the same policy tower, bit for bit.
        let back = d.join(format!("{name}-back"));
        coordinator(&["import".as_ref(), archive.as_os_str(), "--out".as_ref(), back.as_os_str()], d);
        let f = policy::folder::load(&back).unwrap();
        if let policy::Head::Squashed { .. } = model.head {
            // All but the log-stds' rows of the last layer, which the graph does not hold.
            let Some(&policy::nn::Layer::Dense { inp, offset, .. }) = model.pi.layers.last() else { panic!() };
            assert!(f.model.pi.params[..offset + 2 * inp] == model.pi.params[..offset + 2 * inp], "{name}");
            let bias = offset + 4 * inp;
            assert_eq!(f.model.pi.params[bias..bias + 2], model.pi.params[bias..bias + 2], "{name}");
        } else {
            assert_eq!(f.model.pi, model.pi, "{name}");
        }
        assert_eq!(f.metadata.action_space, meta.action_space);
        assert_eq!(f.manifest.training["imported"]["graph"], "agent/model.pb");
    }
}

/// Each input's values out of `batch` samples `x`, written to `PREFIX.xK.bin`: the files and
/// their shapes (batch first), in input order.
fn input_files(
    inputs: &[(policy::Sensor, policy::nn::InputShape)],
    x: &[f32],
    batch: usize,
    prefix: &std::path::Path,
) -> Vec<(std::path::PathBuf, Vec<usize>)> {
    let size: usize = inputs.iter().map(|(_, s)| s.size()).sum();
    let mut at = 0;
    let mut out = Vec::new();
    for (k, (_, shape)) in inputs.iter().enumerate() {
        let n = shape.size();
        let part: Vec<f32> = x.chunks(size).flat_map(|row| row[at..at + n].to_vec()).collect();
        at += n;
        let file = prefix.with_extension(format!("x{k}.bin"));
        write_floats(&file, &part);
        let dims = match *shape {
            policy::nn::InputShape::Image(h, w, c) => vec![batch, h, w, c],
            policy::nn::InputShape::Flat(n) => vec![batch, n],
        };
        out.push((file, dims));
    }
    out
}

/// Observations for a model's inputs, `batch` of them: camera frames with structure (0-255)
/// and LiDAR readings (sector bits, or ranges in [0.15, 1] m).
fn observations(inputs: &[(policy::Sensor, policy::nn::InputShape)], batch: usize, seed: u64) -> Vec<f32> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut rows = vec![Vec::new(); batch];
    for (sensor, shape) in inputs {
        let n = shape.size();
        let part = match sensor {
            policy::Sensor::Lidar => (0..batch * n).map(|_| rng.random_range(0.15..1.0)).collect(),
            s if !s.is_primary() => (0..batch * n).map(|_| f32::from(rng.random_bool(0.3))).collect(),
            _ => frames(batch, n, seed),
        };
        for (row, p) in rows.iter_mut().zip(part.chunks(n)) {
            row.extend_from_slice(p);
        }
    }
    rows.concat()
}

/// DeepRacer's SHALLOW network as rl_coach builds it (its scopes and names, `/255` and the
/// offset in the graph, a flatten whose shape is read at run time, the gradient rescaler
/// before the head), random weights, frozen as the simapp freezes it; its output on the
/// frames in OUT.tf.bin.
const TF_WRITES: &str = r#"
import sys, numpy as np, tensorflow as tf
pb, inputs, out = sys.argv[1:4]
tf.compat.v1.disable_eager_execution()
tf.compat.v1.disable_resource_variables()
rng = np.random.default_rng(5)
def var(name, shape, scale):
    return tf.compat.v1.get_variable(name, initializer=(rng.standard_normal(shape) * scale).astype("float32"))
g = tf.Graph()
with g.as_default():
    x = tf.compat.v1.placeholder("float", [None, 120, 160, 1],
        name="main_level/agent/main/online/network_0/FRONT_FACING_CAMERA/FRONT_FACING_CAMERA")
    with tf.compat.v1.variable_scope("main_level/agent/main/online/network_1"):
        with tf.compat.v1.variable_scope("FRONT_FACING_CAMERA"):
            h = x / 255.0
            h = h - 0.0
            for i, (f, k, s, c) in enumerate([(32, 8, 4, 1), (64, 4, 2, 32), (64, 3, 1, 64)]):
                with tf.compat.v1.variable_scope("Conv2d_%d" % (2 * i)):
                    h = tf.nn.conv2d(h, var("kernel", [k, k, c, f], (k * k * c) ** -0.5), [1, s, s, 1], "VALID")
                    h = tf.nn.bias_add(h, var("bias", [f], 0.1))
                h = tf.nn.relu(h, name="BatchnormActivationDropout_%d_activation" % (2 * i + 1))
            h = tf.reshape(h, tf.stack([tf.shape(h)[0], -1]), name="flatten/Reshape")
        with tf.compat.v1.variable_scope("middleware_fc_embedder/Dense_0"):
            h = tf.nn.bias_add(tf.matmul(h, var("kernel", [11264, 512], 11264 ** -0.5)), var("bias", [512], 0.1))
        h = tf.nn.relu(h, name="middleware_fc_embedder/BatchnormActivationDropout_1_activation")
        r = tf.constant(1.0, name="gradient_rescaler")
        h = (1.0 - r) * tf.stop_gradient(h) + r * h
        with tf.compat.v1.variable_scope("ppo_head_0"):
            with tf.compat.v1.variable_scope("policy_fc"):
                h = tf.nn.bias_add(tf.matmul(h, var("kernel", [512, 5], 0.05)), var("bias", [5], 0.1))
            y = tf.nn.softmax(h, name="policy")
    with tf.compat.v1.Session(graph=g) as sess:
        sess.run(tf.compat.v1.global_variables_initializer())
        frozen = tf.compat.v1.graph_util.convert_variables_to_constants(
            sess, g.as_graph_def(), ["main_level/agent/main/online/network_1/ppo_head_0/policy"])
        xs = np.fromfile(inputs, dtype="<f4").reshape([-1, 120, 160, 1])
        sess.run(y, {x: xs}).astype("<f4").tofile(out)
with open(pb, "wb") as f:
    f.write(frozen.SerializeToString())
print(sorted(set(n.op for n in frozen.node)))
"#;

/// Issue 30: a graph TensorFlow froze imports with the same outputs.
#[test]
fn a_graph_tensorflow_froze_imports_with_the_same_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("tf_writes.py"), TF_WRITES).unwrap();
    let batch = 2;
    let x = frames(batch, 120 * 160, 3);
    write_floats(&d.join("x.bin"), &x);
    std::fs::create_dir(d.join("dr")).unwrap();
    let out = Command::new(car_python())
        .arg(d.join("tf_writes.py"))
        .arg(d.join("dr/model.pb"))
        .arg(d.join("x.bin"))
        .arg(d.join("y.bin"))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let ops = String::from_utf8_lossy(&out.stdout).to_string();
    // TensorFlow's own graph: the ops Paddock does not write itself are in it.
    for op in ["StopGradient", "AddV2", "Shape", "StridedSlice", "Pack", "Sub"] {
        assert!(ops.contains(op), "{op} not in {ops}");
    }
    let meta = r#"{"action_space": [{"steering_angle": -30, "speed": 1}, {"steering_angle": -15, "speed": 1},
        {"steering_angle": 0, "speed": 1}, {"steering_angle": 15, "speed": 1}, {"steering_angle": 30, "speed": 1}],
        "sensor": ["FRONT_FACING_CAMERA"], "neural_network": "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW", "version": "5"}"#;
    std::fs::write(d.join("dr/model_metadata.json"), meta).unwrap();
    let said = coordinator(&["import".as_ref(), "dr/model.pb".as_ref(), "--out".as_ref(), "imported".as_ref()], d);
    assert!(said.contains("DEEP_CONVOLUTIONAL_NETWORK_SHALLOW with 5 actions"), "{said}");
    let f = policy::folder::load(&d.join("imported")).unwrap();
    let want = floats(&d.join("y.bin"));
    let got = paddock_policy(&f.model, &x, batch);
    assert_eq!(got.len(), want.len());
    for (i, (a, b)) in got.iter().zip(&want).enumerate() {
        assert!((a - b).abs() <= 1e-4, "probability {i}: Paddock {a}, TensorFlow {b}");
    }
    // What a model folder is for works on it: an evaluation drives it (a random policy: it
    // leaves the road, and says so), and it goes back out as an archive.
    let said = coordinator(
        &["evaluate", "imported", "--world", "reinvent_base", "--trials", "1"].map(std::ffi::OsStr::new),
        d,
    );
    assert!(said.contains("reinvent_base"), "{said}");
    coordinator(&["export", "imported", "--car", "again.tar.gz"].map(std::ffi::OsStr::new), d);
    // Cloned to train on: the new value tower learns alone first.
    let said = coordinator(&["clone", "imported", "--out", "cloned"].map(std::ffi::OsStr::new), d);
    assert!(said.contains("it learns alone until policy v5"), "{said}");
    let h = std::fs::read_to_string(d.join("cloned/hyperparameters.json")).unwrap();
    assert!(h.contains("\"value_warmup_updates\": 5"), "{h}");
    let again = policy::carpkg::read(&d.join("again.tar.gz")).unwrap().model("again", 1).unwrap();
    assert_eq!(again.pi, f.model.pi);
    // The same graph against another network's metadata: refused, saying what differs,
    // and nothing written.
    let deep = meta.replace("DEEP_CONVOLUTIONAL_NETWORK_SHALLOW", "DEEP_CONVOLUTIONAL_NETWORK_DEEP");
    std::fs::write(d.join("deep.json"), deep).unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .args(["import", "dr/model.pb", "--model-metadata", "deep.json", "--out", "wrong"])
        .current_dir(d)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{text}");
    assert!(text.contains("dr/model.pb") && text.contains("layer 3"), "{text}");
    assert!(!d.join("wrong").exists());
}

/// Issue 30: `bench model-files` times every network against the folder.
#[test]
fn bench_model_files_times_every_network_against_the_folder() {
    let dir = tempfile::tempdir().unwrap();
    let said = coordinator(&["bench", "model-files", "--repeats", "1"].map(std::ffi::OsStr::new), dir.path());
    for network in
        ["DEEP_CONVOLUTIONAL_NETWORK_SHALLOW ", "DEEP_CONVOLUTIONAL_NETWORK ", "DEEP_CONVOLUTIONAL_NETWORK_DEEP "]
    {
        let row = said.lines().find(|l| l.starts_with(network)).unwrap_or_else(|| panic!("{network}: {said}"));
        let figures: Vec<f64> = row[network.len()..].split_whitespace().map(|v| v.parse().unwrap()).collect();
        assert_eq!(figures.len(), 7, "{row}");
        assert!(figures.iter().all(|v| *v > 0.0), "{row}");
    }
}
