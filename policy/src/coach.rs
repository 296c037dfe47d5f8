//! rl_coach's variables: a Paddock model as the checkpoint DeepRacer's trainer saves and
//! restores, every network with its TF1 names and shapes, and back.
//!
//! rl_coach saves the trainable variables of the online networks only (no optimiser slots,
//! no target networks: `savers.py`), named by scope:
//!
//! - clipped PPO: `main_level/agent/main/online/network_0` is the value network (head
//!   `v_values_head_0/output`), `network_1` the policy (`ppo_head_0/policy_fc` for a discrete
//!   space; `ppo_head_0/policy_mean` and the `[1, 2]` `ppo_head_0/policy_log_std` for a
//!   continuous one);
//! - SAC: `main_level/agent/policy/online/network_0` (head `sac_policy_head_0/dense`, then
//!   `policy_mean` and `dense_1`, the log-stds), `main_level/agent/q/online/network_0` (the
//!   sensors' embedders alone, then `q_values_head_0/q1_head/{dense,dense_1,q1_output}` and the
//!   same under `q2_head`), `main_level/agent/v/online/network_0` (`v_values_head_0/output`).
//!
//! In each network every sensor has an embedder scope named after it (`FRONT_FACING_CAMERA`,
//! `STEREO_CAMERAS`, `LIDAR`, …) whose layers rl_coach numbers 0, 2, 4, … (an activation
//! between each): `Conv2d_K` kernels `[k, k, in, out]`, and `Dense_K` `[in, out]`, both for a
//! LiDAR's layers and for a camera scheme's dense layers on the image (Paddock's 1×1
//! convolutions); then `middleware_fc_embedder/Dense_K`; then the head; and each network's
//! `gradients_from_head_0-0_rescalers`, a scalar 1.
//!
//! Paddock's SAC critics take the actions as the policy gives them, in [-1, 1]; DeepRacer's
//! Q heads take them in the environment's units (degrees, m/s). The first layer of each Q head
//! is rescaled on the way out and back, so both compute the same Q.

use crate::metadata::{ActionSpace, ModelMetadata, TrainingAlgorithm};
use crate::model::{ActorCritic, Head};
use crate::nn::{Layer, Net};
use crate::tfckpt::{Checkpoint, DT_FLOAT, Tensor};
use crate::tfgraph::{GraphError, Names};
use std::collections::BTreeSet;

/// SAC's critics as a model folder keeps them beside the policy and V.
#[derive(Clone, Debug, PartialEq)]
pub struct SacCritics {
    /// The Q network's sensor embedders (none where the input goes to the heads as it is).
    pub embed: Option<Net>,
    /// `q1_head`.
    pub q1: Net,
    /// `q2_head`.
    pub q2: Net,
}

/// Why a model could not become a checkpoint, or a checkpoint a model.
#[derive(Debug, thiserror::Error)]
pub enum CoachError {
    /// The model is one DeepRacer has no network for.
    #[error(transparent)]
    Unsupported(#[from] GraphError),
    /// A SAC model without its critics.
    #[error("a SAC model's checkpoint holds its Q and V networks: {0}")]
    NoCritics(String),
    /// A variable the network needs is missing, or has another shape or type.
    #[error("{0}")]
    Mismatch(String),
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Buf {
    Pi,
    V,
    LogStd,
    QEmbed,
    Q1,
    Q2,
}

/// One variable: its name and TensorFlow shape, and where each of its values (in TensorFlow's
/// order) sits in one of the model's parameter vectors (none: a constant, the rescalers).
struct Slot {
    name: String,
    shape: Vec<usize>,
    buf: Option<Buf>,
    idx: Vec<u32>,
}

fn dense_slots(scope: &str, layer: &Layer, rows: std::ops::Range<usize>, buf: Buf, bias: bool, out: &mut Vec<Slot>) {
    let Layer::Dense { inp, out: n, offset } = *layer else { unreachable!("a dense layer") };
    let r = rows.len();
    let mut k = Vec::with_capacity(inp * r);
    for i in 0..inp {
        for o in rows.clone() {
            k.push((offset + o * inp + i) as u32);
        }
    }
    out.push(Slot { name: format!("{scope}/kernel"), shape: vec![inp, r], buf: Some(buf), idx: k });
    if bias {
        let b = rows.map(|o| (offset + inp * n + o) as u32).collect();
        out.push(Slot { name: format!("{scope}/bias"), shape: vec![r], buf: Some(buf), idx: b });
    }
}

/// A convolution as `Conv2d_K` (`[k, k, c, f]`), or a 1×1 one as the dense layer on the image
/// it stands for (`Dense_K`, `[c, f]`).
fn conv_slots(scope: &str, own: usize, layer: &Layer, buf: Buf, out: &mut Vec<Slot>) {
    let Layer::Conv2d { input: [_, _, c], filters, kernel, stride, offset } = *layer else { unreachable!("a conv") };
    let kkc = kernel * kernel * c;
    let mut k = Vec::with_capacity(kkc * filters);
    for j in 0..kkc {
        for f in 0..filters {
            k.push((offset + f * kkc + j) as u32);
        }
    }
    let (name, shape) = if kernel == 1 && stride == 1 {
        (format!("{scope}/Dense_{}", 2 * own), vec![c, filters])
    } else {
        (format!("{scope}/Conv2d_{}", 2 * own), vec![kernel, kernel, c, filters])
    };
    out.push(Slot { name: format!("{name}/kernel"), shape, buf: Some(buf), idx: k });
    let b = (0..filters).map(|f| (offset + kkc * filters + f) as u32).collect();
    out.push(Slot { name: format!("{name}/bias"), shape: vec![filters], buf: Some(buf), idx: b });
}

/// An embedder's layers `range` of `net` under `scope`.
fn embedder_slots(scope: &str, net: &Net, range: std::ops::Range<usize>, buf: Buf, out: &mut Vec<Slot>) {
    let mut own = 0;
    for layer in &net.layers[range] {
        match layer {
            Layer::Conv2d { .. } => conv_slots(scope, own, layer, buf, out),
            Layer::Dense { .. } => {
                dense_slots(&format!("{scope}/Dense_{}", 2 * own), layer, 0..layer.out_size(), buf, true, out)
            }
            _ => continue,
        }
        own += 1;
    }
}

/// The head a tower ends in.
#[derive(Clone, Copy, PartialEq)]
enum HeadKind {
    Value,
    Discrete,
    Continuous,
    Sac,
}

/// A tower (`net`, in `buf`) under the network scope `scope`: its embedders, middleware and
/// head; `sensor` names a one-input network's embedder.
fn tower_slots(scope: &str, net: &Net, buf: Buf, sensor: &str, head: HeadKind, out: &mut Vec<Slot>) {
    let sections = net.sections();
    let trunk = if net.inputs.is_empty() {
        let first_dense = net.layers.iter().position(|l| matches!(l, Layer::Dense { .. })).unwrap_or(net.layers.len());
        embedder_slots(&format!("{scope}/{sensor}"), net, 0..first_dense, buf, out);
        first_dense..net.layers.len()
    } else {
        for (e, r) in net.inputs.iter().zip(&sections) {
            embedder_slots(&format!("{scope}/{}", e.name), net, r.clone(), buf, out);
        }
        sections.last().expect("the rest").clone()
    };
    let denses: Vec<&Layer> = net.layers[trunk].iter().filter(|l| matches!(l, Layer::Dense { .. })).collect();
    let in_head = if head == HeadKind::Sac { 2 } else { 1 };
    let (middle, heads) = denses.split_at(denses.len() - in_head);
    for (j, l) in middle.iter().enumerate() {
        dense_slots(&format!("{scope}/middleware_fc_embedder/Dense_{}", 2 * j), l, 0..l.out_size(), buf, true, out);
    }
    let last = heads[heads.len() - 1];
    match head {
        HeadKind::Value => dense_slots(&format!("{scope}/v_values_head_0/output"), last, 0..1, buf, true, out),
        HeadKind::Discrete => {
            dense_slots(&format!("{scope}/ppo_head_0/policy_fc"), last, 0..last.out_size(), buf, true, out)
        }
        HeadKind::Continuous => {
            dense_slots(&format!("{scope}/ppo_head_0/policy_mean"), last, 0..2, buf, true, out);
            let name = format!("{scope}/ppo_head_0/policy_log_std");
            out.push(Slot { name, shape: vec![1, 2], buf: Some(Buf::LogStd), idx: vec![0, 1] });
        }
        HeadKind::Sac => {
            let h = format!("{scope}/sac_policy_head_0");
            dense_slots(&format!("{h}/dense"), heads[0], 0..heads[0].out_size(), buf, true, out);
            dense_slots(&format!("{h}/policy_mean"), last, 0..2, buf, true, out);
            dense_slots(&format!("{h}/dense_1"), last, 2..4, buf, true, out);
        }
    }
    out.push(Slot {
        name: format!("{scope}/gradients_from_head_0-0_rescalers"),
        shape: vec![],
        buf: None,
        idx: vec![],
    });
}

/// A Q head's dense layers: `dense`, `dense_1`, …, then `qN_output`.
fn q_head_slots(scope: &str, net: &Net, buf: Buf, n: usize, out: &mut Vec<Slot>) {
    let denses: Vec<&Layer> = net.layers.iter().filter(|l| matches!(l, Layer::Dense { .. })).collect();
    for (j, l) in denses.iter().enumerate() {
        let name = if j + 1 == denses.len() {
            format!("q{n}_output")
        } else if j == 0 {
            "dense".to_string()
        } else {
            format!("dense_{j}")
        };
        dense_slots(&format!("{scope}/q_values_head_0/q{n}_head/{name}"), l, 0..l.out_size(), buf, true, out);
    }
}

/// Every variable rl_coach saves for `meta`'s model, laid over Paddock's networks.
fn slots(meta: &ModelMetadata, model: &ActorCritic, critics: Option<&SacCritics>) -> Result<Vec<Slot>, CoachError> {
    let names = Names::of(meta)?;
    let sensor = names.sensor;
    let mut out = Vec::new();
    match meta.training_algorithm {
        TrainingAlgorithm::ClippedPpo => {
            let p = "main_level/agent/main/online";
            tower_slots(&format!("{p}/network_0"), &model.v, Buf::V, sensor, HeadKind::Value, &mut out);
            let head = match model.head {
                Head::Categorical(_) => HeadKind::Discrete,
                _ => HeadKind::Continuous,
            };
            tower_slots(&format!("{p}/network_1"), &model.pi, Buf::Pi, sensor, head, &mut out);
        }
        TrainingAlgorithm::Sac => {
            let Some(c) = critics else {
                return Err(CoachError::NoCritics("this model has none beside it".into()));
            };
            let p = "main_level/agent/policy/online/network_0";
            tower_slots(p, &model.pi, Buf::Pi, sensor, HeadKind::Sac, &mut out);
            let q = "main_level/agent/q/online/network_0";
            if let Some(e) = &c.embed {
                if e.inputs.is_empty() {
                    embedder_slots(&format!("{q}/{sensor}"), e, 0..e.layers.len(), Buf::QEmbed, &mut out);
                } else {
                    for (inp, r) in e.inputs.iter().zip(e.sections()) {
                        embedder_slots(&format!("{q}/{}", inp.name), e, r, Buf::QEmbed, &mut out);
                    }
                }
            }
            q_head_slots(q, &c.q1, Buf::Q1, 1, &mut out);
            q_head_slots(q, &c.q2, Buf::Q2, 2, &mut out);
            out.push(Slot {
                name: format!("{q}/gradients_from_head_0-0_rescalers"),
                shape: vec![],
                buf: None,
                idx: vec![],
            });
            let v = "main_level/agent/v/online/network_0";
            tower_slots(v, &model.v, Buf::V, sensor, HeadKind::Value, &mut out);
        }
    }
    Ok(out)
}

/// The environment's scale and offset of each action (steering, speed) for SAC's Q heads.
fn action_units(meta: &ModelMetadata) -> [(f32, f32); 2] {
    match &meta.action_space {
        ActionSpace::Continuous { steering_angle: s, speed: v } => {
            let u = |r: &(f64, f64)| (((r.1 - r.0) / 2.0) as f32, ((r.1 + r.0) / 2.0) as f32);
            [u(s), u(v)]
        }
        ActionSpace::Discrete(_) => [(1.0, 0.0); 2],
    }
}

/// A Q head's first layer, its last two inputs (the actions) from Paddock's [-1, 1] to the
/// environment's units (`to_env`), or back.
fn rescale_q(net: &mut Net, units: [(f32, f32); 2], to_env: bool) {
    let Some(&Layer::Dense { inp, out, offset }) = net.layers.iter().find(|l| matches!(l, Layer::Dense { .. })) else {
        return;
    };
    for o in 0..out {
        let mut shift = 0.0f32;
        for (d, &(scale, bias)) in units.iter().enumerate() {
            let w = &mut net.params[offset + o * inp + inp - 2 + d];
            if to_env {
                *w /= scale;
                shift += *w * bias;
            } else {
                shift += *w * bias;
                *w *= scale;
            }
        }
        let b = &mut net.params[offset + inp * out + o];
        if to_env {
            *b -= shift;
        } else {
            *b += shift;
        }
    }
}

/// `model` (and for SAC its critics) as rl_coach's checkpoint for `meta`.
pub fn to_checkpoint(
    meta: &ModelMetadata,
    model: &ActorCritic,
    critics: Option<&SacCritics>,
) -> Result<Checkpoint, CoachError> {
    let critics = critics.map(|c| {
        let mut c = c.clone();
        for q in [&mut c.q1, &mut c.q2] {
            rescale_q(q, action_units(meta), true);
        }
        c
    });
    let log_std = match model.head {
        Head::Gaussian { log_std } => log_std.to_vec(),
        _ => vec![],
    };
    let empty = Vec::new();
    let buf = |b: Buf| -> &[f32] {
        match b {
            Buf::Pi => &model.pi.params,
            Buf::V => &model.v.params,
            Buf::LogStd => &log_std,
            Buf::QEmbed => critics.as_ref().and_then(|c| c.embed.as_ref()).map_or(&empty, |e| &e.params),
            Buf::Q1 => &critics.as_ref().expect("critics").q1.params,
            Buf::Q2 => &critics.as_ref().expect("critics").q2.params,
        }
    };
    let mut out = Checkpoint::new();
    for s in slots(meta, model, critics.as_ref())? {
        let values: Vec<f32> = match s.buf {
            Some(b) => {
                let src = buf(b);
                s.idx.iter().map(|&i| src[i as usize]).collect()
            }
            None => vec![1.0],
        };
        out.insert(s.name, Tensor::float(s.shape, &values));
    }
    Ok(out)
}

/// What [`from_checkpoint`] read.
#[derive(Clone, Debug)]
pub struct Restored {
    /// The policy and value networks.
    pub model: ActorCritic,
    /// SAC's critics.
    pub critics: Option<SacCritics>,
    /// Variables of the checkpoint that no network of `meta` has (another agent's, or the
    /// optimiser's, when a checkpoint carries them).
    pub unused: Vec<String>,
}

/// The networks of `meta` from rl_coach's checkpoint: every variable they have must be there
/// with its shape (a missing one, or one of another shape or type, is named); the rest of the
/// checkpoint is listed in [`Restored::unused`].
pub fn from_checkpoint(ckpt: &Checkpoint, meta: &ModelMetadata) -> Result<Restored, CoachError> {
    use rand::SeedableRng;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut model = ActorCritic::new(meta, 0, &mut rng);
    let mut critics = (meta.training_algorithm == TrainingAlgorithm::Sac).then(|| SacCritics {
        embed: crate::model::sac_q_embedder(meta, 0, &mut rng),
        q1: crate::model::sac_q_head(q_width(meta, &model), &mut rng),
        q2: crate::model::sac_q_head(q_width(meta, &model), &mut rng),
    });
    let layout = slots(meta, &model, critics.as_ref())?;
    let mut log_std = vec![0.0f32; 2];
    let mut used = BTreeSet::new();
    for s in &layout {
        let Some(t) = ckpt.get(&s.name) else {
            if s.buf.is_none() {
                continue;
            }
            return Err(CoachError::Mismatch(format!(
                "no variable {} {:?}: the checkpoint is not {} {} for {}",
                s.name,
                s.shape,
                meta.training_algorithm.name(),
                meta.neural_network.name(),
                meta.sensor.iter().map(|x| x.name()).collect::<Vec<_>>().join(" + ")
            )));
        };
        used.insert(s.name.as_str());
        if t.dtype != DT_FLOAT || t.shape != s.shape {
            return Err(CoachError::Mismatch(format!(
                "variable {} is {:?} of dtype {}, the network's is {:?} float (another network, sensor or action count)",
                s.name, t.shape, t.dtype, s.shape
            )));
        }
        let Some(b) = s.buf else { continue };
        let values = t.floats().expect("a float tensor");
        let dst: &mut [f32] = match b {
            Buf::Pi => &mut model.pi.params,
            Buf::V => &mut model.v.params,
            Buf::LogStd => &mut log_std,
            Buf::QEmbed => &mut critics.as_mut().and_then(|c| c.embed.as_mut()).expect("an embedder").params,
            Buf::Q1 => &mut critics.as_mut().expect("critics").q1.params,
            Buf::Q2 => &mut critics.as_mut().expect("critics").q2.params,
        };
        for (&i, v) in s.idx.iter().zip(values) {
            dst[i as usize] = v;
        }
    }
    if let Head::Gaussian { log_std: l } = &mut model.head {
        *l = [log_std[0], log_std[1]];
    }
    if let Some(c) = critics.as_mut() {
        for q in [&mut c.q1, &mut c.q2] {
            rescale_q(q, action_units(meta), false);
        }
    }
    let unused = ckpt.keys().filter(|k| !used.contains(k.as_str())).cloned().collect();
    Ok(Restored { model, critics, unused })
}

/// The width of SAC's Q embedding (the heads take it and the two actions).
fn q_width(meta: &ModelMetadata, model: &ActorCritic) -> usize {
    use rand::SeedableRng;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    crate::model::sac_q_embedder(meta, 0, &mut rng).map_or(model.pi.in_size(), |e| e.out_size())
}

/// Every variable name and shape rl_coach saves for `meta`, in name order (what DeepRacer's
/// trainer restores).
pub fn variables(meta: &ModelMetadata) -> Result<Vec<(String, Vec<usize>)>, CoachError> {
    use rand::SeedableRng;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let model = ActorCritic::new(meta, 0, &mut rng);
    let critics = (meta.training_algorithm == TrainingAlgorithm::Sac).then(|| SacCritics {
        embed: crate::model::sac_q_embedder(meta, 0, &mut rng),
        q1: crate::model::sac_q_head(q_width(meta, &model), &mut rng),
        q2: crate::model::sac_q_head(q_width(meta, &model), &mut rng),
    });
    let mut v: Vec<(String, Vec<usize>)> =
        slots(meta, &model, critics.as_ref())?.into_iter().map(|s| (s.name, s.shape)).collect();
    v.sort();
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metadata::{NeuralNetwork, Sensor};
    use rand::SeedableRng;

    fn metas() -> Vec<ModelMetadata> {
        let mut out = Vec::new();
        for network in [
            NeuralNetwork::DeepConvolutionalNetworkShallow,
            NeuralNetwork::DeepConvolutionalNetwork,
            NeuralNetwork::DeepConvolutionalNetworkDeep,
        ] {
            for sensors in [
                "[\"FRONT_FACING_CAMERA\"]",
                "[\"STEREO_CAMERAS\", \"LIDAR\"]",
                "[\"FRONT_FACING_CAMERA\", \"SECTOR_LIDAR\"]",
            ] {
                for (algo, space) in [
                    (
                        "clipped_ppo",
                        "[{\"steering_angle\": -30, \"speed\": 1}, {\"steering_angle\": 30, \"speed\": 2}]",
                    ),
                    (
                        "clipped_ppo",
                        "{\"steering_angle\": {\"low\": -30, \"high\": 30}, \"speed\": {\"low\": 0.5, \"high\": 3}}",
                    ),
                    (
                        "sac",
                        "{\"steering_angle\": {\"low\": -30, \"high\": 30}, \"speed\": {\"low\": 0.5, \"high\": 3}}",
                    ),
                ] {
                    // The whole grid for SHALLOW; for the deeper networks (slow to draw) one camera
                    // model and one of each other sensor set.
                    let shallow = network == NeuralNetwork::DeepConvolutionalNetworkShallow;
                    let front = sensors == "[\"FRONT_FACING_CAMERA\"]";
                    let wanted = shallow
                        || (front && algo == "clipped_ppo" && space.starts_with('['))
                        || (!front && algo == "sac");
                    if !wanted {
                        continue;
                    }
                    let text = format!(
                        "{{\"action_space\": {space}, \"sensor\": {sensors}, \"neural_network\": \"{}\", \"training_algorithm\": \"{algo}\", \"action_space_type\": \"{}\", \"version\": \"5\"}}",
                        network.name(),
                        if space.starts_with('[') { "discrete" } else { "continuous" }
                    );
                    out.push(ModelMetadata::parse(&text, "test").unwrap());
                }
            }
        }
        out
    }

    fn random_model(meta: &ModelMetadata, seed: u64) -> (ActorCritic, Option<SacCritics>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut model = ActorCritic::new(meta, 0, &mut rng);
        if let Head::Gaussian { log_std } = &mut model.head {
            *log_std = [-0.3, 0.2];
        }
        let critics = (meta.training_algorithm == TrainingAlgorithm::Sac).then(|| {
            let embed = crate::model::sac_q_embedder(meta, 0, &mut rng);
            let w = embed.as_ref().map_or(model.pi.in_size(), |e| e.out_size());
            SacCritics { embed, q1: crate::model::sac_q_head(w, &mut rng), q2: crate::model::sac_q_head(w, &mut rng) }
        });
        (model, critics)
    }

    /// Issue 53: for every network, sensor set and algorithm, the variables cover every
    /// parameter exactly once, and a model comes back from its checkpoint as it was.
    #[test]
    fn every_parameter_is_one_variable_and_comes_back() {
        for meta in metas() {
            let (model, critics) = random_model(&meta, 7);
            let layout = slots(&meta, &model, critics.as_ref()).unwrap();
            for (buf, len) in [
                (Buf::Pi, model.pi.params.len()),
                (Buf::V, model.v.params.len()),
                (Buf::QEmbed, critics.as_ref().and_then(|c| c.embed.as_ref()).map_or(0, |e| e.params.len())),
                (Buf::Q1, critics.as_ref().map_or(0, |c| c.q1.params.len())),
                (Buf::Q2, critics.as_ref().map_or(0, |c| c.q2.params.len())),
            ] {
                let mut hit = vec![0u8; len];
                for s in layout.iter().filter(|s| s.buf == Some(buf)) {
                    assert_eq!(s.idx.len(), s.shape.iter().product::<usize>(), "{}", s.name);
                    for &i in &s.idx {
                        hit[i as usize] += 1;
                    }
                }
                assert!(hit.iter().all(|&h| h == 1), "{buf:?} of {:?}: not every parameter once", meta.neural_network);
            }
            let names: BTreeSet<&str> = layout.iter().map(|s| s.name.as_str()).collect();
            assert_eq!(names.len(), layout.len(), "names are unique");
            let ckpt = to_checkpoint(&meta, &model, critics.as_ref()).unwrap();
            let back = from_checkpoint(&ckpt, &meta).unwrap();
            assert_eq!(back.model.pi, model.pi);
            assert_eq!(back.model.v, model.v);
            assert_eq!(back.model.head, model.head);
            assert!(back.unused.is_empty(), "{:?}", back.unused);
            if let (Some(a), Some(b)) = (&back.critics, &critics) {
                assert_eq!(a.embed, b.embed);
                for (x, y) in [(&a.q1, &b.q1), (&a.q2, &b.q2)] {
                    for (p, q) in x.params.iter().zip(&y.params) {
                        assert!((p - q).abs() <= 1e-5 * (1.0 + q.abs()), "{p} {q}");
                    }
                }
            }
        }
    }

    /// Issue 53: the SHALLOW camera network's names and shapes are those of a real AWS
    /// console export's checkpoint (virtual-model.md §6.3).
    #[test]
    fn shallow_names_are_those_of_a_real_export() {
        let meta = &metas()[1];
        assert_eq!(meta.neural_network, NeuralNetwork::DeepConvolutionalNetworkShallow);
        assert_eq!(meta.sensor, vec![Sensor::FrontFacingCamera]);
        let v = variables(meta).unwrap();
        let p = "main_level/agent/main/online/network_";
        let want: Vec<(String, Vec<usize>)> = [
            ("0/FRONT_FACING_CAMERA/Conv2d_0/bias", vec![32]),
            ("0/FRONT_FACING_CAMERA/Conv2d_0/kernel", vec![8, 8, 1, 32]),
            ("0/FRONT_FACING_CAMERA/Conv2d_2/bias", vec![64]),
            ("0/FRONT_FACING_CAMERA/Conv2d_2/kernel", vec![4, 4, 32, 64]),
            ("0/FRONT_FACING_CAMERA/Conv2d_4/bias", vec![64]),
            ("0/FRONT_FACING_CAMERA/Conv2d_4/kernel", vec![3, 3, 64, 64]),
            ("0/gradients_from_head_0-0_rescalers", vec![]),
            ("0/middleware_fc_embedder/Dense_0/bias", vec![512]),
            ("0/middleware_fc_embedder/Dense_0/kernel", vec![11264, 512]),
            ("0/v_values_head_0/output/bias", vec![1]),
            ("0/v_values_head_0/output/kernel", vec![512, 1]),
        ]
        .into_iter()
        .map(|(n, s)| (format!("{p}{n}"), s))
        .collect();
        assert_eq!(&v[..want.len()], &want[..]);
        let policy: Vec<&str> = v[want.len()..].iter().map(|(n, _)| n.strip_prefix(p).unwrap()).collect();
        assert!(policy.contains(&"1/ppo_head_0/policy_mean/kernel"), "{policy:?}");
        assert!(policy.contains(&"1/ppo_head_0/policy_log_std"), "{policy:?}");
        assert_eq!(v.len(), 2 * want.len() + 1);
    }

    /// Issue 53: a checkpoint of another network is refused naming the variable.
    #[test]
    fn another_networks_checkpoint_is_refused_naming_the_variable() {
        let all = metas();
        let (shallow, deep) = (&all[0], &all[9]);
        let (m, c) = random_model(shallow, 1);
        let ckpt = to_checkpoint(shallow, &m, c.as_ref()).unwrap();
        let e = from_checkpoint(&ckpt, deep).unwrap_err().to_string();
        assert!(e.contains("Conv2d_0/kernel") && e.contains("[8, 8, 1, 32]") && e.contains("[5, 5, 1, 32]"), "{e}");
        let mut partial = ckpt.clone();
        partial.retain(|k, _| !k.contains("network_0"));
        let e = from_checkpoint(&partial, shallow).unwrap_err().to_string();
        assert!(e.starts_with("no variable main_level/agent/main/online/network_0/"), "{e}");
    }
}
