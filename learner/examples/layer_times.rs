//! Time forward and backward of prefixes of the SHALLOW tower to see where time goes.
use faer::Par;
use policy::nn::{InputShape, LayerSpec, Net, Tape};
use rand::SeedableRng;
use std::time::Instant;
fn main() {
    let mut specs = policy::model::tower_specs(policy::NeuralNetwork::DeepConvolutionalNetworkShallow, false);
    specs.push(LayerSpec::Dense(5));
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    for (n, par) in [(64, Par::rayon(2)), (1, Par::Seq)] {
        let x: Vec<f32> = (0..n * 19200).map(|i| (i % 251) as f32).collect();
        for upto in [2, 4, 6, 8, 10] {
            let net = Net::new(InputShape::Image(120, 160, 1), &specs[..upto], None, &mut rng);
            let mut tape = Tape::default();
            let mut grad = vec![0.0; net.params.len()];
            net.forward(&x, n, &mut tape, par);
            let d = vec![0.01f32; n * net.out_size()];
            net.backward(&mut tape, &d, &mut grad, par);
            let reps = if n == 1 { 200 } else { 5 };
            let t = Instant::now();
            for _ in 0..reps {
                net.forward(&x, n, &mut tape, par);
            }
            let f = t.elapsed().as_secs_f64() / reps as f64;
            let t = Instant::now();
            for _ in 0..reps {
                net.backward(&mut tape, &d, &mut grad, par);
            }
            let b = t.elapsed().as_secs_f64() / reps as f64;
            println!(
                "batch {n} layers ..{upto:2} ({:?}): forward {:.3} ms, backward {:.3} ms",
                specs[upto - 1],
                f * 1e3,
                b * 1e3
            );
        }
    }
}
