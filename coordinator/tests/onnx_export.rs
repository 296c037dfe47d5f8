//! `coordinator export MODEL --onnx FILE`, loaded by a runtime nobody here wrote
//! (onnxruntime from PyPI, after `onnx.checker`), gives Paddock's own forward pass.

use policy::{ActorCritic, Manifest, ModelMetadata, ModelParts};
use rand::{Rng, SeedableRng};
use std::process::Command;

mod support;
use support::python;

const RUN: &str = r#"
import sys, numpy as np, onnx, onnxruntime as ort
path, inputs, shape, out = sys.argv[1], sys.argv[2], [int(s) for s in sys.argv[3].split(",")], sys.argv[4]
m = onnx.load(path)
onnx.checker.check_model(m, full_check=True)
sess = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
x = np.fromfile(inputs, dtype="<f4").reshape(shape)
names = [o.name for o in sess.get_outputs()]
res = sess.run(None, {"observation": x})
np.concatenate([r.reshape(-1) for r in res]).astype("<f4").tofile(out)
print(",".join(names))
"#;

fn check(meta: &ModelMetadata, obs_size: usize, shape: &[usize], seed: u64) {
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
    // Sample inputs: grey frames (or state vectors) with structure, batch of 3.
    let batch = 3;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed + 1);
    let x: Vec<f32> =
        (0..batch * obs_size).map(|i| ((i % 251) as f32 + rng.random_range(0.0..4.0)).min(255.0)).collect();
    let inputs = d.join("x.bin");
    std::fs::write(&inputs, x.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>()).unwrap();
    let script = d.join("run.py");
    std::fs::write(&script, RUN).unwrap();
    let shape_arg =
        std::iter::once(batch).chain(shape.iter().copied()).map(|s| s.to_string()).collect::<Vec<_>>().join(",");
    let got_path = d.join("y.bin");
    let out = Command::new(python("onnx and onnxruntime"))
        .arg(&script)
        .arg(&onnx)
        .arg(&inputs)
        .arg(&shape_arg)
        .arg(&got_path)
        .output()
        .unwrap();
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
    } else {
        assert_eq!(names, "logits");
    }
}

#[test]
fn issue_9_onnx_export_matches_paddocks_forward_pass_in_onnxruntime() {
    // DeepRacer's SHALLOW camera network, discrete actions.
    check(&ModelMetadata::default_camera(), 120 * 160, &[120, 160, 1], 3);
    // The deeper camera network with a continuous action space.
    let text = r#"{"action_space": {"steering_angle": {"low": -30, "high": 30}, "speed": {"low": 0.5, "high": 3}},
        "sensor": ["FRONT_FACING_CAMERA"], "neural_network": "DEEP_CONVOLUTIONAL_NETWORK", "training_algorithm": "clipped_ppo",
        "action_space_type": "continuous", "version": "5"}"#;
    let meta = ModelMetadata::parse(text, "continuous").unwrap();
    check(&meta, 120 * 160, &[120, 160, 1], 4);
    // The state-vector model.
    check(&ModelMetadata::default_state_vector(), 20, &[20], 5);
}
