//! Every layer's backward pass against finite differences, alone and stacked.

use faer::Par;
use policy::nn::{Adam, InputShape, LayerSpec, Net, Tape};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// L = Σ c·y with fixed random c: dL/dy = c.
fn loss(net: &Net, x: &[f32], batch: usize, c: &[f32]) -> f64 {
    let mut tape = Tape::default();
    net.forward(x, batch, &mut tape, Par::Seq);
    tape.output().iter().zip(c).map(|(y, c)| *y as f64 * *c as f64).sum()
}

fn check(input: InputShape, specs: &[LayerSpec], batch: usize, seed: u64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let net = Net::new(input, specs, None, &mut rng);
    check_net(net, batch, &format!("{specs:?}"), &mut rng);
}

fn check_net(mut net: Net, batch: usize, what: &str, rng: &mut ChaCha8Rng) {
    // Non-zero biases so ReLUs sit away from their kink for most units.
    for p in net.params.iter_mut() {
        *p += rng.random_range(-0.05..0.05);
    }
    let x: Vec<f32> = (0..batch * net.in_size()).map(|_| rng.random_range(-1.0..1.0)).collect();
    let c: Vec<f32> = (0..batch * net.out_size()).map(|_| rng.random_range(-1.0..1.0)).collect();
    let mut tape = Tape::default();
    net.forward(&x, batch, &mut tape, Par::Seq);
    let mut grad = vec![0.0f32; net.params.len()];
    net.backward(&mut tape, &c, &mut grad, Par::Seq);
    let h = 2e-3f32;
    let mut checked = 0;
    let mut bad = Vec::new();
    for _ in 0..200 {
        let i = rng.random_range(0..net.params.len());
        let orig = net.params[i];
        net.params[i] = orig + h;
        let up = loss(&net, &x, batch, &c);
        net.params[i] = orig - h;
        let down = loss(&net, &x, batch, &c);
        net.params[i] = orig;
        let numeric = (up - down) / (2.0 * h as f64);
        let analytic = grad[i] as f64;
        checked += 1;
        // f32 rounding in the loss limits the difference quotient to about 1e-3 absolute.
        if (numeric - analytic).abs() > 1.5e-3 + 2e-2 * analytic.abs() {
            bad.push((i, numeric, analytic));
        }
    }
    // A ReLU kink inside ±h can spoil a rare difference quotient; a wrong backward spoils most.
    assert!(
        bad.len() <= checked / 50,
        "{what}: {} of {checked} gradients disagree: {:?}",
        bad.len(),
        &bad[..bad.len().min(5)]
    );
}

#[test]
fn dense_layer() {
    check(InputShape::Flat(7), &[LayerSpec::Dense(5)], 4, 1);
}

#[test]
fn mlp_with_relus() {
    check(
        InputShape::Flat(9),
        &[LayerSpec::Dense(16), LayerSpec::Relu, LayerSpec::Dense(16), LayerSpec::Relu, LayerSpec::Dense(3)],
        6,
        2,
    );
}

#[test]
fn conv_layer_with_stride() {
    check(InputShape::Image(9, 11, 2), &[LayerSpec::Conv(4, 3, 2)], 3, 3);
}

#[test]
fn scaled_conv_stack_into_dense_as_deepracer_builds_it() {
    check(
        InputShape::Image(20, 24, 1),
        &[
            LayerSpec::Scale(1.0 / 255.0 * 200.0),
            LayerSpec::Conv(4, 4, 2),
            LayerSpec::Relu,
            LayerSpec::Conv(6, 3, 1),
            LayerSpec::Relu,
            LayerSpec::Dense(8),
            LayerSpec::Relu,
            LayerSpec::Dense(3),
        ],
        3,
        4,
    );
}

/// A net whose first conv layer unfolds more than `CONV_CHUNK_BYTES` a sample (one sample a
/// chunk) and whose second unfolds two samples a chunk, so that 5 samples go through uneven
/// chunks, and through uneven thread shares on two threads.
fn chunked_conv_net() -> (InputShape, Vec<LayerSpec>) {
    let specs =
        vec![LayerSpec::Conv(8, 4, 1), LayerSpec::Relu, LayerSpec::Conv(4, 3, 2), LayerSpec::Relu, LayerSpec::Dense(3)];
    (InputShape::Image(60, 64, 4), specs)
}

/// Issue 8: conv layers worked a chunk at a time match finite differences.
#[test]
fn conv_layers_worked_a_chunk_at_a_time_match_finite_differences() {
    let (input, specs) = chunked_conv_net();
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let net = Net::new(input, &specs, None, &mut rng);
    assert_eq!(net.layers[0].conv_chunk(), 1, "the first conv layer goes a sample at a time");
    assert_eq!(net.layers[2].conv_chunk(), 2, "the second two samples at a time");
    // Without the ReLUs: a first-layer weight moves 17,000 pre-activations, and the kinks
    // crossed within ±h would spoil the difference quotients (the ReLUs' backward is
    // checked by the tests above, and with these layers by the test below).
    let linear: Vec<LayerSpec> = specs.into_iter().filter(|s| *s != LayerSpec::Relu).collect();
    check(input, &linear, 5, 8);
}

/// Issue 8: conv layers in chunks and thread shares give the whole batch's gradient.
#[test]
fn conv_layers_in_chunks_and_thread_shares_give_the_whole_batchs_gradient() {
    let (input, specs) = chunked_conv_net();
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let net = Net::new(input, &specs, None, &mut rng);
    let batch = 5;
    let x: Vec<f32> = (0..batch * net.in_size()).map(|_| rng.random_range(-1.0..1.0)).collect();
    let c: Vec<f32> = (0..batch * net.out_size()).map(|_| rng.random_range(-1.0..1.0)).collect();
    let run = |x: &[f32], c: &[f32], n: usize, par: Par| {
        let mut tape = Tape::default();
        net.forward(x, n, &mut tape, par);
        let mut grad = vec![0.0f32; net.params.len()];
        net.backward(&mut tape, c, &mut grad, par);
        (tape.output().to_vec(), grad)
    };
    // The reference: each sample alone (one chunk, one share), outputs concatenated and
    // gradients summed in f64.
    let mut out = Vec::new();
    let mut sum = vec![0.0f64; net.params.len()];
    for s in 0..batch {
        let (o, g) = run(&x[s * net.in_size()..(s + 1) * net.in_size()], &c[s * 3..(s + 1) * 3], 1, Par::Seq);
        out.extend(o);
        sum.iter_mut().zip(&g).for_each(|(a, b)| *a += *b as f64);
    }
    let scale = sum.iter().fold(0.0f64, |m, g| m.max(g.abs()));
    for par in [Par::Seq, Par::rayon(2)] {
        let (o, g) = run(&x, &c, batch, par);
        for (a, b) in o.iter().zip(&out) {
            assert!((a - b).abs() <= 1e-5 * (1.0 + b.abs()), "{par:?}: output {a} against {b}");
        }
        let worst = g.iter().zip(&sum).map(|(a, b)| (*a as f64 - b).abs()).fold(0.0, f64::max);
        assert!(worst <= 1e-5 * scale, "{par:?}: a gradient {worst} away from the per-sample sum (scale {scale})");
        assert!(run(&x, &c, batch, par) == (o, g), "{par:?}: the same bits on a second run");
    }
}

/// Issue 8: kernel rows of 8 floats (SHALLOW's and DEEPER's first layer: an 8×8 kernel on
/// one channel, or 4 wide on two) are unfolded by their own copy loop; its backward pass too.
#[test]
fn conv_layers_with_kernel_rows_of_eight_floats_match_finite_differences() {
    check(InputShape::Image(20, 24, 1), &[LayerSpec::Conv(3, 8, 4), LayerSpec::Dense(3)], 2, 10);
    check(InputShape::Image(9, 11, 2), &[LayerSpec::Conv(3, 4, 2), LayerSpec::Dense(3)], 2, 11);
}

/// Every conv layer's output against the convolution's definition, over geometries that
/// take each of im2col's copy loops: (h, w, c, filters, kernel, stride).
#[test]
fn conv_output_matches_a_direct_convolution() {
    for (h, w, c, f, k, s) in [(7, 8, 3, 2, 3, 2), (20, 24, 1, 3, 8, 4), (9, 11, 2, 2, 4, 2), (6, 7, 4, 2, 2, 1)] {
        direct_convolution(h, w, c, f, k, s);
    }
}

fn direct_convolution(h: usize, w: usize, c: usize, f: usize, k: usize, s: usize) {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let net = Net::new(InputShape::Image(h, w, c), &[LayerSpec::Conv(f, k, s)], None, &mut rng);
    let x: Vec<f32> = (0..h * w * c).map(|_| rng.random_range(-1.0..1.0)).collect();
    let mut tape = Tape::default();
    net.forward(&x, 1, &mut tape, Par::Seq);
    let (oh, ow) = ((h - k) / s + 1, (w - k) / s + 1);
    let kkc = k * k * c;
    for oy in 0..oh {
        for ox in 0..ow {
            for fi in 0..f {
                let mut acc = net.params[f * kkc + fi] as f64; // bias
                for ky in 0..k {
                    for kx in 0..k {
                        for ci in 0..c {
                            let xv = x[((oy * s + ky) * w + ox * s + kx) * c + ci] as f64;
                            acc += xv * net.params[fi * kkc + (ky * k + kx) * c + ci] as f64;
                        }
                    }
                }
                let got = tape.output()[(oy * ow + ox) * f + fi] as f64;
                assert!(
                    (got - acc).abs() < 1e-5,
                    "{h}×{w}×{c}, kernel {k}, stride {s}: ({oy},{ox},{fi}): {got} vs {acc}"
                );
            }
        }
    }
}

#[test]
fn adam_minimises_a_quadratic() {
    let target = [3.0f32, -2.0, 0.5];
    let mut p = vec![0.0f32; 3];
    let mut opt = Adam::new(3, 0.1);
    for _ in 0..500 {
        let g: Vec<f32> = p.iter().zip(&target).map(|(a, b)| 2.0 * (a - b)).collect();
        opt.step(&mut p, &g);
    }
    for (a, b) in p.iter().zip(&target) {
        assert!((a - b).abs() < 1e-2, "{p:?}");
    }
    assert_eq!(opt.eps, 1e-5);
    assert_eq!(opt.beta2, 0.999);
}

/// Issue 8: a dense layer's weight gradient left as factors and multiplied out inside the Adam
/// step (in bands of rows, one a thread) gives the step Adam takes on the multiplied-out
/// gradient; the same bits on one thread or two; and a non-finite value anywhere is reported.
#[test]
fn adam_on_factored_weight_gradients_matches_the_multiplied_out_step() {
    use policy::nn::{Deferral, FactoredGrad, Factors};
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    // 37 inputs → 21 outputs (two threads take uneven bands: 11 and 10 rows) → ReLU → 3.
    let net =
        Net::new(InputShape::Flat(37), &[LayerSpec::Dense(21), LayerSpec::Relu, LayerSpec::Dense(3)], None, &mut rng);
    let (batch, n) = (5, net.params.len());
    let x: Vec<f32> = (0..batch * 37).map(|_| rng.random_range(-1.0..1.0)).collect();
    let c: Vec<f32> = (0..batch * 3).map(|_| rng.random_range(-1.0..1.0)).collect();
    let mut tape = Tape::default();
    net.forward(&x, batch, &mut tape, Par::Seq);
    let mut whole = vec![0.0f32; n];
    net.backward(&mut tape, &c, &mut whole, Par::Seq);
    net.forward(&x, batch, &mut tape, Par::Seq);
    let mut rest = vec![0.0f32; n];
    let mut factors: Vec<Factors> = Vec::new();
    net.backward_factored(&mut tape, &c, &mut rest, Par::Seq, Deferral { layers: &[0], factors: &mut factors });
    assert_eq!(factors.len(), 1);
    let f = &factors[0];
    // Two shares (as two learners of a team would send them) and one.
    let split = 2 * f.n_in;
    let one = vec![(&f.x[..], &f.d[..])];
    let two = vec![(&f.x[..split], &f.d[..2 * f.n_out]), (&f.x[split..], &f.d[2 * f.n_out..])];
    let step = |shares: &Vec<(&[f32], &[f32])>, par: Par, bad: Option<usize>| {
        let mut p = net.params.clone();
        let mut opt = Adam::new(n, 1e-3);
        let mut g = rest.clone();
        if let Some(i) = bad {
            g[i] = f32::NAN;
        }
        let mut ok = true;
        for _ in 0..3 {
            let fg = FactoredGrad { offset: f.offset, n_in: f.n_in, n_out: f.n_out, shares: shares.clone() };
            ok &= opt.step_factored(&mut p, &g, &[fg], par);
        }
        (p, ok)
    };
    let mut reference = net.params.clone();
    let mut opt = Adam::new(n, 1e-3);
    for _ in 0..3 {
        opt.step(&mut reference, &whole);
    }
    for shares in [&one, &two] {
        let (p, ok) = step(shares, Par::Seq, None);
        assert!(ok);
        let worst = p.iter().zip(&reference).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        let moved = net.params.iter().zip(&reference).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(worst <= 1e-4 * moved, "off by {worst} of a {moved} move");
        assert_eq!(p, step(shares, Par::rayon(2), None).0, "the same bits on two threads");
    }
    // A NaN outside the factored weights, and one inside (an input of the factors).
    assert!(!step(&one, Par::Seq, Some(n - 1)).1);
    let mut bad_x = f.x.clone();
    bad_x[3] = f32::INFINITY;
    let bad = vec![(&bad_x[..], &f.d[..])];
    assert!(!step(&bad, Par::Seq, None).1);
}

/// Issue 8: Adam's loop runs on the widest vectors the CPU has (runtime dispatch); it must
/// still be the plain IEEE formula, element by element, so that every CPU and every thread
/// count gives the same bits (a fused multiply-add, or any reordering, would fail this).
#[test]
fn adam_on_wide_vectors_gives_the_plain_formulas_bits() {
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    // Not a multiple of any vector width, and long enough for the threaded path's chunks.
    let n = 4 * (1 << 15) + 1003;
    let mut params: Vec<f32> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
    let mut expected = params.clone();
    let (mut m, mut v) = (vec![0.0f32; n], vec![0.0f32; n]);
    let mut adam = Adam::new(n, 3e-4);
    let mut threaded = (Adam::new(n, 3e-4), params.clone());
    for t in 1..=3 {
        // Magnitudes from 1e-30 to 1e10, zeros among them.
        let grad: Vec<f32> =
            (0..n)
                .map(|i| {
                    if i % 97 == 0 {
                        0.0
                    } else {
                        rng.random_range(-1.0f32..1.0) * 10f32.powi(rng.random_range(-30..10))
                    }
                })
                .collect();
        adam.step(&mut params, &grad);
        threaded.0.step_with(&mut threaded.1, &grad, Par::rayon(2));
        let (b1, b2, eps, lr) = (adam.beta1, adam.beta2, adam.eps, adam.lr);
        let step = lr / (1.0 - b1.powi(t));
        let inv_c2 = 1.0 / (1.0 - b2.powi(t));
        for i in 0..n {
            let g = grad[i];
            m[i] = b1 * m[i] + (1.0 - b1) * g;
            v[i] = b2 * v[i] + (1.0 - b2) * g * g;
            expected[i] -= step * m[i] / ((v[i] * inv_c2).sqrt() + eps);
        }
        let differ = (0..n).filter(|&i| params[i].to_bits() != expected[i].to_bits()).count();
        assert_eq!(differ, 0, "step {t}: {differ} of {n} parameters differ from the plain formula's bits");
        assert!(threaded.1.iter().zip(&params).all(|(a, b)| a.to_bits() == b.to_bits()), "step {t}: 2 threads differ");
    }
}

/// Issue 8: a dense layer's forward pass over a batch is made as `outᵀ = b + W · xᵀ` and turned
/// (faster for the camera networks' big layer), over one sample as `x · Wᵀ`: both give every
/// sample the plain product, `y = x Wᵀ + b`, computed here in f64, whatever the batch.
#[test]
fn a_dense_layer_gives_every_batch_size_the_plain_product() {
    let mut rng = ChaCha8Rng::seed_from_u64(18);
    let (n_in, n_out) = (300, 17);
    let mut net = Net::new(InputShape::Flat(n_in), &[LayerSpec::Dense(n_out)], None, &mut rng);
    for p in net.params.iter_mut() {
        *p += rng.random_range(-0.05..0.05);
    }
    let (w, b) = net.params.split_at(n_in * n_out);
    for batch in [1, 2, 3, 8, 64] {
        let x: Vec<f32> = (0..batch * n_in).map(|_| rng.random_range(-1.0..1.0)).collect();
        let mut tape = Tape::default();
        net.forward(&x, batch, &mut tape, Par::Seq);
        let y = tape.output();
        assert_eq!(y.len(), batch * n_out);
        for s in 0..batch {
            for o in 0..n_out {
                let want =
                    b[o] as f64 + (0..n_in).map(|i| x[s * n_in + i] as f64 * w[o * n_in + i] as f64).sum::<f64>();
                let got = y[s * n_out + o] as f64;
                assert!((got - want).abs() < 1e-4, "batch {batch}, sample {s}, output {o}: {got} against {want}");
            }
        }
        // Two threads: the same numbers.
        let mut tape2 = Tape::default();
        net.forward(&x, batch, &mut tape2, Par::rayon(2));
        assert_eq!(tape2.output(), y, "batch {batch} on two threads");
    }
}

/// Issue 8: a forward pass over no samples gives no output: the one-sample orientation of the dense
/// layer once set its bias with one slice copy of the whole output, which panicked on an
/// empty batch.
#[test]
fn a_forward_pass_over_no_samples_gives_no_output() {
    let mut rng = ChaCha8Rng::seed_from_u64(19);
    let net =
        Net::new(InputShape::Flat(10), &[LayerSpec::Dense(4), LayerSpec::Relu, LayerSpec::Dense(2)], None, &mut rng);
    let mut tape = Tape::default();
    net.forward(&[], 0, &mut tape, Par::Seq);
    assert!(tape.output().is_empty());
}

/// DeepRacer's camera + LiDAR network in small: a conv embedder and a dense embedder whose
/// outputs are concatenated into the middleware and the head.
fn two_input_net(rng: &mut ChaCha8Rng) -> Net {
    use LayerSpec::*;
    Net::new_multi(
        &[
            ("FRONT_FACING_CAMERA", InputShape::Image(12, 14, 1), &[Scale(0.5), Conv(4, 3, 2), Relu]),
            ("SECTOR_LIDAR", InputShape::Flat(8), &[Dense(6), Relu, Dense(5), Relu]),
        ],
        &[Dense(7), Relu, Dense(3)],
        None,
        rng,
    )
}

/// Issue 31: a two-input network matches finite differences in every embedder.
#[test]
fn a_two_input_network_matches_finite_differences_in_every_embedder() {
    let mut rng = ChaCha8Rng::seed_from_u64(31);
    let net = two_input_net(&mut rng);
    assert_eq!(net.in_size(), 12 * 14 + 8);
    assert_eq!(net.sections(), [0..3, 3..7, 7..10]);
    check_net(net, 3, "camera + lidar", &mut rng);
    // An input with no embedder of its own goes into the concatenation as it is.
    let net = Net::new_multi(
        &[("A", InputShape::Flat(4), &[LayerSpec::Dense(3), LayerSpec::Relu]), ("B", InputShape::Flat(2), &[])],
        &[LayerSpec::Dense(2)],
        None,
        &mut rng,
    );
    check_net(net, 4, "dense + bare input", &mut rng);
}

/// Issue 31: embedders are concatenated in input order sample by sample.
#[test]
fn embedders_are_concatenated_in_input_order_sample_by_sample() {
    let mut rng = ChaCha8Rng::seed_from_u64(32);
    let net = two_input_net(&mut rng);
    let batch = 3;
    let x: Vec<f32> = (0..batch * net.in_size()).map(|_| rng.random_range(-1.0..1.0)).collect();
    let mut tape = Tape::default();
    net.forward(&x, batch, &mut tape, Par::Seq);
    let got = tape.output().to_vec();
    // The same sums by hand: each embedder as a network of its own, then the rest on the
    // concatenation (camera first, then lidar, per sample).
    let part = |layers: std::ops::Range<usize>| Net {
        layers: net.layers[layers].to_vec(),
        params: net.params.clone(),
        inputs: vec![],
    };
    let (cam, lidar, rest) = (part(0..3), part(3..7), part(7..10));
    let per = net.in_size();
    let mut merged = Vec::new();
    for row in x.chunks(per) {
        cam.forward(&row[..168], 1, &mut tape, Par::Seq);
        merged.extend_from_slice(tape.output());
        lidar.forward(&row[168..], 1, &mut tape, Par::Seq);
        merged.extend_from_slice(tape.output());
    }
    rest.forward(&merged, batch, &mut tape, Par::Seq);
    let want = tape.output().to_vec();
    let off = got.iter().zip(&want).filter(|(a, b)| (*a - *b).abs() > 1e-5).count();
    assert_eq!(off, 0, "{off} of {} outputs differ", want.len());
}

/// dL/dx from `backward_input` against finite differences in the input, and the parameter
/// gradient it adds the same as `backward`'s.
fn check_input_grad(mut net: Net, batch: usize, what: &str, rng: &mut ChaCha8Rng) {
    for p in net.params.iter_mut() {
        *p += rng.random_range(-0.05..0.05);
    }
    let mut x: Vec<f32> = (0..batch * net.in_size()).map(|_| rng.random_range(-1.0..1.0)).collect();
    let c: Vec<f32> = (0..batch * net.out_size()).map(|_| rng.random_range(-1.0..1.0)).collect();
    let mut tape = Tape::default();
    net.forward(&x, batch, &mut tape, Par::Seq);
    let (mut grad, mut d_in) = (vec![0.0f32; net.params.len()], Vec::new());
    net.backward_input(&mut tape, &c, &mut grad, Par::Seq, &mut d_in);
    net.forward(&x, batch, &mut tape, Par::Seq);
    let mut plain = vec![0.0f32; net.params.len()];
    net.backward(&mut tape, &c, &mut plain, Par::Seq);
    assert_eq!(grad, plain, "{what}: the parameter gradient");
    assert_eq!(d_in.len(), x.len());
    let h = 2e-3f32;
    let mut bad = Vec::new();
    let checks = x.len().min(150);
    for k in 0..checks {
        let i = if x.len() <= 150 { k } else { rng.random_range(0..x.len()) };
        let orig = x[i];
        x[i] = orig + h;
        let up = loss(&net, &x, batch, &c);
        x[i] = orig - h;
        let down = loss(&net, &x, batch, &c);
        x[i] = orig;
        let numeric = (up - down) / (2.0 * h as f64);
        if (numeric - d_in[i] as f64).abs() > 1.5e-3 + 2e-2 * (d_in[i] as f64).abs() {
            bad.push((i, numeric, d_in[i]));
        }
    }
    assert!(
        bad.len() <= checks / 50,
        "{what}: {} of {checks} input gradients disagree: {:?}",
        bad.len(),
        &bad[..bad.len().min(5)]
    );
}

/// Issue 32: the gradient w.r.t. the input matches finite differences.
#[test]
fn the_gradient_wrt_the_input_matches_finite_differences() {
    use LayerSpec::*;
    let mut rng = ChaCha8Rng::seed_from_u64(32);
    let mlp = Net::new(InputShape::Flat(9), &[Dense(16), Relu, Dense(16), Relu, Dense(1)], None, &mut rng);
    check_input_grad(mlp, 5, "mlp", &mut rng);
    let conv = Net::new(
        InputShape::Image(12, 14, 2),
        &[Scale(0.5), Conv(4, 3, 2), Relu, Conv(3, 3, 1), Relu, Dense(5), Relu, Dense(2)],
        None,
        &mut rng,
    );
    check_input_grad(conv, 2, "scaled conv stack", &mut rng);
    // SAC's Q head: an embedding and the action side by side; and an embedder of its own.
    let q = Net::new_multi(
        &[("A", InputShape::Flat(6), &[Dense(4), Relu]), ("action", InputShape::Flat(2), &[])],
        &[Dense(8), Relu, Dense(1)],
        None,
        &mut rng,
    );
    check_input_grad(q, 4, "embedder + bare input", &mut rng);
    let parallel = Net::new_multi(
        &[("A", InputShape::Image(6, 6, 1), &[Conv(2, 3, 1), Relu]), ("B", InputShape::Flat(3), &[Scale(2.0)])],
        &[],
        None,
        &mut rng,
    );
    check_input_grad(parallel, 3, "embedders side by side", &mut rng);
}

/// Issue 55: a camera network's forward and backward pass with bf16 products (on a CPU with
/// AVX-512 BF16) stays within bf16's rounding of the f32 pass, and is not the f32 pass; on a
/// CPU without it, bf16 asks give the f32 pass bit for bit.
#[test]
fn bf16_products_give_the_f32_pass_to_bf16s_rounding() {
    use policy::nn::Precision;
    let mut rng = ChaCha8Rng::seed_from_u64(55);
    let specs = [
        LayerSpec::Conv(8, 4, 2),
        LayerSpec::Relu,
        LayerSpec::Conv(16, 3, 1),
        LayerSpec::Relu,
        LayerSpec::Dense(32),
        LayerSpec::Relu,
        LayerSpec::Dense(5),
    ];
    let net = Net::new(InputShape::Image(24, 32, 1), &specs, None, &mut rng);
    let batch = 16;
    let x: Vec<f32> = (0..batch * net.in_size()).map(|_| rng.random_range(-1.0..1.0)).collect();
    let d: Vec<f32> = (0..batch * net.out_size()).map(|_| rng.random_range(-1.0..1.0)).collect();
    let pass = |precision: Precision, par: Par| {
        let mut tape = Tape::default();
        tape.precision = precision;
        net.forward(&x, batch, &mut tape, par);
        let out = tape.output().to_vec();
        let mut grad = vec![0.0f32; net.params.len()];
        net.backward(&mut tape, &d, &mut grad, par);
        (out, grad)
    };
    let (out32, grad32) = pass(Precision::F32, Par::Seq);
    let (out16, grad16) = pass(Precision::Bf16, Par::Seq);
    let rel = |a: &[f32], b: &[f32]| {
        let diff: f64 = a.iter().zip(b).map(|(x, y)| (*x as f64 - *y as f64).powi(2)).sum();
        let norm: f64 = b.iter().map(|y| (*y as f64).powi(2)).sum();
        (diff / norm).sqrt()
    };
    if Precision::bf16_available() {
        // bf16 keeps 8 bits of mantissa: 0.4 % an operand at worst, less over sums.
        assert!(rel(&out16, &out32) < 1e-2, "outputs {}", rel(&out16, &out32));
        assert!(rel(&grad16, &grad32) < 2e-2, "gradients {}", rel(&grad16, &grad32));
        assert!(out16 != out32 && grad16 != grad32, "the bf16 pass made the f32 products");
        assert_eq!(pass(Precision::Bf16, Par::rayon(2)).0, out16, "the forward pass depends on the threads");
    } else {
        assert_eq!((out16, grad16), (out32, grad32));
    }
}
