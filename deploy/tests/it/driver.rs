//! The car's loop without a network: which models it takes and refuses, what it sends for each
//! frame, the watchdog and the e-stop.

use deploy::{CarState, Driver, Follow, ModelSlot, Offer};
use policy::car::CarConfig;
use policy::signature::{Signer, TrustedKeys};
use policy::{ActorCritic, Manifest, ModelMetadata, ModelParts};
use protocol::ros::{self, Header, Image, Layout, RawFrame, Time};
use rand::SeedableRng;
use serde_bytes::ByteBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

fn manifest(version: u64, obs_size: usize) -> Manifest {
    Manifest {
        format: "paddock-model-1".into(),
        policy_version: version,
        parent: None,
        weights_sha256: String::new(),
        obs_size,
        observation: serde_json::json!({}),
        training: serde_json::json!({}),
    }
}

fn camera_parts(version: u64, signer: &Signer) -> ModelParts {
    let meta = ModelMetadata::default_camera();
    let model = ActorCritic::new(&meta, 120 * 160, &mut rand_chacha::ChaCha8Rng::seed_from_u64(version));
    ModelParts::new(&meta, &model, &manifest(version, 120 * 160), Some(signer))
}

fn aws_frame(sec: i32) -> Vec<u8> {
    let img = Image {
        header: Header { stamp: Time { sec, nanosec: 0 }, frame_id: "camera".into() },
        height: 480,
        width: 640,
        encoding: "bgr8".into(),
        is_bigendian: 0,
        step: 640 * 3,
        data: ByteBuf::from((0..640 * 480 * 3).map(|i| (i % 251) as u8).collect::<Vec<u8>>()),
    };
    ros::encode_sensor(vec![RawFrame::Raw(img)], &[], Layout::Aws)
}

fn aws_car() -> CarConfig {
    CarConfig { layout: policy::car::Layout::Aws, ..CarConfig::default() }
}

/// Issue 9: only genuine models that fit the car are taken.
#[test]
fn only_genuine_models_that_fit_the_car_are_taken() {
    let learner = Signer::from_seed([1; 32]);
    let stranger = Signer::from_seed([2; 32]);
    let mut trust = TrustedKeys::default();
    trust.add("learner.pub", &learner);
    let car = CarConfig::default();
    let slot = ModelSlot::default();
    let offer = |p: ModelParts, f: &Follow| slot.offer(p, &trust, &car, "latest", f);

    // Unsigned, signed by a stranger, changed after signing, a state-vector model: refused.
    let mut unsigned = camera_parts(3, &learner);
    unsigned.signature = None;
    let mut changed = camera_parts(3, &learner);
    let n = changed.weights.len();
    changed.weights[n - 1] ^= 1;
    let sv_meta = ModelMetadata::default_state_vector();
    let sv = ModelParts::new(
        &sv_meta,
        &ActorCritic::new(&sv_meta, 20, &mut rand_chacha::ChaCha8Rng::seed_from_u64(0)),
        &manifest(3, 20),
        Some(&learner),
    );
    for (parts, why) in [
        (unsigned, "not signed"),
        (camera_parts(3, &stranger), "not trusted"),
        (changed, "changed after signing"),
        (sv, "STATE_VECTOR"),
    ] {
        match offer(parts, &Follow::Latest) {
            Offer::Refused(r) => assert!(r.contains(why), "{r}"),
            o => panic!("{why}: {o:?}"),
        }
    }
    assert!(slot.current().is_none());
    assert_eq!(slot.refusals().0, 4);

    // Genuine: taken; an older version is not, a newer one is.
    assert_eq!(offer(camera_parts(3, &learner), &Follow::Latest), Offer::Taken(3));
    assert_eq!(offer(camera_parts(2, &learner), &Follow::Latest), Offer::Skipped(2));
    assert_eq!(offer(camera_parts(5, &learner), &Follow::Latest), Offer::Taken(5));
    // A refused model leaves the one that drives in place.
    assert!(matches!(offer(camera_parts(9, &stranger), &Follow::Latest), Offer::Refused(_)));
    assert_eq!(slot.current().unwrap().version, 5);
    // Following one version: only that one.
    assert_eq!(offer(camera_parts(7, &learner), &Follow::Version(6)), Offer::Skipped(7));
    assert_eq!(offer(camera_parts(6, &learner), &Follow::Version(6)), Offer::Taken(6));
    assert_eq!(slot.swaps(), 3);
}

/// Issue 9: no throttle before a model, then the model's choice.
#[test]
fn no_throttle_before_a_model_then_the_models_choice() {
    let learner = Signer::from_seed([1; 32]);
    let mut trust = TrustedKeys::default();
    trust.add("learner.pub", &learner);
    let car = aws_car();
    let slot = Arc::new(ModelSlot::default());
    let mut d = Driver::new(car.clone(), slot.clone());
    let t0 = Instant::now();
    let c = d.frame(&aws_frame(1), t0).unwrap();
    assert_eq!((c.servo.throttle, c.servo.angle, c.version), (0.0, 0.0, None));
    assert_eq!(c.correlation.stamp.sec, 1);
    assert_eq!(d.state(), CarState::NoModel);

    let parts = camera_parts(4, &learner);
    assert_eq!(slot.offer(parts, &trust, &car, "latest", &Follow::Latest), Offer::Taken(4));
    let c = d.frame(&aws_frame(2), t0 + Duration::from_millis(66)).unwrap();
    assert_eq!(c.version, Some(4));
    assert_eq!(d.state(), CarState::Driving);
    // The command is the model's own choice, mapped as the navigation node maps it.
    let m = slot.current().unwrap();
    let frames = ros::decode_sensor(&aws_frame(2), Layout::Aws).unwrap().frames;
    let mut obs = Vec::new();
    deploy::frame::preprocess(&frames, 120, 160, 1, &mut obs).unwrap();
    let choice = m.policy.mode(&obs, &mut deploy::infer::Scratch::default());
    let action = match choice {
        policy::Choice::Discrete(i) => m.metadata.action_space.discrete(i).unwrap(),
        policy::Choice::Continuous(_) => unreachable!(),
    };
    let (angle, throttle) = m.servo.to_servo(action);
    assert_eq!((c.servo.angle, c.servo.throttle), (angle, throttle));
    assert!(throttle > 0.0);

    // A frame that does not decode is an error, not a command, and not a crash.
    assert!(d.frame(b"\x00\x01\x00\x00garbage", t0).is_err());
    assert_eq!(d.figures().bad_frames, 1);
}

/// Issue 9: the watchdog and the e-stop bring the throttle to zero.
#[test]
fn watchdog_and_e_stop_bring_throttle_to_zero() {
    let learner = Signer::from_seed([1; 32]);
    let mut trust = TrustedKeys::default();
    trust.add("learner.pub", &learner);
    let car = aws_car();
    let slot = Arc::new(ModelSlot::default());
    slot.offer(camera_parts(1, &learner), &trust, &car, "latest", &Follow::Latest);
    let mut d = Driver::new(car, slot);
    let t0 = Instant::now();
    assert!(d.tick(t0).is_none(), "no frame yet: nothing to watch");
    d.frame(&aws_frame(1), t0).unwrap();
    assert!(d.tick(t0 + Duration::from_millis(200)).is_none());
    let stop = d.tick(t0 + Duration::from_millis(251)).expect("the watchdog fires after 250 ms");
    assert_eq!((stop.servo.throttle, stop.version), (0.0, None));
    assert_eq!(d.state(), CarState::FramesStopped);
    assert!(d.tick(t0 + Duration::from_millis(300)).is_none(), "once per period");
    assert!(d.tick(t0 + Duration::from_millis(502)).is_some(), "and again while frames stay away");
    // Frames return: driving again.
    let c = d.frame(&aws_frame(2), t0 + Duration::from_millis(600)).unwrap();
    assert!(c.version.is_some());
    assert_eq!(d.state(), CarState::Driving);
    // The e-stop holds the car until released.
    d.set_estop(true);
    let c = d.frame(&aws_frame(3), t0 + Duration::from_millis(666)).unwrap();
    assert_eq!((c.servo.throttle, c.version, d.state()), (0.0, None, CarState::EStop));
    d.set_estop(false);
    let c = d.frame(&aws_frame(4), t0 + Duration::from_millis(733)).unwrap();
    assert!(c.version.is_some() && d.state() == CarState::Driving);
}

/// Issue 9: the CI run of the car-in-the-loop test once missed one frame's 66 ms period while a
/// model loaded beside the drive loop on two cores: the loader now runs as a background thread.
#[cfg(target_os = "linux")]
#[test]
fn the_model_loader_runs_at_background_priority() {
    // Field 19 of /proc/thread-self/stat is the thread's niceness (after the command's closing
    // parenthesis, field 3 is the first).
    fn nice() -> i32 {
        let stat = std::fs::read_to_string("/proc/thread-self/stat").unwrap();
        let rest = &stat[stat.rfind(')').unwrap() + 2..];
        rest.split_whitespace().nth(19 - 3).unwrap().parse().unwrap()
    }
    let loader = std::thread::spawn(|| {
        deploy::driver::background_thread().unwrap();
        nice()
    })
    .join()
    .unwrap();
    assert_eq!(loader, 19);
    // The thread that spawned it keeps its own priority.
    assert_ne!(nice(), 19);
}

/// Issue 30: a DeepRacer archive drives only when the car trusts its name and then as Paddock
/// computes.
#[test]
fn a_deepracer_archive_drives_only_when_the_car_trusts_its_name_and_then_as_paddock_computes() {
    let meta = ModelMetadata::default_camera();
    let model = ActorCritic::new(&meta, 120 * 160, &mut rand_chacha::ChaCha8Rng::seed_from_u64(4));
    let dir = tempfile::tempdir().unwrap();
    let archive = dir.path().join("my model.v3.tar.gz");
    policy::carpkg::write(&archive, &model, &meta).unwrap();
    let name = policy::carpkg::car_model_name(&archive);
    assert_eq!(name, "my_model");
    let origin = archive.display().to_string();
    let f = policy::carpkg::read(&archive).unwrap().to_folder(&origin, 0).unwrap();
    let parts = || ModelParts::new(&f.metadata, &f.model, &f.manifest, None);
    // Not trusted: refused, saying which name to list; the car has no model.
    let slot = ModelSlot::default();
    match slot.offer_import(parts(), &name, &aws_car(), "archive") {
        Offer::Refused(why) => assert!(why.contains("trust_unsigned") && why.contains("\"my_model\""), "{why}"),
        other => panic!("{other:?}"),
    }
    assert!(slot.current().is_none());
    // Another name trusted: still refused.
    let other = CarConfig { trust_unsigned: vec!["my".into()], ..aws_car() };
    assert!(matches!(slot.offer_import(parts(), &name, &other, "archive"), Offer::Refused(_)));
    // Trusted by name: it drives, with the archive's policy tower.
    let car = CarConfig { trust_unsigned: vec!["my_model".into()], ..aws_car() };
    assert!(matches!(slot.offer_import(parts(), &name, &car, "archive"), Offer::Taken(0)));
    let m = slot.current().unwrap();
    assert_eq!(m.model.pi, model.pi);
    assert!(m.key.contains("unsigned"), "{}", m.key);
    // And the binary says the same before touching the network.
    let car_toml = dir.path().join("car.toml");
    std::fs::write(&car_toml, "trust_unsigned = [\"someone_else\"]\n").unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_deploy"))
        .arg("--model-dir")
        .arg(&archive)
        .arg("--car")
        .arg(&car_toml)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("my model.v3.tar.gz") && err.contains("trust_unsigned lists \"my_model\""), "{err}");
}

/// Issue 31: a stereo model drives from both images in both layouts.
#[test]
fn a_stereo_model_drives_from_both_images_in_both_layouts() {
    let learner = Signer::from_seed([1; 32]);
    let mut trust = TrustedKeys::default();
    trust.add("learner.pub", &learner);
    let meta = ModelMetadata::default_stereo();
    let model = ActorCritic::new(&meta, 2 * 120 * 160, &mut rand_chacha::ChaCha8Rng::seed_from_u64(5));
    let parts = || ModelParts::new(&meta, &model, &manifest(6, 2 * 120 * 160), Some(&learner));
    // The left and right images differ: each must reach its own channel.
    let image = |sec: i32, shift: usize| Image {
        header: Header { stamp: Time { sec, nanosec: 0 }, frame_id: "camera".into() },
        height: 120,
        width: 160,
        encoding: "rgb8".into(),
        is_bigendian: 0,
        step: 160 * 3,
        data: ByteBuf::from((0..160 * 120 * 3).map(|i| ((i / 3 + shift) % 241) as u8).collect::<Vec<u8>>()),
    };
    let jpeg = |img: &Image| {
        let rgb = image::RgbImage::from_raw(160, 120, img.data.to_vec()).unwrap();
        let mut out = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 95).encode_image(&rgb).unwrap();
        RawFrame::Compressed(ros::CompressedImage {
            header: img.header.clone(),
            format: "jpeg".into(),
            data: ByteBuf::from(out),
        })
    };
    let stereo = |c: CarConfig| CarConfig { sensors: vec!["STEREO_CAMERAS".into()], ..c };
    for (layout, car) in [(Layout::Aws, stereo(aws_car())), (Layout::Community, stereo(CarConfig::default()))] {
        let frames = |sec| {
            let (l, r) = (image(sec, 0), image(sec, 37));
            match layout {
                Layout::Aws => vec![RawFrame::Raw(l), RawFrame::Raw(r)],
                Layout::Community => vec![jpeg(&l), jpeg(&r)],
            }
        };
        let slot = Arc::new(ModelSlot::default());
        let mut d = Driver::new(car.clone(), slot.clone());
        assert_eq!(slot.offer(parts(), &trust, &car, "latest", &Follow::Latest), Offer::Taken(6));
        let msg = ros::encode_sensor(frames(3), &[], layout);
        let c = d.frame(&msg, Instant::now()).unwrap();
        assert_eq!(c.version, Some(6), "{layout:?}");
        // As Paddock computes it: channel 0 the first (left) image, channel 1 the second.
        let mut obs = Vec::new();
        deploy::frame::preprocess(&ros::decode_sensor(&msg, layout).unwrap().frames, 120, 160, 2, &mut obs).unwrap();
        assert_ne!(obs.iter().step_by(2).collect::<Vec<_>>(), obs.iter().skip(1).step_by(2).collect::<Vec<_>>());
        let m = slot.current().unwrap();
        let action = match m.policy.mode(&obs, &mut deploy::infer::Scratch::default()) {
            policy::Choice::Discrete(i) => m.metadata.action_space.discrete(i).unwrap(),
            policy::Choice::Continuous(_) => unreachable!(),
        };
        assert_eq!((c.servo.angle, c.servo.throttle), m.servo.to_servo(action), "{layout:?}");
        // One image is not enough for a stereo model: an error, not a command.
        let one = ros::encode_sensor(frames(4).into_iter().take(1).collect(), &[], layout);
        assert!(d.frame(&one, Instant::now()).is_err(), "{layout:?}");
    }
}

/// Issue 31: a camera and sector-LiDAR model drives from the message's LiDAR data in both layouts.
#[test]
fn a_camera_and_sector_lidar_model_drives_from_the_messages_lidar_data_in_both_layouts() {
    let learner = Signer::from_seed([1; 32]);
    let mut trust = TrustedKeys::default();
    trust.add("learner.pub", &learner);
    let meta = ModelMetadata::parse(
        r#"{"action_space": [{"steering_angle": -20, "speed": 1}, {"steering_angle": 0, "speed": 2}, {"steering_angle": 20, "speed": 1}],
            "sensor": ["FRONT_FACING_CAMERA", "SECTOR_LIDAR"], "neural_network": "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW", "version": "5"}"#,
        "m.json",
    )
    .unwrap();
    let size = 120 * 160 + 8;
    let model = ActorCritic::new(&meta, size, &mut rand_chacha::ChaCha8Rng::seed_from_u64(31));
    let parts = || ModelParts::new(&meta, &model, &manifest(9, size), Some(&learner));
    // A car without the LiDAR does not take the model.
    let slot = ModelSlot::default();
    let refused = slot.offer(parts(), &trust, &CarConfig::default(), "latest", &Follow::Latest);
    assert!(matches!(&refused, Offer::Refused(r) if r.contains("needs sensor SECTOR_LIDAR")), "{refused:?}");
    let image = Image {
        header: Header { stamp: Time { sec: 5, nanosec: 0 }, frame_id: "camera".into() },
        height: 120,
        width: 160,
        encoding: "rgb8".into(),
        is_bigendian: 0,
        step: 160 * 3,
        data: ByteBuf::from((0..160 * 120 * 3).map(|i| ((i / 3) % 233) as u8).collect::<Vec<u8>>()),
    };
    let with_lidar =
        |c: CarConfig| CarConfig { sensors: vec!["FRONT_FACING_CAMERA".into(), "SECTOR_LIDAR".into()], ..c };
    for (layout, car) in [(Layout::Aws, with_lidar(aws_car())), (Layout::Community, with_lidar(CarConfig::default()))] {
        let frame = match layout {
            Layout::Aws => RawFrame::Raw(image.clone()),
            Layout::Community => {
                let rgb = image::RgbImage::from_raw(160, 120, image.data.to_vec()).unwrap();
                let mut out = Vec::new();
                image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 95).encode_image(&rgb).unwrap();
                RawFrame::Compressed(ros::CompressedImage {
                    header: image.header.clone(),
                    format: "jpeg".into(),
                    data: ByteBuf::from(out),
                })
            }
        };
        let slot = Arc::new(ModelSlot::default());
        let mut d = Driver::new(car.clone(), slot.clone());
        assert_eq!(slot.offer(parts(), &trust, &car, "latest", &Follow::Latest), Offer::Taken(9));
        let m = slot.current().unwrap();
        let mut pixels = Vec::new();
        deploy::frame::preprocess(std::slice::from_ref(&frame), 120, 160, 1, &mut pixels).unwrap();
        // The car's choice with the camera's pixels first, then the 8 sector bits
        // (FRONT_FACING_CAMERA < SECTOR_LIDAR).
        let bits = |p: u32| (0..8).map(|s| f32::from(p >> s & 1 == 1)).collect::<Vec<f32>>();
        let want = |p: u32| {
            let obs = [pixels.clone(), bits(p)].concat();
            let action = match m.policy.mode(&obs, &mut deploy::infer::Scratch::default()) {
                policy::Choice::Discrete(i) => m.metadata.action_space.discrete(i).unwrap(),
                policy::Choice::Continuous(_) => unreachable!(),
            };
            m.servo.to_servo(action)
        };
        // Two LiDAR readings the model answers differently: the LiDAR steers the car.
        let (p1, p2) = (0..256u32)
            .flat_map(|a| (a + 1..256).map(move |b| (a, b)))
            .find(|&(a, b)| want(a) != want(b))
            .expect("some LiDAR readings change the model's choice");
        for p in [p1, p2] {
            // The fusion node's sectors as they are, and the 64 raw ranges through DeepRacer's
            // filter (0.3 m in a sector with something near, 5 m elsewhere).
            let raw: Vec<f32> = (0..64).map(|k| if p >> (k / 8) & 1 == 1 { 0.3 } else { 5.0 }).collect();
            for lidar in [bits(p), raw] {
                let c = d.frame(&ros::encode_sensor(vec![frame.clone()], &lidar, layout), Instant::now()).unwrap();
                assert_eq!(
                    (c.servo.angle, c.servo.throttle),
                    want(p),
                    "{layout:?} {p:08b} from {} values",
                    lidar.len()
                );
            }
        }
        // No LiDAR values, or a count the model cannot take: an error naming lidar_data.
        for lidar in [vec![], vec![0.5; 5]] {
            let e = d
                .frame(&ros::encode_sensor(vec![frame.clone()], &lidar, layout), Instant::now())
                .unwrap_err()
                .to_string();
            assert!(e.starts_with("lidar_data: ") && e.contains("SECTOR_LIDAR takes 8"), "{e}");
        }
    }
}
