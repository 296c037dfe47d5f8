use faer::Par;
use policy::nn::gemm;
use std::time::Instant;
fn main() {
    // (m, n, k, a_t, b_t, label)
    let shapes = [
        (72384, 32, 64, false, true, "conv1 fwd"),
        (32, 64, 72384, true, false, "conv1 dW"),
        (14976, 64, 512, false, true, "conv2 fwd"),
        (64, 512, 14976, true, false, "conv2 dW"),
        (14976, 512, 64, false, false, "conv2 dX"),
        (11264, 64, 576, false, true, "conv3 fwd"),
        (64, 576, 11264, true, false, "conv3 dW"),
        (11264, 576, 64, false, false, "conv3 dX"),
        (64, 512, 11264, false, true, "dense fwd"),
        (512, 11264, 64, true, false, "dense dW"),
        (64, 11264, 512, false, false, "dense dX"),
    ];
    for par in [Par::Seq, Par::rayon(2)] {
        let mut total = 0.0;
        for &(m, n, k, at, bt, label) in &shapes {
            let a = vec![0.5f32; m * k];
            let b = vec![0.25f32; k * n];
            let mut c = vec![0.0f32; m * n];
            gemm(&mut c, m, n, k, &a, at, &b, bt, false, par);
            let t = Instant::now();
            let reps = 5;
            for _ in 0..reps {
                gemm(&mut c, m, n, k, &a, at, &b, bt, true, par);
            }
            let s = t.elapsed().as_secs_f64() / reps as f64;
            total += s;
            println!(
                "{par:?} {label:10} {m}x{n}x{k}: {:.2} ms, {:.1} GFLOP/s",
                s * 1e3,
                2.0 * (m * n * k) as f64 / s / 1e9
            );
        }
        println!(
            "{par:?} total per tower {:.1} ms -> both towers {:.1} ms per minibatch of 64 -> {:.0} samples/s",
            total * 1e3,
            2.0 * total * 1e3,
            64.0 / (2.0 * total)
        );
    }
}
