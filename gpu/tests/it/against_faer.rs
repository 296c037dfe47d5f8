//! Each kernel against the CPU path it stands in for, to float tolerance.

use gpu::kernels::{AdamStep, Gemm, Operand};
use gpu::{DeviceChoice, Gpu, GpuNet};
use policy::nn::{Adam, InputShape, LayerSpec, Net, Tape};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn open() -> Gpu {
    Gpu::open(DeviceChoice::Gpu).expect("an adapter (lavapipe: mesa-vulkan-drivers)").expect("`gpu` opens one")
}

fn random(n: usize, rng: &mut ChaCha8Rng) -> Vec<f32> {
    (0..n).map(|_| rng.random_range(-1.0f32..1.0)).collect()
}

/// |a − b| within `tol` of the larger magnitude in `b`, element by element.
fn close(what: &str, a: &[f32], b: &[f32], tol: f32) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-6);
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!((x - y).abs() <= tol * scale, "{what}[{i}]: GPU {x}, faer {y} (scale {scale})");
    }
}

/// Issue 33: the product in every orientation and split matches faer.
#[test]
fn the_product_in_every_orientation_and_split_matches_faer() {
    let gpu = open();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut scratch = None;
    // (m, n, k): odd sizes (partial tiles), a long K under a small output (split over K),
    // a vector times a matrix (the bias gradient's shape).
    for [m, n, k] in [[1, 1, 1], [5, 7, 3], [70, 33, 129], [32, 64, 9000], [1, 40, 5000], [130, 70, 16]] {
        for (a_t, b_t, add) in [(false, false, false), (true, false, true), (false, true, false), (true, true, true)] {
            let a = random(m * k, &mut rng);
            let b = random(k * n, &mut rng);
            let c0 = random(m * n, &mut rng);
            let mut want = c0.clone();
            policy::nn::gemm(&mut want, &a, &b, policy::nn::Product { m, n, k, a_t, b_t, add }, faer::Par::Seq);
            // Each operand from an offset in a bigger buffer.
            let (pa, pb, pc) = (3, 5, 7);
            let abuf = gpu.buffer("a", pa + a.len()).unwrap();
            let bbuf = gpu.buffer("b", pb + b.len()).unwrap();
            let cbuf = gpu.buffer("c", pc + c0.len()).unwrap();
            gpu.upload(&abuf, pa, &a);
            gpu.upload(&bbuf, pb, &b);
            gpu.upload(&cbuf, pc, &c0);
            let mut enc = gpu.device.create_command_encoder(&Default::default());
            gpu.gemm(
                &mut enc,
                &Gemm {
                    mnk: [m, n, k],
                    a: Operand { buf: &abuf, at: pa, t: a_t },
                    b: Operand { buf: &bbuf, at: pb, t: b_t },
                    c: (&cbuf, pc),
                    add,
                },
                &mut scratch,
            );
            gpu.queue.submit([enc.finish()]);
            let got = gpu.download(&cbuf, pc, m * n).unwrap();
            close(&format!("{m}×{n}×{k} a_t {a_t} b_t {b_t} add {add}"), &got, &want, 1e-5);
        }
    }
}

/// The networks the GPU runs: a state-vector MLP, a small camera network with every layer
/// kind (scale, strided convs, ReLU after each, dense), a camera + LiDAR network (an embedder
/// per input, then the rest), and embedders alone (SAC's critics' embedder for camera +
/// LiDAR, one input going through as it is).
fn networks(rng: &mut ChaCha8Rng) -> Vec<(&'static str, Net)> {
    use LayerSpec::*;
    let camera = [Scale(1.0 / 255.0), Conv(4, 3, 2), Relu];
    vec![
        ("mlp", Net::new(InputShape::Flat(13), &[Dense(64), Relu, Dense(64), Relu, Dense(5)], Some(0.01), rng)),
        (
            "conv",
            Net::new(
                InputShape::Image(23, 29, 2),
                &[Scale(1.0 / 255.0), Conv(8, 5, 2), Relu, Conv(6, 3, 1), Relu, Dense(32), Relu, Dense(3)],
                None,
                rng,
            ),
        ),
        (
            "camera + lidar",
            Net::new_multi(
                &[("camera", InputShape::Image(12, 16, 1), &camera), ("lidar", InputShape::Flat(8), &[Dense(6), Relu])],
                &[Dense(10), Relu, Dense(3)],
                None,
                rng,
            ),
        ),
        (
            "embedders alone",
            Net::new_multi(
                &[("camera", InputShape::Image(10, 12, 1), &camera), ("lidar", InputShape::Flat(5), &[])],
                &[],
                None,
                rng,
            ),
        ),
    ]
}

/// Issue 33: every layer forward and backward matches faer.
#[test]
fn every_layer_forward_and_backward_matches_faer() {
    let gpu = open();
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    for (name, net) in networks(&mut rng) {
        for batch in [1, 7] {
            let scale = if name == "mlp" { 1.0 } else { 255.0 };
            let x: Vec<f32> = random(batch * net.in_size(), &mut rng).iter().map(|v| (v + 1.0) * 0.5 * scale).collect();
            let d_out = random(batch * net.out_size(), &mut rng);
            let mut tape = Tape::default();
            net.forward(&x, batch, &mut tape, faer::Par::Seq);
            let want_out = tape.output().to_vec();
            let mut want_grad = vec![0.0; net.params.len()];
            let mut want_d_in = Vec::new();
            net.backward_input(&mut tape, &d_out, &mut want_grad, faer::Par::Seq, &mut want_d_in);

            let mut g = GpuNet::new(&gpu, &net, 8).unwrap();
            let xb = gpu.buffer("x", x.len()).unwrap();
            let db = gpu.buffer("d", d_out.len()).unwrap();
            let d_in = gpu.buffer("d_in", x.len()).unwrap();
            gpu.upload(&xb, 0, &x);
            gpu.upload(&db, 0, &d_out);
            let mut enc = gpu.device.create_command_encoder(&Default::default());
            g.forward(&gpu, &mut enc, &xb, batch);
            g.zero_grad(&mut enc);
            g.backward_with(&gpu, &mut enc, &xb, (&db, 0), batch, gpu::Wants { params: true, d_in: Some(&d_in) });
            gpu.queue.submit([enc.finish()]);
            let got_out = gpu.download(g.output(), 0, want_out.len()).unwrap();
            close(&format!("{name} batch {batch} output"), &got_out, &want_out, 1e-5);
            close(&format!("{name} batch {batch} gradient"), &g.read_grad(&gpu).unwrap(), &want_grad, 1e-4);
            let got_d_in = gpu.download(&d_in, 0, x.len()).unwrap();
            close(&format!("{name} batch {batch} input gradient"), &got_d_in, &want_d_in, 1e-4);
            // Without the input gradient (what a loss at the network's end needs), the same
            // parameters' gradient.
            let mut enc = gpu.device.create_command_encoder(&Default::default());
            g.forward(&gpu, &mut enc, &xb, batch);
            g.zero_grad(&mut enc);
            g.backward(&gpu, &mut enc, &xb, &db, batch);
            gpu.queue.submit([enc.finish()]);
            close(&format!("{name} batch {batch} gradient alone"), &g.read_grad(&gpu).unwrap(), &want_grad, 1e-4);
        }
    }
}

/// Issue 33: Adam on the GPU matches the CPU optimiser and flags a non-finite gradient.
#[test]
fn adam_matches_the_cpu_optimiser_and_flags_a_non_finite_gradient() {
    let gpu = open();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let n = 70_000;
    let mut params = random(n, &mut rng);
    let mut adam = Adam::new(n, 3e-4);
    let (p, m, v, g, flag) = (
        gpu.buffer("p", n).unwrap(),
        gpu.buffer("m", n).unwrap(),
        gpu.buffer("v", n).unwrap(),
        gpu.buffer("g", n).unwrap(),
        gpu.buffer("flag", 1).unwrap(),
    );
    gpu.upload(&p, 0, &params);
    for t in 1..=3u32 {
        let mut grad = random(n, &mut rng);
        if t == 3 {
            grad[n / 2] = f32::NAN;
        }
        let finite = adam.step_factored(&mut params, &grad, &[], faer::Par::Seq);
        gpu.upload(&g, 0, &grad);
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        let step = 3e-4 / (1.0 - 0.9f32.powi(t as i32));
        let inv_c2 = 1.0 / (1.0 - 0.999f32.powi(t as i32));
        let constants = AdamStep { b1: 0.9, b2: 0.999, eps: 1e-5, step, inv_c2 };
        gpu.adam(&mut enc, n, [&p, &m, &v], &g, &flag, constants);
        gpu.queue.submit([enc.finish()]);
        let raised = gpu.download(&flag, 0, 1).unwrap()[0].to_bits() != 0;
        assert_eq!(raised, !finite, "step {t}");
        if finite {
            close(&format!("step {t}"), &gpu.download(&p, 0, n).unwrap(), &params, 1e-6);
        }
    }
}
