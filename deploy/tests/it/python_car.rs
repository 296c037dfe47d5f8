//! `deploy` against a car written with clients nobody in Paddock wrote. A Python peer
//! (`tests/python/car_peer.py`: rosbags' CDR from the .msg definitions, eclipse-zenoh) encodes
//! the camera messages in both interfaces layouts and decodes the commands the real `deploy`
//! binary sends back; this test checks each command against Paddock's own decoding of the same
//! bytes and its own driver. The Python environment is the one `./paddock test` makes
//! (`PADDOCK_PYTHON`).

use deploy::{Driver, Follow, ModelSlot, Offer};
use policy::car::CarConfig;
use policy::signature::{Signer, TrustedKeys};
use policy::{ActorCritic, Manifest, ModelMetadata, ModelParts};
use protocol::ros::{self, RawFrame};
use rand::SeedableRng;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::Instant;

fn python() -> PathBuf {
    std::env::var_os("PADDOCK_PYTHON").map(PathBuf::from).unwrap_or_else(|| {
        panic!("PADDOCK_PYTHON is not set: run `./paddock test`, which makes target/pyenv with rosbags, eclipse-zenoh and onnxruntime")
    })
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

fn model_folder(dir: &Path) -> (PathBuf, PathBuf) {
    let signer = Signer::generate();
    let (_, public) = signer.write_pair(&dir.join("learner")).unwrap();
    let meta = ModelMetadata::default_camera();
    let model = ActorCritic::new(&meta, 120 * 160, &mut rand_chacha::ChaCha8Rng::seed_from_u64(9));
    let manifest = Manifest {
        format: "paddock-model-1".into(),
        policy_version: 42,
        parent: None,
        weights_sha256: String::new(),
        obs_size: 120 * 160,
        observation: serde_json::json!({}),
        training: serde_json::json!({}),
    };
    let folder = dir.join("model");
    ModelParts::new(&meta, &model, &manifest, Some(&signer)).write(&folder).unwrap();
    (folder, public)
}

/// 160×120 RGB frames with patterns that differ from frame to frame.
fn rgb_frame(i: u32) -> Vec<u8> {
    (0..160 * 120u32)
        .flat_map(|p| {
            let (x, y) = (p % 160, p / 160);
            [((x * (i + 1)) % 256) as u8, ((y * 3 + i * 40) % 256) as u8, (((x + y) * (i % 5 + 1)) % 256) as u8]
        })
        .collect()
}

fn check_layout(layout: &str) {
    check(layout, false);
}

/// The car's bridge speaks to `deploy` over plain TCP on loopback, with no certificate; with
/// `certs` the on-car agent runs under the cluster's credentials and access rules, which give
/// a peer on loopback TCP (the `local-ros` subject) the camera and the servo keys only.
fn check(layout: &str, certs: bool) {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (folder, public) = model_folder(d);
    let frames = d.join("frames");
    std::fs::create_dir(&frames).unwrap();
    let n = 8;
    for i in 0..n {
        let rgb = rgb_frame(i);
        let bytes = if layout == "community" {
            let mut jpeg = Vec::new();
            image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 85)
                .encode(&rgb, 160, 120, image::ExtendedColorType::Rgb8)
                .unwrap();
            jpeg
        } else {
            rgb.chunks_exact(3).flat_map(|p| [p[2], p[1], p[0]]).collect()
        };
        std::fs::write(frames.join(format!("frame_{i}.bin")), bytes).unwrap();
    }
    let ns = format!("py_{layout}");
    let car_toml = d.join("car.toml");
    std::fs::write(&car_toml, format!("id = \"py-{layout}\"\nnamespace = \"{ns}\"\nlayout = \"{layout}\"\n")).unwrap();
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    // The Python peer listens (as a car's bridge does); deploy drives the saved model offline.
    let peer = Command::new(python())
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/car_peer.py"))
        .args([&endpoint, layout, &ns])
        .arg(&frames)
        .arg(d.join("answers.json"))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_millis(500));
    let mut deploy = Command::new(env!("CARGO_BIN_EXE_deploy"));
    if certs {
        // The cluster's credentials, made by the coordinator built beside `deploy`.
        let coordinator = PathBuf::from(env!("CARGO_BIN_EXE_deploy")).with_file_name("coordinator");
        let o = Command::new(&coordinator).args(["certs", "new"]).arg(d.join("certs")).output().unwrap();
        assert!(o.status.success(), "{}: {}", coordinator.display(), String::from_utf8_lossy(&o.stderr));
        deploy.arg("--certs").arg(d.join("certs"));
    }
    let mut deploy = deploy
        .args(["--connect", &endpoint, "--trust"])
        .arg(&public)
        .arg("--car")
        .arg(&car_toml)
        .arg("--model-dir")
        .arg(&folder)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let out = peer.wait_with_output().unwrap();
    let _ = deploy.kill();
    let _ = deploy.wait();
    assert!(out.status.success(), "the Python peer failed: {}", String::from_utf8_lossy(&out.stderr));
    let answers: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(d.join("answers.json")).unwrap()).unwrap();
    assert_eq!(answers.len(), n as usize);

    // Paddock's own reading of the bytes rosbags wrote, and its own driver on them.
    let car = CarConfig::parse(&std::fs::read_to_string(&car_toml).unwrap(), "car.toml").unwrap();
    let trust = TrustedKeys::load(std::slice::from_ref(&public)).unwrap();
    let slot = Arc::new(ModelSlot::default());
    assert_eq!(
        slot.offer(ModelParts::read(&folder).unwrap(), &trust, &car, "folder", &Follow::Latest),
        Offer::Taken(42)
    );
    let mut driver = Driver::new(car, slot);
    let rl = if layout == "community" { ros::Layout::Community } else { ros::Layout::Aws };
    let mut throttles = Vec::new();
    for (i, a) in answers.iter().enumerate() {
        let msg = std::fs::read(frames.join(format!("msg_{i}.cdr"))).unwrap();
        let sensors = ros::decode_sensor(&msg, rl).unwrap();
        // The Python car's lidar_data: [0.5, 1.5] in the community layout, none in AWS's.
        let lidar: &[f32] = if layout == "community" { &[0.5, 1.5] } else { &[] };
        assert_eq!(sensors.lidar, lidar);
        let decoded = sensors.frames;
        assert_eq!(decoded.len(), 1);
        let original = std::fs::read(frames.join(format!("frame_{i}.bin"))).unwrap();
        match &decoded[0] {
            RawFrame::Compressed(c) => {
                assert_eq!((c.format.as_str(), &c.data[..]), ("jpeg", &original[..]));
                assert_eq!(
                    (c.header.stamp.sec, c.header.stamp.nanosec, c.header.frame_id.as_str()),
                    (1000 + i as i32, i as u32, format!("f{i}").as_str())
                );
            }
            RawFrame::Raw(im) => {
                assert_eq!((im.width, im.height, im.step, im.encoding.as_str()), (160, 120, 480, "bgr8"));
                assert_eq!(&im.data[..], &original[..]);
                assert_eq!(im.header.frame_id, format!("f{i}"));
            }
        }
        let c = driver.frame(&msg, Instant::now()).unwrap();
        assert_eq!(c.version, Some(42));
        assert_eq!(a["angle"].as_f64().unwrap(), c.servo.angle as f64, "frame {i}: {a}");
        assert_eq!(a["throttle"].as_f64().unwrap(), c.servo.throttle as f64, "frame {i}: {a}");
        if layout == "community" {
            assert_eq!(a["correlation"], format!("f{i}"));
            assert_eq!(a["correlation_sec"], 1000 + i);
        }
        throttles.push(c.servo.throttle);
    }
    assert!(throttles.iter().all(|t| *t > 0.0), "a verified model drives: {throttles:?}");
}

/// Issue 9: a Python car speaks CDR with deploy-community layout.
#[test]
fn a_python_car_speaks_cdr_with_deploy_community_layout() {
    check_layout("community");
}

/// Issue 9: a Python car speaks CDR with deploy-aws layout.
#[test]
fn a_python_car_speaks_cdr_with_deploy_aws_layout() {
    check_layout("aws");
}

/// Issue 10: the car's bridge on loopback works under the cluster's access rules.
#[test]
fn the_cars_bridge_on_loopback_works_under_the_clusters_access_rules() {
    check("community", true);
}
