//! The model folder: a bit-exact round trip, and clear refusals.

use policy::folder::{self, Manifest};
use policy::{ActorCritic, ModelMetadata};
use rand::SeedableRng;

fn meta(text: &str) -> ModelMetadata {
    ModelMetadata::parse(text, "m.json").unwrap()
}

const DISCRETE: &str = r#"{"action_space":[{"steering_angle":-30,"speed":1},{"steering_angle":30,"speed":2}],"sensor":["STATE_VECTOR"],"neural_network":"PADDOCK_MLP","version":"5"}"#;
const CONTINUOUS: &str = r#"{"action_space":{"steering_angle":{"low":-30,"high":30},"speed":{"low":1,"high":3}},"action_space_type":"continuous","sensor":["STATE_VECTOR"],"neural_network":"PADDOCK_MLP","version":"5"}"#;

fn manifest(version: u64) -> Manifest {
    Manifest {
        format: "paddock-model-1".into(),
        policy_version: version,
        parent: None,
        weights_sha256: String::new(),
        obs_size: 9,
        observation: serde_json::json!({"kind": "state"}),
        training: serde_json::json!({"iteration": 3}),
    }
}

#[test]
fn save_and_load_round_trip_bit_exactly() {
    let dir = tempfile::tempdir().unwrap();
    for text in [DISCRETE, CONTINUOUS] {
        let m = meta(text);
        let mut model = ActorCritic::new(&m, 9, &mut rand_chacha::ChaCha8Rng::seed_from_u64(1));
        if let policy::Head::Gaussian { log_std } = &mut model.head {
            *log_std = [-0.25, 0.125];
        }
        let path = dir.path().join("model");
        let written = folder::save(&path, &m, &model, &manifest(7)).unwrap();
        assert_eq!(written.weights_sha256.len(), 64);
        let back = folder::load(&path).unwrap();
        assert_eq!(back.model, model, "weights, layers and head survive bit for bit");
        assert_eq!(back.metadata.action_space, m.action_space);
        assert_eq!(back.manifest, written);
        // Saving again over it replaces it whole.
        folder::save(&path, &m, &model, &manifest(8)).unwrap();
        assert_eq!(folder::load(&path).unwrap().manifest.policy_version, 8);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1, "no temporary folders left");
        // model_metadata.json is DeepRacer's file.
        let written_meta = std::fs::read_to_string(path.join("model_metadata.json")).unwrap();
        let v: serde_json::Value = serde_json::from_str(&written_meta).unwrap();
        assert_eq!(v["training_algorithm"], "clipped_ppo");
        assert!(v["action_space"].is_array() || v["action_space"].is_object());
    }
}

#[test]
fn weights_that_do_not_fit_the_metadata_are_refused_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let m = meta(DISCRETE);
    let model = ActorCritic::new(&m, 9, &mut rand_chacha::ChaCha8Rng::seed_from_u64(1));
    let path = dir.path().join("model");
    folder::save(&path, &m, &model, &manifest(1)).unwrap();
    // Three actions in the metadata, two in the weights.
    let three = DISCRETE.replace(
        r#"{"steering_angle":30,"speed":2}"#,
        r#"{"steering_angle":30,"speed":2},{"steering_angle":0,"speed":2}"#,
    );
    std::fs::write(path.join("model_metadata.json"), three).unwrap();
    let err = folder::load(&path).unwrap_err().to_string();
    assert!(err.contains("model.safetensors") && err.contains("pi.4.weight") && err.contains("[3, 128]"), "{err}");
    // A damaged weights file.
    folder::save(&path, &m, &model, &manifest(1)).unwrap();
    let w = path.join("model.safetensors");
    let mut bytes = std::fs::read(&w).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 1;
    std::fs::write(&w, bytes).unwrap();
    let err = folder::load(&path).unwrap_err().to_string();
    assert!(err.contains("sha256") && err.contains("changed or damaged"), "{err}");
}

#[test]
fn compatibility_names_what_differs() {
    use policy::Incompatible;
    let a = meta(DISCRETE);
    assert!(a.compatible_with(&a).is_ok());
    let faster = meta(&DISCRETE.replace(r#""speed":2"#, r#""speed":3"#));
    let lidar = meta(&DISCRETE.replace(r#"["STATE_VECTOR"]"#, r#"["STATE_VECTOR","LIDAR"]"#));
    // Issue 50: each reason is typed, and its message names what differs and why it matters.
    for (other, want, shown) in [
        (meta(CONTINUOUS), "Outputs", "action space differs (discrete 2 outputs vs continuous 2): the output layer"),
        (faster, "ActionValues", "change meaning"),
        (lidar, "Sensors", "sensors differ ([StateVector] vs [StateVector, Lidar]): the network's inputs"),
    ] {
        let e = a.compatible_with(&other).unwrap_err();
        let kind = match e {
            Incompatible::Sensors { .. } => "Sensors",
            Incompatible::Network { .. } => "Network",
            Incompatible::Outputs { .. } => "Outputs",
            Incompatible::ActionValues => "ActionValues",
        };
        assert_eq!(kind, want, "{e}");
        assert!(e.to_string().contains(shown), "{e}");
    }
}
