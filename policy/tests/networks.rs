//! DeepRacer's networks by name: the per-tower parameter counts of DeepRacer's TensorFlow graphs,
//! and the layer shapes for a 120×160×1 frame.

use policy::model::{input_shape, tower_specs};
use policy::nn::{Layer, Net};
use policy::{ModelMetadata, NeuralNetwork};
use rand::SeedableRng;

fn tower(network: NeuralNetwork) -> Net {
    let meta = ModelMetadata::parse(
        &format!(r#"{{"action_space":[{{"steering_angle":0,"speed":1}}],"sensor":["FRONT_FACING_CAMERA"],"neural_network":"{}","version":"5"}}"#, network.name()),
        "m.json",
    )
    .unwrap();
    Net::new(input_shape(&meta, 0), &tower_specs(network), None, &mut rand_chacha::ChaCha8Rng::seed_from_u64(1))
}

#[test]
fn parameter_counts_per_tower_match_deepracer() {
    for (network, params, flatten) in [
        (NeuralNetwork::DeepConvolutionalNetworkShallow, 5_839_520, 11_264),
        (NeuralNetwork::DeepConvolutionalNetwork, 28_742_176, 56_000),
        (NeuralNetwork::DeepConvolutionalNetworkDeep, 2_776_640, 9_216),
    ] {
        let net = tower(network);
        assert_eq!(net.params.len(), params, "{network:?}");
        let first_dense =
            net.layers.iter().find_map(|l| if let Layer::Dense { inp, .. } = l { Some(*inp) } else { None }).unwrap();
        assert_eq!(first_dense, flatten, "{network:?} flatten size");
    }
}

#[test]
fn shallow_layer_shapes_follow_the_reference() {
    let net = tower(NeuralNetwork::DeepConvolutionalNetworkShallow);
    let convs: Vec<[usize; 3]> = net
        .layers
        .iter()
        .filter_map(|l| {
            if let Layer::Conv2d { filters, .. } = l {
                let [h, w] = l.conv_out();
                Some([h, w, *filters])
            } else {
                None
            }
        })
        .collect();
    assert_eq!(convs, vec![[29, 39, 32], [13, 18, 64], [11, 16, 64]]);
    assert_eq!(net.out_size(), 512);
    assert!(
        matches!(net.layers[0], Layer::Scale { factor, .. } if factor == 1.0 / 255.0),
        "pixels scaled /255 inside the model"
    );
}
