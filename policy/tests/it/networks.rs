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
    Net::new(input_shape(&meta, 0), &tower_specs(network, false), None, &mut rand_chacha::ChaCha8Rng::seed_from_u64(1))
}

fn stereo_tower(network: NeuralNetwork) -> Net {
    let meta = ModelMetadata::parse(
        &format!(r#"{{"action_space":[{{"steering_angle":0,"speed":1}}],"sensor":["STEREO_CAMERAS"],"neural_network":"{}","version":"5"}}"#, network.name()),
        "m.json",
    )
    .unwrap();
    policy::ActorCritic::new(&meta, 0, &mut rand_chacha::ChaCha8Rng::seed_from_u64(1)).pi
}

/// Issue 31: stereo towers are DeepRacer's.
#[test]
fn stereo_towers_are_deepracers() {
    // 120×160×2. SHALLOW: the front camera's embedder with two input channels (11×16×64).
    // DEEP and DEEPER: DeepRacer's stereo embedder (32,3,1)(64,3,2)(64,3,1)(128,3,2)(128,3,1),
    // 25×35×128, then Dense 512, or 256 and 128.
    let conv = |k: usize, c: usize, f: usize| k * k * c * f + f;
    let stereo_convs = conv(3, 2, 32) + conv(3, 32, 64) + conv(3, 64, 64) + conv(3, 64, 128) + conv(3, 128, 128);
    let flat = 25 * 35 * 128;
    for (network, flatten, params) in [
        (NeuralNetwork::DeepConvolutionalNetworkShallow, 11_264, 5_839_520 + 8 * 8 * 32),
        (NeuralNetwork::DeepConvolutionalNetwork, flat, stereo_convs + flat * 512 + 512),
        (NeuralNetwork::DeepConvolutionalNetworkDeep, flat, stereo_convs + flat * 256 + 256 + 256 * 128 + 128),
    ] {
        let net = stereo_tower(network);
        assert_eq!(net.in_size(), 120 * 160 * 2);
        let first_dense =
            net.layers.iter().find_map(|l| if let Layer::Dense { inp, .. } = l { Some(*inp) } else { None }).unwrap();
        assert_eq!(first_dense, flatten, "{network:?} flatten size");
        // Without the head (Dense to the 1 action).
        let head = net.out_size()
            * net
                .layers
                .iter()
                .rev()
                .find_map(|l| if let Layer::Dense { inp, .. } = l { Some(*inp) } else { None })
                .unwrap()
            + net.out_size();
        assert_eq!(net.params.len() - head, params, "{network:?}");
    }
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

/// Issue 31: camera and LiDAR networks concatenate embedders in DeepRacer's order.
#[test]
fn camera_and_lidar_networks_concatenate_embedders_in_deepracers_order() {
    let meta = |sensors: &str, network: NeuralNetwork| {
        ModelMetadata::parse(
            &format!(
                r#"{{"action_space":[{{"steering_angle":0,"speed":1}},{{"steering_angle":10,"speed":1}}],"sensor":[{sensors}],"neural_network":"{}","version":"5"}}"#,
                network.name()
            ),
            "m.json",
        )
        .unwrap()
    };
    let shallow = NeuralNetwork::DeepConvolutionalNetworkShallow;
    let lidar_embedder = |n: usize| n * 256 + 256 + 256 * 256 + 256;
    // (sensors, inputs in order, merged width, parameters of the policy tower)
    let camera = tower(shallow).params.len();
    let mono_convs = camera - 11_264 * 512 - 512;
    let table = [
        (r#""FRONT_FACING_CAMERA","SECTOR_LIDAR""#, vec!["FRONT_FACING_CAMERA", "SECTOR_LIDAR"], 11_264 + 256, 8),
        (r#""FRONT_FACING_CAMERA","LIDAR""#, vec!["FRONT_FACING_CAMERA", "LIDAR"], 11_264 + 256, 64),
        (
            r#""FRONT_FACING_CAMERA","DISCRETIZED_SECTOR_LIDAR""#,
            vec!["DISCRETIZED_SECTOR_LIDAR", "FRONT_FACING_CAMERA"],
            256 + 11_264,
            64,
        ),
        (r#""STEREO_CAMERAS","LIDAR""#, vec!["LIDAR", "STEREO_CAMERAS"], 256 + 11_264, 64),
        (r#""STEREO_CAMERAS","SECTOR_LIDAR""#, vec!["SECTOR_LIDAR", "STEREO_CAMERAS"], 256 + 11_264, 8),
    ];
    for (sensors, order, merged, lidar) in table {
        let m = meta(sensors, shallow);
        let net = policy::ActorCritic::new(&m, 0, &mut rand_chacha::ChaCha8Rng::seed_from_u64(1)).pi;
        let names: Vec<&str> = net.inputs.iter().map(|e| e.name.as_str()).collect();
        assert_eq!(names, order, "{sensors}");
        let frame = if sensors.contains("STEREO") { 2 * 19_200 } else { 19_200 };
        assert_eq!(net.in_size(), frame + lidar, "{sensors}");
        assert_eq!(policy::model::input_size(&m, 0), frame + lidar, "{sensors}");
        let trunk = net.sections().last().unwrap().start;
        assert!(matches!(net.layers[trunk], Layer::Dense { inp, out: 512, .. } if inp == merged), "{sensors}");
        let convs = if sensors.contains("STEREO") { mono_convs + 8 * 8 * 32 } else { mono_convs };
        let head = 512 * 2 + 2;
        assert_eq!(net.params.len(), convs + lidar_embedder(lidar) + merged * 512 + 512 + head, "{sensors}");
    }
}

/// Issue 55: acting with the policy tower alone chooses as acting with both towers does, from
/// the same random stream (sampled and deterministic, for each head), and says no value.
#[test]
fn acting_with_the_policy_tower_alone_chooses_as_both_towers_do() {
    use rand::SeedableRng;
    let camera =
        r#""sensor":["FRONT_FACING_CAMERA"],"neural_network":"DEEP_CONVOLUTIONAL_NETWORK_SHALLOW","version":"5""#;
    for (head, meta) in [
        (
            "discrete",
            format!(
                r#"{{"action_space":[{{"steering_angle":-30,"speed":1}},{{"steering_angle":0,"speed":2}},{{"steering_angle":30,"speed":1}}],{camera}}}"#
            ),
        ),
        (
            "continuous",
            format!(
                r#"{{"action_space":{{"steering_angle":{{"low":-30,"high":30}},"speed":{{"low":0.5,"high":2}}}},"action_space_type":"continuous",{camera}}}"#
            ),
        ),
        (
            "SAC",
            format!(
                r#"{{"action_space":{{"steering_angle":{{"low":-30,"high":30}},"speed":{{"low":0.5,"high":2}}}},"action_space_type":"continuous","training_algorithm":"sac",{camera}}}"#
            ),
        ),
    ] {
        let meta = ModelMetadata::parse(&meta, "m.json").unwrap();
        let model = policy::ActorCritic::new(&meta, 0, &mut rand_chacha::ChaCha8Rng::seed_from_u64(2));
        let batch = 3;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let obs: Vec<f32> = (0..batch * model.obs_size()).map(|_| rand::Rng::random::<f32>(&mut rng)).collect();
        for deterministic in [false, true] {
            let (mut a, mut b) = (rand_chacha::ChaCha8Rng::seed_from_u64(4), rand_chacha::ChaCha8Rng::seed_from_u64(4));
            let both = model.act(&obs, batch, deterministic, &mut a, faer::Par::Seq);
            let alone = model.act_policy(&obs, batch, deterministic, &mut b, faer::Par::Seq);
            assert_eq!(both.len(), batch);
            for (x, y) in both.iter().zip(&alone) {
                assert_eq!((x.choice, x.logp), (y.choice, y.logp), "{head}, deterministic {deterministic}");
                assert_eq!(y.value, 0.0, "{head}");
            }
            assert!(both.iter().any(|x| x.value != 0.0), "{head}: both towers give values");
        }
    }
}
