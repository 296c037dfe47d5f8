//! `deploy bench`: what a frame and a new model cost on the car, measured on one core.
//!
//! - Frame to command, without the network: a 160×120 JPEG frame in (the community car's
//!   frames, resized at the source) and a 640×480 bgr8 frame (the AWS layout, resized here),
//!   decoded, prepared and run through the SHALLOW policy tower, p50/p99 per frame; the
//!   inference alone beside it; the big dense layer in f16 and in int8 (`precision`).
//! - A new model to its first frame: the published message decoded, its signature and checksum
//!   checked, the model loaded and swapped in, then one frame driven with it.

use anyhow::Result;
use deploy::{Driver, Follow, ModelSlot, Offer};
use policy::car::{CarConfig, Layout, Precision};
use policy::signature::{Signer, TrustedKeys};
use policy::{ActorCritic, Manifest, ModelMetadata, ModelParts};
use protocol::ros::{self, CompressedImage, Header, Image, RawFrame};
use protocol::{PROTOCOL_VERSION, PolicyUpdate};
use serde_bytes::ByteBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

fn percentiles(mut v: Vec<f64>) -> (f64, f64) {
    v.sort_by(f64::total_cmp);
    let at = |p: f64| v[((p * (v.len() - 1) as f64).round() as usize).min(v.len() - 1)];
    (at(0.5), at(0.99))
}

fn frame_bytes(layout: ros::Layout, w: u32, h: u32) -> Vec<u8> {
    // A textured frame (a flat one would make JPEG decoding unrealistically cheap).
    let rgb: Vec<u8> = (0..w * h)
        .flat_map(|i| {
            let (x, y) = (i % w, i / w);
            [(x * 7 + y * 3) as u8, (x ^ y) as u8, (y * 5) as u8]
        })
        .collect();
    let header = Header::default();
    let frame = match layout {
        ros::Layout::Community => {
            let mut jpeg = Vec::new();
            image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 90)
                .encode(&rgb, w, h, image::ExtendedColorType::Rgb8)
                .expect("JPEG");
            RawFrame::Compressed(CompressedImage { header, format: "jpeg".into(), data: ByteBuf::from(jpeg) })
        }
        ros::Layout::Aws => RawFrame::Raw(Image {
            header,
            height: h,
            width: w,
            encoding: "bgr8".into(),
            is_bigendian: 0,
            step: w * 3,
            data: ByteBuf::from(rgb),
        }),
    };
    ros::encode_sensor(vec![frame], &[], layout)
}

fn model_message(signer: &Signer, version: u64) -> Vec<u8> {
    let meta = ModelMetadata::default_camera();
    let model =
        ActorCritic::new(&meta, 120 * 160, &mut <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(version));
    let manifest = Manifest {
        format: "paddock-model-1".into(),
        policy_version: version,
        parent: None,
        weights_sha256: String::new(),
        obs_size: 120 * 160,
        observation: serde_json::json!({}),
        training: serde_json::json!({}),
    };
    let p = ModelParts::new(&meta, &model, &manifest, Some(signer));
    protocol::encode(&PolicyUpdate {
        protocol_version: PROTOCOL_VERSION,
        job_id: "bench".into(),
        policy_version: version,
        weights: p.weights,
        model_metadata_json: p.metadata_json,
        manifest_json: p.manifest_json,
        signature_json: serde_json::to_string(&p.signature).expect("JSON"),
    })
}

/// Run the benchmark and print a table.
pub fn run(seconds: f64) -> Result<()> {
    let signer = Signer::generate();
    let mut trust = TrustedKeys::default();
    trust.add("bench.pub", &signer);
    println!("# deploy bench: SHALLOW camera model (policy tower on the car), one core");
    println!();
    println!("| measurement | p50 | p99 |");
    println!("|---|---|---|");
    for (layout, w, h, name, precision) in [
        (ros::Layout::Community, 160, 120, "160×120 JPEG (community car), f16", Precision::F16),
        (ros::Layout::Community, 160, 120, "160×120 JPEG (community car), int8", Precision::Int8),
        (ros::Layout::Aws, 640, 480, "640×480 bgr8 (AWS layout), f16", Precision::F16),
    ] {
        let car = CarConfig {
            layout: if layout == ros::Layout::Community { Layout::Community } else { Layout::Aws },
            precision,
            ..CarConfig::default()
        };
        let slot = Arc::new(ModelSlot::default());
        let parts = protocol::exchange::policy_parts(&protocol::decode::<PolicyUpdate>(&model_message(&signer, 1))?)?;
        slot.offer(parts, &trust, &car, "bench", &Follow::Latest);
        let mut d = Driver::new(car, slot.clone());
        let bytes = frame_bytes(layout, w, h);
        let (mut total, mut infer) = (Vec::new(), Vec::new());
        let m = slot.current().expect("taken");
        let mut scratch = deploy::infer::Scratch::default();
        let mut tape = policy::nn::Tape::default();
        let obs = vec![128.0f32; 120 * 160];
        let mut reference = Vec::new();
        let t = Instant::now();
        while t.elapsed().as_secs_f64() < seconds {
            let t0 = Instant::now();
            d.frame(&bytes, t0).map_err(|e| anyhow::anyhow!(e))?;
            total.push(t0.elapsed().as_secs_f64() * 1e3);
            let t1 = Instant::now();
            std::hint::black_box(m.policy.mode(&obs, &mut scratch));
            infer.push(t1.elapsed().as_secs_f64() * 1e3);
        }
        // The reference, in the same run (its own loop: interleaved, its 23 MB of f32 weights
        // would evict the car's): the same tower through the training code's forward pass.
        let t = Instant::now();
        while precision == Precision::F16 && layout == ros::Layout::Community && t.elapsed().as_secs_f64() < seconds {
            let t2 = Instant::now();
            m.model.pi.forward(&obs, 1, &mut tape, faer::Par::Seq);
            std::hint::black_box(tape.output());
            reference.push(t2.elapsed().as_secs_f64() * 1e3);
        }
        let (p50, p99) = percentiles(total);
        println!("| {name}: frame to command (decode, prepare, infer, map) | {p50:.3} ms | {p99:.3} ms |");
        if layout == ros::Layout::Community {
            let (p50, p99) = percentiles(infer);
            let what = if precision == Precision::F16 { "f16" } else { "int8" };
            println!("| inference alone (policy tower, batch 1), {what} | {p50:.3} ms | {p99:.3} ms |");
        }
        if !reference.is_empty() {
            let (r50, r99) = percentiles(reference);
            println!("| reference: the same tower in f32 (the training forward pass) | {r50:.3} ms | {r99:.3} ms |");
        }
    }
    // A new model: message decode, signature + checksum + tensors, swap, first frame.
    let car = CarConfig::default();
    let slot = Arc::new(ModelSlot::default());
    let mut d = Driver::new(car.clone(), slot.clone());
    let frame = frame_bytes(ros::Layout::Community, 160, 120);
    let mut to_first = Vec::new();
    let t = Instant::now();
    let mut v = 0;
    while t.elapsed().as_secs_f64() < seconds || to_first.len() < 3 {
        v += 1;
        let msg = model_message(&signer, v);
        let t0 = Instant::now();
        let u = protocol::decode::<PolicyUpdate>(&msg)?;
        let parts = protocol::exchange::policy_parts(&u)?;
        match slot.offer(parts, &trust, &car, "bench", &Follow::Latest) {
            Offer::Taken(_) => {}
            o => anyhow::bail!("the bench model was not taken: {o:?}"),
        }
        let c = d.frame(&frame, Instant::now()).map_err(|e| anyhow::anyhow!(e))?;
        assert_eq!(c.version, Some(v));
        to_first.push(t0.elapsed().as_secs_f64() * 1e3);
        std::thread::sleep(Duration::from_millis(1));
    }
    let (p50, p99) = percentiles(to_first);
    println!(
        "| a new model ({:.1} MB message): decode, verify (ed25519, sha256, tensors), load, swap, first frame | {p50:.1} ms | {p99:.1} ms |",
        model_message(&signer, 1).len() as f64 / 1e6
    );
    Ok(())
}
