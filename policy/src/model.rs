//! The actor-critic: separate policy and value towers as DeepRacer builds them (simapp's
//! `agents/utils.py::get_network_settings`, COACH's clipped PPO), the action heads, and the
//! maths of their log-probabilities and entropies.
//!
//! Heads: a categorical over a discrete action list (softmax); for continuous ranges a
//! Gaussian with a state-independent log-std (DeepRacer's PPO head). Paddock's continuous
//! head is a *clipped* Gaussian: the sample is unbounded (its log-probability is the
//! Gaussian's), and the environment receives it clipped to [-1, 1] and rescaled linearly to
//! [low, high], as DeepRacer's `ScalableBoxActionSpace` does.

use crate::metadata::{Action, ActionSpace, ModelMetadata, NeuralNetwork, Sensor, TrainingAlgorithm};
use crate::nn::{InputShape, LayerSpec, Net, Tape};
use faer::Par;
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};

/// DeepRacer's camera frame: 120 rows × 160 columns × 1 (grayscale).
pub const CAMERA_SHAPE: (usize, usize, usize) = (120, 160, 1);
/// DeepRacer's clip on the Gaussian head's log-std.
pub const LOG_STD_RANGE: (f32, f32) = (-20.0, 3.0);

/// The policy's output head.
#[derive(Clone, Debug, PartialEq)]
pub enum Head {
    /// Softmax over `n` actions.
    Categorical(usize),
    /// Two means from the tower and a learned log-std per dimension.
    Gaussian {
        /// log σ for (steering, speed).
        log_std: [f32; 2],
    },
    /// SAC's tanh-squashed Gaussian: the tower gives two means and two log-stds; the
    /// action is `tanh(u)` for a draw `u` (`tanh(mean)` when deterministic), which the
    /// environment rescales linearly (see [`squashed`]).
    Squashed {
        /// Half of each action's range in the environment's units (log π's tanh correction).
        scale: [f32; 2],
    },
}

/// What the policy chose for one observation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Choice {
    /// Index into the discrete action list.
    Discrete(usize),
    /// The raw Gaussian sample (before clipping) for (steering, speed); for SAC's head the
    /// squashed action `tanh(u)`, in [-1, 1].
    Continuous([f32; 2]),
}

impl Choice {
    /// The command for the car.
    pub fn to_action(self, space: &ActionSpace) -> Action {
        match self {
            Choice::Discrete(i) => space.discrete(i).expect("index within the action list"),
            Choice::Continuous(u) => space.scale([u[0] as f64, u[1] as f64]).expect("continuous space"),
        }
    }
}

/// One step of acting: the choice, its log-probability, and the value estimate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ActOutput {
    /// The choice.
    pub choice: Choice,
    /// log π(choice | obs).
    pub logp: f32,
    /// V(obs); 0 from [`ActorCritic::act_policy`], which does not compute it.
    pub value: f32,
}

/// Separate policy and value towers plus the head.
#[derive(Clone, Debug, PartialEq)]
pub struct ActorCritic {
    /// Policy tower (ends in the head's logits or means).
    pub pi: Net,
    /// Value tower (ends in one output).
    pub v: Net,
    /// The head.
    pub head: Head,
}

/// The tower layers (without the final output layer) for a network name, for one camera or
/// the stereo pair (`stereo`): DeepRacer's stereo embedder differs from the front camera's for
/// the two deeper networks (`sensors/utils.py`), and has no dense layer of its own.
pub fn tower_specs(network: NeuralNetwork, stereo: bool) -> Vec<LayerSpec> {
    use LayerSpec::*;
    if stereo && network != NeuralNetwork::DeepConvolutionalNetworkShallow && network != NeuralNetwork::PaddockMlp {
        let mut specs = vec![
            Scale(1.0 / 255.0),
            Conv(32, 3, 1),
            Relu,
            Conv(64, 3, 2),
            Relu,
            Conv(64, 3, 1),
            Relu,
            Conv(128, 3, 2),
            Relu,
            Conv(128, 3, 1),
            Relu,
        ];
        // The middleware: Dense 512, or the deepest network's 256, 128.
        if network == NeuralNetwork::DeepConvolutionalNetworkDeep {
            specs.extend([Dense(256), Relu, Dense(128), Relu]);
        } else {
            specs.extend([Dense(512), Relu]);
        }
        return specs;
    }
    match network {
        NeuralNetwork::DeepConvolutionalNetworkShallow => {
            vec![Scale(1.0 / 255.0), Conv(32, 8, 4), Relu, Conv(64, 4, 2), Relu, Conv(64, 3, 1), Relu, Dense(512), Relu]
        }
        // "Dense on the last axis" of a 4-D tensor (Keras) is a 1×1 convolution.
        NeuralNetwork::DeepConvolutionalNetwork => vec![
            Scale(1.0 / 255.0),
            Conv(32, 5, 2),
            Relu,
            Conv(32, 3, 1),
            Relu,
            Conv(64, 3, 2),
            Relu,
            Conv(64, 3, 1),
            Relu,
            Conv(64, 1, 1),
            Relu,
            Dense(512),
            Relu,
        ],
        NeuralNetwork::DeepConvolutionalNetworkDeep => vec![
            Scale(1.0 / 255.0),
            Conv(32, 8, 4),
            Relu,
            Conv(32, 4, 2),
            Relu,
            Conv(64, 4, 2),
            Relu,
            Conv(64, 3, 1),
            Relu,
            Conv(512, 1, 1),
            Relu,
            Conv(512, 1, 1),
            Relu,
            Dense(256),
            Relu,
            Dense(128),
            Relu,
        ],
        NeuralNetwork::PaddockMlp => vec![Dense(128), Relu, Dense(128), Relu],
    }
}

/// The network input for a model's camera (or state vector): the camera frame (two
/// channels for the stereo pair), or a vector of `obs_size`.
pub fn input_shape(meta: &ModelMetadata, obs_size: usize) -> InputShape {
    if meta.sensor.contains(&Sensor::StateVector) {
        InputShape::Flat(obs_size - inputs_beside(meta))
    } else {
        let (h, w, c) = CAMERA_SHAPE;
        let c = if meta.sensor.contains(&Sensor::StereoCameras) { 2 } else { c };
        InputShape::Image(h, w, c)
    }
}

fn inputs_beside(meta: &ModelMetadata) -> usize {
    if meta.sensor.contains(&Sensor::StateVector) { 0 } else { meta.lidar.map_or(0, |l| l.size()) }
}

/// A model's network inputs in the order a sample holds them and the network concatenates
/// their embeddings: DeepRacer's sorted input names (COACH's `merger`), so
/// `FRONT_FACING_CAMERA` comes before `SECTOR_LIDAR`, and `LIDAR` before `STEREO_CAMERAS`.
/// One input for a camera alone or the state vector (whose lidar is part of its vector).
pub fn inputs(meta: &ModelMetadata, obs_size: usize) -> Vec<(Sensor, InputShape)> {
    let primary = *meta.sensor.iter().find(|s| s.is_primary()).expect("a parsed metadata has one camera");
    let mut out = vec![(primary, input_shape(meta, obs_size))];
    if let (Some(lidar), false) = (meta.lidar, primary == Sensor::StateVector) {
        out.push((lidar.sensor, InputShape::Flat(lidar.size())));
        out.sort_by_key(|(s, _)| s.name());
    }
    out
}

/// Values per sample a model takes (`obs_size` for the state vector, whose length the
/// simulator's configuration decides).
pub fn input_size(meta: &ModelMetadata, obs_size: usize) -> usize {
    inputs(meta, obs_size).iter().map(|(_, s)| s.size()).sum()
}

/// DeepRacer's LiDAR embedder (`sensors/utils.py`): two dense layers of 256.
pub const LIDAR_EMBEDDER: [LayerSpec; 4] =
    [LayerSpec::Dense(256), LayerSpec::Relu, LayerSpec::Dense(256), LayerSpec::Relu];

/// One tower for `meta`, its output layer `out` wide.
fn tower(
    meta: &ModelMetadata,
    obs_size: usize,
    out: usize,
    last_std: impl Fn(&[LayerSpec]) -> f32,
    rng: &mut impl Rng,
) -> Net {
    tower_with(meta, obs_size, &[], out, last_std, rng)
}

/// One tower for `meta` with `head` between the middleware and the output layer.
fn tower_with(
    meta: &ModelMetadata,
    obs_size: usize,
    head: &[LayerSpec],
    out: usize,
    last_std: impl Fn(&[LayerSpec]) -> f32,
    rng: &mut impl Rng,
) -> Net {
    let mut specs = tower_specs(meta.neural_network, meta.sensor.contains(&Sensor::StereoCameras));
    specs.extend_from_slice(head);
    specs.push(LayerSpec::Dense(out));
    let inputs = inputs(meta, obs_size);
    if let [(_, shape)] = inputs[..] {
        return Net::new(shape, &specs, Some(last_std(&specs)), rng);
    }
    // The camera's layers up to the middleware are its embedder; the LiDAR has its own.
    let middle = specs.iter().position(|s| matches!(s, LayerSpec::Dense(_))).expect("a dense layer");
    let (camera, trunk) = specs.split_at(middle);
    let parts: Vec<(&str, InputShape, &[LayerSpec])> = inputs
        .iter()
        .map(|&(s, shape)| (s.name(), shape, if s.is_primary() { camera } else { &LIDAR_EMBEDDER[..] }))
        .collect();
    Net::new_multi(&parts, trunk, Some(last_std(trunk)), rng)
}

impl ActorCritic {
    /// A freshly initialised model for `meta` (state-vector models take `obs_size` inputs).
    pub fn new(meta: &ModelMetadata, obs_size: usize, rng: &mut impl Rng) -> ActorCritic {
        if let (TrainingAlgorithm::Sac, ActionSpace::Continuous { steering_angle, speed }) =
            (meta.training_algorithm, &meta.action_space)
        {
            let half = |r: &(f64, f64)| ((r.1 - r.0) / 2.0) as f32;
            let pi = sac_policy(meta, obs_size, rng);
            let v = sac_value(meta, obs_size, rng);
            return ActorCritic { pi, v, head: Head::Squashed { scale: [half(steering_angle), half(speed)] } };
        }
        let head = match meta.action_space {
            ActionSpace::Discrete(ref a) => Head::Categorical(a.len()),
            ActionSpace::Continuous { .. } => Head::Gaussian { log_std: [0.0, 0.0] },
        };
        // Small initial policy outputs: near-uniform actions at the start (DeepRacer's
        // continuous head uses std 0.01); value head with unit-scale weights.
        let pi = tower(meta, obs_size, meta.action_space.dim(), |_| 0.01, rng);
        let v = tower(meta, obs_size, 1, |specs| 1.0 / (tower_width(specs) as f32).sqrt(), rng);
        ActorCritic { pi, v, head }
    }

    /// Inputs per observation.
    pub fn obs_size(&self) -> usize {
        self.pi.in_size()
    }

    /// The policy's most likely choice for one observation, from the policy tower alone (as a
    /// car drives, and as evaluations choose): the argmax class, or the Gaussian's means.
    /// `tape` keeps the buffers between calls.
    pub fn mode(&self, obs: &[f32], tape: &mut Tape) -> Choice {
        self.pi.forward(obs, 1, tape, Par::Seq);
        let row = tape.output();
        match self.head {
            Head::Categorical(_) => Choice::Discrete(argmax(row)),
            Head::Gaussian { .. } => Choice::Continuous([row[0], row[1]]),
            Head::Squashed { scale } => Choice::Continuous(squashed(row, [0.0; 2], scale).a),
        }
    }

    /// Act on a batch of observations: sample (training) or take the mode (evaluation).
    pub fn act(&self, obs: &[f32], batch: usize, deterministic: bool, rng: &mut impl Rng, par: Par) -> Vec<ActOutput> {
        let mut tape = Tape::default();
        self.pi.forward(obs, batch, &mut tape, par);
        let out = tape.output().to_vec();
        self.v.forward(obs, batch, &mut tape, par);
        self.choose(&out, tape.output(), batch, deterministic, rng)
    }

    /// [`ActorCritic::act`] from the policy tower alone, every value 0: what acting needs, at
    /// half the maths. An evaluation takes the choice alone, and PPO's update computes the
    /// values it needs from the network as it begins (`make_batch_for`), not from acting time.
    pub fn act_policy(
        &self,
        obs: &[f32],
        batch: usize,
        deterministic: bool,
        rng: &mut impl Rng,
        par: Par,
    ) -> Vec<ActOutput> {
        let mut tape = Tape::default();
        self.pi.forward(obs, batch, &mut tape, par);
        self.choose(tape.output(), &vec![0.0; batch], batch, deterministic, rng)
    }

    /// [`ActorCritic::act`] from the towers' outputs over the batch, computed elsewhere (on a
    /// GPU): the policy's `out` (`batch × pi.out_size()`) and the `values`.
    pub fn choose(
        &self,
        out: &[f32],
        values: &[f32],
        batch: usize,
        deterministic: bool,
        rng: &mut impl Rng,
    ) -> Vec<ActOutput> {
        let dim = self.pi.out_size();
        (0..batch)
            .map(|i| {
                let row = &out[i * dim..(i + 1) * dim];
                let (choice, logp) = match self.head {
                    Head::Categorical(n) => {
                        let logp = log_softmax(row);
                        let a = if deterministic {
                            argmax(&logp)
                        } else {
                            let u: f32 = rng.random();
                            let mut acc = 0.0;
                            let mut pick = n - 1;
                            for (k, lp) in logp.iter().enumerate() {
                                acc += lp.exp();
                                if u < acc {
                                    pick = k;
                                    break;
                                }
                            }
                            pick
                        };
                        (Choice::Discrete(a), logp[a])
                    }
                    Head::Gaussian { log_std } => {
                        let mut x = [0.0f32; 2];
                        for d in 0..2 {
                            let z: f32 = if deterministic { 0.0 } else { StandardNormal.sample(rng) };
                            x[d] = row[d] + z * clip_log_std(log_std[d]).exp();
                        }
                        (Choice::Continuous(x), gaussian_logp(row, &log_std, &x))
                    }
                    Head::Squashed { scale } => {
                        let mut eps = [0.0f32; 2];
                        if !deterministic {
                            eps = [StandardNormal.sample(rng), StandardNormal.sample(rng)];
                        }
                        let d = squashed(row, eps, scale);
                        (Choice::Continuous(d.a), d.logp)
                    }
                };
                ActOutput { choice, logp, value: values[i] }
            })
            .collect()
    }
}

/// SAC's clip on its policy's log-std (COACH's `sac_head.py`).
pub const SAC_LOG_STD_RANGE: (f32, f32) = (-20.0, 2.0);

/// SAC's policy network (COACH's `SoftActorCriticAgent`, `sac_head.py`): the sensor
/// embedders and middleware, Dense 256 ReLU, then the two means and the two log-stds side by
/// side (`policy_mean` and `log_std`, one output layer of 4).
pub fn sac_policy(meta: &ModelMetadata, obs_size: usize, rng: &mut impl Rng) -> Net {
    tower_with(meta, obs_size, &[LayerSpec::Dense(256), LayerSpec::Relu], 4, |_| 0.01, rng)
}

/// SAC's V network: the embedders and middleware, then one output (its target copy is the
/// learner's).
pub fn sac_value(meta: &ModelMetadata, obs_size: usize, rng: &mut impl Rng) -> Net {
    tower(meta, obs_size, 1, |specs| 1.0 / (tower_width(specs) as f32).sqrt(), rng)
}

/// The layers of SAC's Q heads, on the embedding and the action side by side (`sac_q_head.py`).
pub const SAC_Q_HEAD: [LayerSpec; 5] =
    [LayerSpec::Dense(256), LayerSpec::Relu, LayerSpec::Dense(256), LayerSpec::Relu, LayerSpec::Dense(1)];

/// SAC's Q network's sensor embedders (no middleware: `MiddlewareScheme.Empty`), shared by its
/// two heads; `None` where the input goes to the heads as it is (the state vector, whose
/// Paddock network has only dense layers).
pub fn sac_q_embedder(meta: &ModelMetadata, obs_size: usize, rng: &mut impl Rng) -> Option<Net> {
    let specs = tower_specs(meta.neural_network, meta.sensor.contains(&Sensor::StereoCameras));
    let middle = specs.iter().position(|s| matches!(s, LayerSpec::Dense(_))).unwrap_or(specs.len());
    let camera = &specs[..middle];
    let inputs = inputs(meta, obs_size);
    if let [(_, shape)] = inputs[..] {
        return (!camera.is_empty()).then(|| Net::new(shape, camera, None, rng));
    }
    let parts: Vec<(&str, InputShape, &[LayerSpec])> = inputs
        .iter()
        .map(|&(s, shape)| (s.name(), shape, if s.is_primary() { camera } else { &LIDAR_EMBEDDER[..] }))
        .collect();
    Some(Net::new_multi(&parts, &[], None, rng))
}

/// One of SAC's Q heads on `embedding` features and the two action values.
pub fn sac_q_head(embedding: usize, rng: &mut impl Rng) -> Net {
    Net::new(InputShape::Flat(embedding + 2), &SAC_Q_HEAD, None, rng)
}

/// SAC's squashed Gaussian for one row of its policy's output (`[mean; 2]`, `[log_std; 2]`)
/// and a standard-normal draw `eps` (zero for the deterministic action): the pre-tanh sample
/// `u = mean + exp(log_std)·eps`, the action `a = tanh(u)` in [-1, 1] (the environment takes
/// `scale·a + bias`), and log π(a) as COACH computes it, `log N(u) − Σ log(clip(scale·(1 − a²)
/// + ε, 1e-10, 1))` with `scale` the half-range of each action in the environment's units.
pub fn squashed(row: &[f32], eps: [f32; 2], scale: [f32; 2]) -> Squashed {
    let mut out = Squashed { u: [0.0; 2], a: [0.0; 2], logp: 0.0 };
    for d in 0..2 {
        let ls = row[2 + d].clamp(SAC_LOG_STD_RANGE.0, SAC_LOG_STD_RANGE.1);
        let u = row[d] + ls.exp() * eps[d];
        let a = u.tanh().clamp(-1.0, 1.0);
        let jac = (scale[d] * (1.0 - a * a) + f32::EPSILON).clamp(1e-10, 1.0);
        out.u[d] = u;
        out.a[d] = a;
        out.logp += -0.5 * eps[d] * eps[d] - ls - 0.5 * (2.0 * std::f32::consts::PI).ln() - jac.ln();
    }
    out
}

/// A draw from SAC's policy: see [`squashed`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Squashed {
    /// The pre-tanh sample.
    pub u: [f32; 2],
    /// The action in [-1, 1].
    pub a: [f32; 2],
    /// log π(a | s).
    pub logp: f32,
}

fn tower_width(specs: &[LayerSpec]) -> usize {
    specs.iter().rev().skip(1).find_map(|s| if let LayerSpec::Dense(n) = s { Some(*n) } else { None }).unwrap_or(1)
}

/// log-softmax of one row of logits.
pub fn log_softmax(z: &[f32]) -> Vec<f32> {
    let m = z.iter().cloned().fold(f32::MIN, f32::max);
    let lse = m + z.iter().map(|v| (v - m).exp()).sum::<f32>().ln();
    z.iter().map(|v| v - lse).collect()
}

fn argmax(v: &[f32]) -> usize {
    v.iter().enumerate().fold((0, f32::MIN), |b, (i, &x)| if x > b.1 { (i, x) } else { b }).0
}

/// The clipped log-std actually used.
pub fn clip_log_std(l: f32) -> f32 {
    l.clamp(LOG_STD_RANGE.0, LOG_STD_RANGE.1)
}

/// log N(x; mean, exp(log_std)) summed over the two dimensions.
pub fn gaussian_logp(mean: &[f32], log_std: &[f32; 2], x: &[f32; 2]) -> f32 {
    (0..2)
        .map(|d| {
            let ls = clip_log_std(log_std[d]);
            let z = (x[d] - mean[d]) / ls.exp();
            -0.5 * z * z - ls - 0.5 * (2.0 * std::f32::consts::PI).ln()
        })
        .sum()
}

/// Entropy of the Gaussian head (nats).
pub fn gaussian_entropy(log_std: &[f32; 2]) -> f32 {
    (0..2).map(|d| clip_log_std(log_std[d]) + 0.5 * (2.0 * std::f32::consts::PI * std::f32::consts::E).ln()).sum()
}
