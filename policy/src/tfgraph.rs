//! DeepRacer's frozen TensorFlow graph (`model.pb`), both ways: a model's policy tower
//! written as the graph a DeepRacer car loads, and a DeepRacer graph's policy tower read back
//! into a Paddock network. The messages are TensorFlow's own (`proto/tensorflow/`, built by
//! prost).
//!
//! **Writing.** The graph has DeepRacer's names: the input placeholder
//! `main_level/agent/main/online/network_0/{SENSOR}/{SENSOR}` (`[N,120,160,C]` float, grey
//! levels 0–255; the `/255` is the graph's own `RealDiv`), the layers under
//! `main_level/agent/main/online/network_1` as rl_coach names them (`{SENSOR}/Conv2d_0`,
//! `middleware_fc_embedder/Dense_0`, `ppo_head_0/policy_fc`), and the output
//! `…/network_1/ppo_head_0/policy`: the softmax of a discrete space, the two means of a
//! continuous one; for SAC (`training_algorithm: "sac"`) the `policy` network's
//! `main_level/agent/policy/online/network_0`, its head `sac_policy_head_0` with the output
//! `…/sac_policy_head_0/policy`, the pre-tanh means (the log-stds are not in DeepRacer's
//! frozen graph, and an imported SAC model's are fresh). Only TF1 ops that every converter takes (Placeholder, Const, RealDiv,
//! Conv2D, BiasAdd, Relu, Reshape, MatMul, Softmax, Identity); kernels are HWIO and dense
//! weights `[in, out]`, so Paddock's NHWC layers map one to one. The names per sensor and
//! algorithm are [`Names`].
//!
//! **Reading.** Node names in real exports vary between TensorFlow releases, so the reader
//! walks the graph from the output back to the input placeholder instead, and keeps every
//! node's value as `a·T + b` of the last layer's output `T` (scalars `a`, `b`): scalings,
//! offsets and rl_coach's gradient rescaler (`(1−r)·stop_gradient(x) + r·x`) fold into the
//! next layer's weights. Convolutions and matrix products become layers (a product on a
//! 4-D value is a 1×1 convolution, as Keras's `Dense` on an image is, or a flattening dense
//! layer), and the result must be the network the metadata names, layer for layer. Any other
//! op on the way is refused by name.

use crate::metadata::{ActionSpace, ModelMetadata, NeuralNetwork, Sensor, TrainingAlgorithm};
use crate::model::{ActorCritic, Head};
use crate::nn::{InputShape, Layer, Net};
use prost::Message;
use std::collections::HashMap;

/// TensorFlow's graph messages (the part of its `.proto` files a frozen graph uses).
#[allow(missing_docs, dead_code, clippy::all)]
pub mod pb {
    include!(concat!(env!("OUT_DIR"), "/tensorflow.rs"));
}

pub use pb::GraphDef;

const DT_FLOAT: i32 = 1;
const DT_INT32: i32 = 3;
/// The most nodes between the output and an input a graph may have (the recursion's depth).
const MAX_GRAPH_DEPTH: usize = 256;

/// The largest graph read (a DEEPER camera model is ≈ 40 MB).
pub const MAX_GRAPH_BYTES: usize = 512 << 20;

/// Why a graph could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum GraphError {
    /// The model asks for what DeepRacer's graph has no form for (yet).
    #[error("{0}")]
    Unsupported(String),
    /// The bytes are not a TensorFlow GraphDef.
    #[error("not a TensorFlow GraphDef: {0}")]
    NotAGraph(String),
    /// A GraphDef, but not DeepRacer's network for this metadata.
    #[error("the graph is not the network model_metadata.json names: {0}")]
    Mismatch(String),
}

/// DeepRacer's node names for a model's sensor and algorithm.
#[derive(Clone, Debug, PartialEq)]
pub struct Names {
    /// The sensor's key, which names the placeholder and the embedder's scope.
    pub sensor: &'static str,
    /// The input placeholder.
    pub input: String,
    /// The scope of the policy tower's layers.
    pub scope: String,
    /// The policy head's scope, under `scope`.
    pub head: &'static str,
    /// The output node.
    pub output: String,
    /// Channels of the input image.
    pub channels: usize,
    /// Every input placeholder in the network's input order (DeepRacer's sorted sensor
    /// names): the camera's alone, or the camera's and the LiDAR's.
    pub inputs: Vec<String>,
}

impl Names {
    /// The names DeepRacer's simapp gives a model with this metadata (its
    /// `FROZEN_HEAD_OUTPUT_GRAPH_FORMAT_MAPPING`, and the model optimizer's
    /// `NETWORK_INPUT_FORMAT_MAPPING`).
    pub fn of(meta: &ModelMetadata) -> Result<Names, GraphError> {
        let unsupported = |what: String| Err(GraphError::Unsupported(what));
        let camera: Vec<Sensor> = meta.sensor.iter().copied().filter(|s| s.is_primary()).collect();
        let (sensor, channels) = match camera.as_slice() {
            [Sensor::FrontFacingCamera] => ("FRONT_FACING_CAMERA", 1),
            [Sensor::Observation] => ("observation", 1),
            [Sensor::LeftCamera] => ("LEFT_CAMERA", 1),
            [Sensor::StereoCameras] => ("STEREO_CAMERAS", 2),
            [Sensor::StateVector] => {
                return unsupported(
                    "a STATE_VECTOR model drives only in the simulator: a car has no such sensor, \
                     and DeepRacer's graph no such input"
                        .into(),
                );
            }
            _ => {
                return unsupported(format!(
                    "sensors {:?}: DeepRacer's graph is written for one camera input \
                     (FRONT_FACING_CAMERA, LEFT_CAMERA, STEREO_CAMERAS or observation), with or without a LiDAR",
                    meta.sensor.iter().map(|s| s.name()).collect::<Vec<_>>()
                ));
            }
        };
        if meta.neural_network == NeuralNetwork::PaddockMlp {
            return unsupported("neural_network PADDOCK_MLP is Paddock's own; DeepRacer has no graph for it".into());
        }
        // PPO's policy tower is the `main` network's second; SAC's is the `policy` network.
        let (agent, network, head) = match meta.training_algorithm {
            TrainingAlgorithm::ClippedPpo => ("main_level/agent/main/online", "network_1", "ppo_head_0"),
            TrainingAlgorithm::Sac => ("main_level/agent/policy/online", "network_0", "sac_policy_head_0"),
        };
        let placeholder = |name: &str| format!("{agent}/network_0/{name}/{name}");
        Ok(Names {
            sensor,
            inputs: crate::model::inputs(meta, 0).iter().map(|(s, _)| placeholder(s.name())).collect(),
            input: placeholder(sensor),
            scope: format!("{agent}/{network}"),
            head,
            output: format!("{agent}/{network}/{head}/policy"),
            channels,
        })
    }
}

// ---------------------------------------------------------------------------------------
// Writing

struct Writer {
    nodes: Vec<pb::NodeDef>,
}

fn attr(v: pb::attr_value::Value) -> pb::AttrValue {
    pb::AttrValue { value: Some(v) }
}

fn shape_proto(dims: &[i64]) -> pb::TensorShapeProto {
    pb::TensorShapeProto {
        dim: dims.iter().map(|&size| pb::tensor_shape_proto::Dim { size, name: String::new() }).collect(),
        unknown_rank: false,
    }
}

fn float_type() -> (String, pb::AttrValue) {
    ("T".into(), attr(pb::attr_value::Value::Type(DT_FLOAT)))
}

impl Writer {
    fn node(&mut self, name: &str, op: &str, inputs: &[&str], attrs: Vec<(String, pb::AttrValue)>) -> String {
        self.nodes.push(pb::NodeDef {
            name: name.into(),
            op: op.into(),
            input: inputs.iter().map(|s| s.to_string()).collect(),
            attr: attrs.into_iter().collect(),
            ..Default::default()
        });
        name.to_string()
    }

    fn constant(&mut self, name: &str, dims: &[i64], values: &[f32]) -> String {
        let content: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let t = pb::TensorProto {
            dtype: DT_FLOAT,
            tensor_shape: Some(shape_proto(dims)),
            tensor_content: content,
            ..Default::default()
        };
        let attrs = vec![
            ("dtype".into(), attr(pb::attr_value::Value::Type(DT_FLOAT))),
            ("value".into(), attr(pb::attr_value::Value::Tensor(t))),
        ];
        self.node(name, "Const", &[], attrs)
    }

    fn int_constant(&mut self, name: &str, dims: &[i64], values: &[i32]) -> String {
        let t = pb::TensorProto {
            dtype: DT_INT32,
            tensor_shape: Some(shape_proto(dims)),
            int_val: values.to_vec(),
            ..Default::default()
        };
        let attrs = vec![
            ("dtype".into(), attr(pb::attr_value::Value::Type(DT_INT32))),
            ("value".into(), attr(pb::attr_value::Value::Tensor(t))),
        ];
        self.node(name, "Const", &[], attrs)
    }

    /// `x·W + b` with Paddock's `W` (`rows × inp`) written as TensorFlow's kernel (`inp ×
    /// rows`): a dense layer's first `rows = b.len()` outputs (all of them but for SAC's policy
    /// means), `w` their weights.
    fn dense(&mut self, scope: &str, x: &str, inp: usize, w: &[f32], b: &[f32]) -> String {
        let rows = b.len();
        debug_assert_eq!(w.len(), rows * inp);
        let mut kernel = vec![0.0f32; inp * rows];
        for o in 0..rows {
            for i in 0..inp {
                kernel[i * rows + o] = w[o * inp + i];
            }
        }
        let k = self.constant(&format!("{scope}/kernel"), &[inp as i64, rows as i64], &kernel);
        let b = self.constant(&format!("{scope}/bias"), &[rows as i64], b);
        let attrs = vec![
            float_type(),
            ("transpose_a".into(), attr(pb::attr_value::Value::B(false))),
            ("transpose_b".into(), attr(pb::attr_value::Value::B(false))),
        ];
        let m = self.node(&format!("{scope}/MatMul"), "MatMul", &[x, &k], attrs);
        self.node(&format!("{scope}/BiasAdd"), "BiasAdd", &[&m, &b], vec![float_type()])
    }
}

/// The policy tower of `model` as DeepRacer's frozen graph (`model.pb`'s bytes).
pub fn write(model: &ActorCritic, meta: &ModelMetadata) -> Result<Vec<u8>, GraphError> {
    Ok(graph(model, meta)?.encode_to_vec())
}

/// [`write`]'s graph.
pub fn graph(model: &ActorCritic, meta: &ModelMetadata) -> Result<GraphDef, GraphError> {
    let names = Names::of(meta)?;
    let net = &model.pi;
    let Some(Layer::Conv2d { input: [_, _, c], .. }) = net.layers.iter().find(|l| matches!(l, Layer::Conv2d { .. }))
    else {
        return Err(GraphError::Unsupported("the model has no camera input".into()));
    };
    if *c != names.channels {
        return Err(GraphError::Unsupported(format!("{} channels for {}", c, names.sensor)));
    }
    let sections = net.sections();
    let trunk = sections.last().expect("the rest").clone();
    // Each input: its sensor name, shape and layers (a one-input network: the camera, whose
    // layers run on into the middleware).
    let inputs: Vec<(String, InputShape, std::ops::Range<usize>)> = if net.inputs.is_empty() {
        vec![(names.sensor.to_string(), crate::model::input_shape(meta, 0), 0..net.layers.len())]
    } else {
        net.inputs.iter().zip(&sections).map(|(e, r)| (e.name.clone(), e.shape, r.clone())).collect()
    };
    let mut g = Writer { nodes: vec![] };
    // Where the middleware starts: the first dense layer of a camera network, or the layers
    // after the embedders.
    let middleware = if net.inputs.is_empty() {
        net.layers.iter().position(|l| matches!(l, Layer::Dense { .. })).unwrap_or(net.layers.len())
    } else {
        trunk.start
    };
    let trunk_denses = net.layers[middleware..].iter().filter(|l| matches!(l, Layer::Dense { .. })).count();
    let mut count = Count { names: &names, own: 0, denses: 0, trunk_denses };
    let mut embedded = Vec::new();
    for ((sensor, shape, range), placeholder) in inputs.iter().zip(&names.inputs) {
        let dims: Vec<i64> = match *shape {
            InputShape::Image(h, w, c) => vec![-1, h as i64, w as i64, c as i64],
            InputShape::Flat(n) => vec![-1, n as i64],
        };
        let mut cur = g.node(
            placeholder,
            "Placeholder",
            &[],
            vec![
                ("dtype".into(), attr(pb::attr_value::Value::Type(DT_FLOAT))),
                ("shape".into(), attr(pb::attr_value::Value::Shape(shape_proto(&dims)))),
            ],
        );
        let embedder = format!("{}/{sensor}", names.scope);
        // rl_coach numbers an embedder's layers 0, 2, 4, … and the activation after layer k
        // `BatchnormActivationDropout_{k+1}`.
        count.own = 0;
        let mut image = matches!(shape, InputShape::Image(..));
        for i in range.clone() {
            let in_trunk = i >= middleware;
            if in_trunk && image {
                cur = g.flatten(&embedder, &cur, net.layers[i].in_size());
                image = false;
            }
            cur = g.layer(net, i, &cur, (&embedder, in_trunk), &mut count)?;
        }
        if image && !net.inputs.is_empty() {
            let n = net.layers[range.clone()].last().map_or(shape.size(), |l| l.out_size());
            cur = g.flatten(&embedder, &cur, n);
        }
        embedded.push(cur);
    }
    let mut cur = embedded[0].clone();
    if !net.inputs.is_empty() {
        // COACH's `merger`: the embedders' outputs side by side, then the middleware.
        let axis = g.int_constant(&format!("{}/merger/axis", names.scope), &[], &[1]);
        let mut ins: Vec<&str> = embedded.iter().map(|s| s.as_str()).collect();
        ins.push(&axis);
        let attrs = vec![
            float_type(),
            ("N".into(), attr(pb::attr_value::Value::I(embedded.len() as i64))),
            ("Tidx".into(), attr(pb::attr_value::Value::Type(DT_INT32))),
        ];
        cur = g.node(&format!("{}/merger", names.scope), "ConcatV2", &ins, attrs);
        count.own = 0;
        for i in trunk {
            cur = g.layer(net, i, &cur, (&names.scope, true), &mut count)?;
        }
    }
    match model.head {
        Head::Categorical(_) => g.node(&names.output, "Softmax", &[&cur], vec![float_type()]),
        Head::Gaussian { .. } => g.node(&names.output, "Identity", &[&cur], vec![float_type()]),
        // SAC's `policy` is the pre-tanh means, as DeepRacer freezes it.
        Head::Squashed { .. } => g.node(&names.output, "Identity", &[&cur], vec![float_type()]),
    };
    Ok(GraphDef {
        node: g.nodes,
        versions: Some(pb::VersionDef { producer: 27, min_consumer: 0, bad_consumers: vec![] }),
        ..Default::default()
    })
}

/// The counts that name the layers as rl_coach does: the current embedder's layers so far
/// (`own`), and the middleware's and head's dense layers so far (`denses`) of `trunk_denses`.
struct Count<'a> {
    names: &'a Names,
    own: usize,
    denses: usize,
    trunk_denses: usize,
}

impl Writer {
    fn flatten(&mut self, embedder: &str, x: &str, n: usize) -> String {
        let s = self.int_constant(&format!("{embedder}/flatten/Reshape/shape"), &[2], &[-1, n as i32]);
        let attrs = vec![float_type(), ("Tshape".into(), attr(pb::attr_value::Value::Type(DT_INT32)))];
        self.node(&format!("{embedder}/flatten/Reshape"), "Reshape", &[x, &s], attrs)
    }

    /// Layer `i` of `net` on `x`: in an embedder (`embedder`'s scope, its layers counted in
    /// `count.own`), or in the middleware and head (`in_trunk`; its dense layers counted in
    /// `count.denses`).
    fn layer(
        &mut self,
        net: &Net,
        i: usize,
        x: &str,
        (embedder, in_trunk): (&str, bool),
        count: &mut Count<'_>,
    ) -> Result<String, GraphError> {
        let Count { names, own, denses, trunk_denses } = count;
        let trunk_denses = *trunk_denses;
        Ok(match net.layers[i] {
            Layer::Scale { factor, .. } => {
                let y = self.constant(&format!("{embedder}/truediv/y"), &[], &[1.0 / factor]);
                self.node(&format!("{embedder}/truediv"), "RealDiv", &[x, &y], vec![float_type()])
            }
            Layer::Conv2d { input: [_, _, c], filters, kernel: k, stride, offset } => {
                let scope = format!("{embedder}/Conv2d_{}", 2 * *own);
                *own += 1;
                let wt = &net.params[offset..offset + filters * k * k * c];
                // Paddock's [f][ky][kx][c] as TensorFlow's HWIO [ky][kx][c][f].
                let mut hwio = vec![0.0f32; wt.len()];
                for f in 0..filters {
                    for j in 0..k * k * c {
                        hwio[j * filters + f] = wt[f * k * k * c + j];
                    }
                }
                let kern =
                    self.constant(&format!("{scope}/kernel"), &[k as i64, k as i64, c as i64, filters as i64], &hwio);
                let bias = self.constant(
                    &format!("{scope}/bias"),
                    &[filters as i64],
                    &net.params[offset + wt.len()..][..filters],
                );
                let s = stride as i64;
                let attrs = vec![
                    float_type(),
                    (
                        "strides".into(),
                        attr(pb::attr_value::Value::List(pb::attr_value::ListValue {
                            i: vec![1, s, s, 1],
                            ..Default::default()
                        })),
                    ),
                    ("padding".into(), attr(pb::attr_value::Value::S(b"VALID".to_vec()))),
                    ("data_format".into(), attr(pb::attr_value::Value::S(b"NHWC".to_vec()))),
                ];
                let conv = self.node(&format!("{scope}/Conv2D"), "Conv2D", &[x, &kern], attrs);
                self.node(&format!("{scope}/BiasAdd"), "BiasAdd", &[&conv, &bias], vec![float_type()])
            }
            Layer::Dense { inp, out, offset } if !in_trunk => {
                let scope = format!("{embedder}/Dense_{}", 2 * *own);
                *own += 1;
                self.dense(&scope, x, inp, &net.params[offset..][..inp * out], &net.params[offset + inp * out..][..out])
            }
            Layer::Dense { inp, out, offset } => {
                *denses += 1;
                let sac = names.head == "sac_policy_head_0";
                let (scope, rows) = if *denses == trunk_denses && sac {
                    // SAC's head: the means alone (`policy_mean`); the log-stds are not frozen.
                    (format!("{}/{}/policy_mean", names.scope, names.head), 2)
                } else if *denses == trunk_denses {
                    (format!("{}/{}/policy_fc", names.scope, names.head), out)
                } else if *denses + 1 == trunk_denses && sac {
                    (format!("{}/{}/Dense_0", names.scope, names.head), out)
                } else {
                    (format!("{}/middleware_fc_embedder/Dense_{}", names.scope, 2 * (*denses - 1)), out)
                };
                self.dense(
                    &scope,
                    x,
                    inp,
                    &net.params[offset..][..inp * rows],
                    &net.params[offset + inp * out..][..rows],
                )
            }
            Layer::Relu { .. } => {
                let name = if in_trunk {
                    format!(
                        "{}/middleware_fc_embedder/BatchnormActivationDropout_{}_activation",
                        names.scope,
                        2 * *denses - 1
                    )
                } else {
                    format!("{embedder}/BatchnormActivationDropout_{}_activation", 2 * *own - 1)
                };
                self.node(&format!("{name}/Relu"), "Relu", &[x], vec![float_type()])
            }
        })
    }
}

// ---------------------------------------------------------------------------------------
// Reading

/// A graph's node name without a port (`:0`) or control mark (`^`).
fn base_name(input: &str) -> &str {
    let s = input.strip_prefix('^').unwrap_or(input);
    s.split(':').next().unwrap_or(s)
}

/// A value on the way from an input to the output: `a·T + b`, `T` the output of layer
/// `layer` of chain `chain` (`None`: the chain's start), with `T`'s shape per sample.
#[derive(Clone, Debug)]
struct Affine {
    /// Which chain of layers: an input's embedder (the input's index), or, after a
    /// multi-input graph's merger, the rest (the number of inputs).
    chain: usize,
    layer: Option<usize>,
    a: f32,
    b: f32,
    dims: Vec<usize>,
}

/// A node's value: a constant tensor, or a function of the input.
#[derive(Clone, Debug)]
enum Value {
    Const { dims: Vec<usize>, values: Vec<f32> },
    Data(Affine),
}

/// A layer read from the graph (weights in Paddock's layout).
#[derive(Clone, Debug)]
enum Read {
    Scale(f32),
    Conv { kernel: usize, stride: usize, c: usize, filters: usize, w: Vec<f32>, b: Vec<f32> },
    Dense { inp: usize, out: usize, w: Vec<f32>, b: Vec<f32> },
    Relu,
}

struct Reader<'g> {
    nodes: HashMap<&'g str, &'g pb::NodeDef>,
    /// The input placeholders, in the network's input order.
    inputs: Vec<&'g str>,
    memo: HashMap<&'g str, Value>,
    /// The nodes being evaluated now, from the output inwards: a node met again among them
    /// is a cycle, and their number is the recursion's depth.
    path: Vec<&'g str>,
    /// The layers read: one chain per input, then (after a merger) the rest.
    chains: Vec<Vec<Read>>,
    softmax: bool,
}

fn tensor_values(t: &pb::TensorProto, name: &str) -> Result<(Vec<usize>, Vec<f32>), GraphError> {
    let dims: Vec<usize> =
        t.tensor_shape.as_ref().map(|s| s.dim.iter().map(|d| d.size.max(0) as usize).collect()).unwrap_or_default();
    let n: usize = dims.iter().product();
    let values: Vec<f32> = match t.dtype {
        DT_FLOAT if !t.tensor_content.is_empty() => {
            t.tensor_content.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
        }
        DT_FLOAT if t.float_val.len() == 1 => vec![t.float_val[0]; n],
        DT_FLOAT => t.float_val.clone(),
        DT_INT32 if !t.tensor_content.is_empty() => {
            t.tensor_content.chunks_exact(4).map(|b| i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32).collect()
        }
        DT_INT32 if t.int_val.len() == 1 => vec![t.int_val[0] as f32; n],
        DT_INT32 => t.int_val.iter().map(|&v| v as f32).collect(),
        other => {
            return Err(GraphError::Mismatch(format!("constant {name} has data type {other}, not float or int32")));
        }
    };
    if values.len() != n {
        return Err(GraphError::Mismatch(format!("constant {name}: {} values for shape {dims:?}", values.len())));
    }
    Ok((dims, values))
}

impl<'g> Reader<'g> {
    fn node(&self, name: &str) -> Result<&'g pb::NodeDef, GraphError> {
        self.nodes.get(base_name(name)).copied().ok_or_else(|| GraphError::Mismatch(format!("node {name} is missing")))
    }

    fn input(&mut self, n: &'g pb::NodeDef, i: usize) -> Result<Value, GraphError> {
        let name = n
            .input
            .iter()
            .filter(|s| !s.starts_with('^'))
            .nth(i)
            .ok_or_else(|| GraphError::Mismatch(format!("{} ({}) has no input {i}", n.name, n.op)))?;
        let node = self.node(name)?;
        self.value(node)
    }

    fn constant(&mut self, n: &'g pb::NodeDef, i: usize) -> Result<(Vec<usize>, Vec<f32>), GraphError> {
        match self.input(n, i)? {
            Value::Const { dims, values } => Ok((dims, values)),
            Value::Data(_) => Err(GraphError::Mismatch(format!("{} ({}): input {i} is not a constant", n.name, n.op))),
        }
    }

    /// The value of `n`, memoised (a graph is a DAG; the walk is a depth-first evaluation).
    fn value(&mut self, n: &'g pb::NodeDef) -> Result<Value, GraphError> {
        if let Some(v) = self.memo.get(n.name.as_str()) {
            return Ok(v.clone());
        }
        if self.path.contains(&n.name.as_str()) {
            return Err(GraphError::Mismatch(format!("{} ({}) is its own input: the graph has a cycle", n.name, n.op)));
        }
        if self.path.len() >= MAX_GRAPH_DEPTH {
            return Err(GraphError::Mismatch(format!(
                "{} ({}) is over {MAX_GRAPH_DEPTH} nodes from the output; DeepRacer's graphs are tens deep",
                n.name, n.op
            )));
        }
        self.path.push(&n.name);
        let v = self.eval(n);
        self.path.pop();
        let v = v?;
        self.memo.insert(&n.name, v.clone());
        Ok(v)
    }

    fn eval(&mut self, n: &'g pb::NodeDef) -> Result<Value, GraphError> {
        let bad = |why: String| Err(GraphError::Mismatch(format!("{} ({}): {why}", n.name, n.op)));
        Ok(match n.op.as_str() {
            "Placeholder" if self.inputs.contains(&n.name.as_str()) => {
                let dims = match n.attr.get("shape").and_then(|a| a.value.as_ref()) {
                    Some(pb::attr_value::Value::Shape(s)) => {
                        s.dim.iter().skip(1).map(|d| d.size.max(0) as usize).collect()
                    }
                    _ => vec![],
                };
                let chain = self.inputs.iter().position(|i| *i == n.name).expect("an input");
                Value::Data(Affine { chain, layer: None, a: 1.0, b: 0.0, dims })
            }
            "Placeholder" | "PlaceholderWithDefault" => {
                return bad(format!("an input beside the model's ({})", self.inputs.join(", ")));
            }
            "ConcatV2" if matches!(self.input(n, 0)?, Value::Data(_)) => self.merger(n)?,
            "Const" => match n.attr.get("value").and_then(|a| a.value.as_ref()) {
                Some(pb::attr_value::Value::Tensor(t)) => {
                    let (dims, values) = tensor_values(t, &n.name)?;
                    Value::Const { dims, values }
                }
                _ => return bad("no value".into()),
            },
            "Identity" | "StopGradient" | "Snapshot" => self.input(n, 0)?,
            "RealDiv" | "Mul" | "Sub" | "Add" | "AddV2" | "Maximum" | "Minimum" => {
                let (x, y) = (self.input(n, 0)?, self.input(n, 1)?);
                self.binary(n, x, y)?
            }
            "Shape" | "StridedSlice" | "Pack" | "GatherV2" | "Prod" | "ConcatV2" => match self.input(n, 0)? {
                // Shape arithmetic (Keras's Flatten and Dense on an image compute their
                // reshapes from the data's shape): only a reshape's shape operand uses it.
                Value::Data(_) => Value::Const { dims: vec![0], values: vec![] },
                c => c,
            },
            "Reshape" => match self.input(n, 0)? {
                Value::Data(x) => {
                    // A flattening reshape to [-1, K]; any other (the per-pixel view of
                    // Keras's Dense on an image) keeps the shape the next layer sees.
                    let target = match self.input(n, 1)? {
                        Value::Const { values, .. } if values.len() == 2 && values[0] == -1.0 => {
                            Some(values[1] as usize)
                        }
                        _ => None,
                    };
                    match target {
                        Some(k) if k == x.dims.iter().product::<usize>() => Value::Data(Affine { dims: vec![k], ..x }),
                        Some(k) if x.dims.last() == Some(&k) => Value::Data(x),
                        Some(k) => return bad(format!("reshape to [-1, {k}] of a value of shape {:?}", x.dims)),
                        None => Value::Data(x),
                    }
                }
                Value::Const { .. } => return bad("reshapes a constant".into()),
            },
            "Transpose" => match (self.input(n, 0)?, self.input(n, 1)?) {
                (Value::Data(x), Value::Const { values, .. })
                    if values.iter().enumerate().all(|(i, &p)| p == i as f32) =>
                {
                    Value::Data(x)
                }
                _ => return bad("a transpose other than the identity".into()),
            },
            "Conv2D" => {
                let Value::Data(x) = self.input(n, 0)? else { return bad("convolves a constant".into()) };
                let (kd, kernel) = self.constant(n, 1)?;
                let attr = |k: &str| n.attr.get(k).and_then(|a| a.value.as_ref());
                let strides = match attr("strides") {
                    Some(pb::attr_value::Value::List(l)) => l.i.clone(),
                    _ => vec![],
                };
                let padding = match attr("padding") {
                    Some(pb::attr_value::Value::S(s)) => String::from_utf8_lossy(s).into_owned(),
                    _ => String::new(),
                };
                let format = match attr("data_format") {
                    Some(pb::attr_value::Value::S(s)) => String::from_utf8_lossy(s).into_owned(),
                    _ => "NHWC".into(),
                };
                let dil_ok = match attr("dilations") {
                    Some(pb::attr_value::Value::List(l)) => l.i.iter().all(|&d| d == 1),
                    _ => true,
                };
                if kd.len() != 4 || kd[0] != kd[1] || x.dims.len() != 3 || x.dims[2] != kd[2] {
                    return bad(format!("kernel {kd:?} on a value of shape {:?}", x.dims));
                }
                if padding != "VALID" || format != "NHWC" || !dil_ok || strides.len() != 4 || strides[1] != strides[2] {
                    return bad(format!(
                        "padding {padding}, format {format}, strides {strides:?} (DeepRacer's: VALID, NHWC, square)"
                    ));
                }
                let (k, c, f, s) = (kd[0], kd[2], kd[3], strides[1].max(1) as usize);
                // HWIO [ky][kx][c][f] → Paddock's [f][ky][kx][c].
                let mut w = vec![0.0f32; kernel.len()];
                for j in 0..k * k * c {
                    for o in 0..f {
                        w[o * k * k * c + j] = kernel[j * f + o];
                    }
                }
                let b = vec![0.0; f];
                let (oh, ow) = ((x.dims[0].saturating_sub(k)) / s + 1, (x.dims[1].saturating_sub(k)) / s + 1);
                self.layer(x, Read::Conv { kernel: k, stride: s, c, filters: f, w, b }, vec![oh, ow, f])?
            }
            "MatMul" => {
                let Value::Data(x) = self.input(n, 0)? else { return bad("multiplies a constant".into()) };
                let (kd, kernel) = self.constant(n, 1)?;
                let flag = |k: &str| {
                    matches!(n.attr.get(k).and_then(|a| a.value.as_ref()), Some(pb::attr_value::Value::B(true)))
                };
                if flag("transpose_a") || flag("transpose_b") || kd.len() != 2 {
                    return bad("a transposed or non-matrix product".into());
                }
                let (inp, out) = (kd[0], kd[1]);
                let mut w = vec![0.0f32; inp * out];
                for i in 0..inp {
                    for o in 0..out {
                        w[o * inp + i] = kernel[i * out + o];
                    }
                }
                let b = vec![0.0; out];
                match x.dims.as_slice() {
                    // Keras's Dense on an image: a 1×1 convolution.
                    [h, wd, c] if *c == inp => {
                        let dims = vec![*h, *wd, out];
                        self.layer(x, Read::Conv { kernel: 1, stride: 1, c: inp, filters: out, w, b }, dims)?
                    }
                    d if d.iter().product::<usize>() == inp => {
                        self.layer(x, Read::Dense { inp, out, w, b }, vec![out])?
                    }
                    d => return bad(format!("kernel {kd:?} on a value of shape {d:?}")),
                }
            }
            "BiasAdd" => {
                let Value::Data(x) = self.input(n, 0)? else { return bad("adds to a constant".into()) };
                let (_, bias) = self.constant(n, 1)?;
                let chain = &mut self.chains[x.chain];
                let Some(l) = x.layer.filter(|&l| x.a == 1.0 && x.b == 0.0 && l + 1 == chain.len()) else {
                    return bad("a bias not right after a layer".into());
                };
                match &mut chain[l] {
                    Read::Conv { b, .. } | Read::Dense { b, .. } if b.len() == bias.len() => {
                        b.iter_mut().zip(&bias).for_each(|(b, v)| *b += v)
                    }
                    _ => return bad(format!("{} biases for the layer before", bias.len())),
                }
                Value::Data(x)
            }
            "Relu" | "Softmax" => {
                let Value::Data(x) = self.input(n, 0)? else { return bad("of a constant".into()) };
                if x.a != 1.0 || x.b != 0.0 {
                    return bad(format!("of {}·x + {}", x.a, x.b));
                }
                if n.op == "Softmax" {
                    self.softmax = true;
                    Value::Data(x)
                } else {
                    self.layer(x.clone(), Read::Relu, x.dims.clone())?
                }
            }
            other => return bad(format!("op {other} is not in DeepRacer's networks")),
        })
    }

    /// A layer on `x` (whose `a·T + b` folds into the layer's weights; on the input itself,
    /// the scaling is a layer of its own, as Paddock's networks begin with `/255`).
    fn layer(&mut self, x: Affine, mut read: Read, dims: Vec<usize>) -> Result<Value, GraphError> {
        let input = x.chain < self.inputs.len();
        let chain = &mut self.chains[x.chain];
        if !x.layer.map_or(chain.is_empty(), |l| l + 1 == chain.len()) {
            return Err(GraphError::Mismatch("the layers do not form one chain from each input".into()));
        }
        let (mut a, b) = (x.a, x.b);
        if input && x.layer.is_none() && chain.is_empty() && a != 1.0 {
            chain.push(Read::Scale(a));
            a = 1.0;
        }
        if a != 1.0 || b != 0.0 {
            match &mut read {
                Read::Conv { w, b: bias, .. } | Read::Dense { w, b: bias, .. } => {
                    let per = w.len() / bias.len();
                    for (o, bo) in bias.iter_mut().enumerate() {
                        let row = &mut w[o * per..(o + 1) * per];
                        *bo += b * row.iter().sum::<f32>();
                        row.iter_mut().for_each(|v| *v *= a);
                    }
                }
                _ => return Err(GraphError::Mismatch(format!("an activation of {a}·x + {b}"))),
            }
        }
        chain.push(read);
        Ok(Value::Data(Affine { chain: x.chain, layer: Some(chain.len() - 1), a: 1.0, b: 0.0, dims }))
    }

    /// COACH's `merger`: every input's embedding (flattened, in input order) side by side,
    /// where the rest of the layers starts.
    fn merger(&mut self, n: &'g pb::NodeDef) -> Result<Value, GraphError> {
        let bad = |why: String| Err(GraphError::Mismatch(format!("{} ({}): {why}", n.name, n.op)));
        let parts = n.input.iter().filter(|s| !s.starts_with('^')).count();
        let (_, axis) = self.constant(n, parts - 1)?;
        if axis.len() != 1 || !(axis[0] == 1.0 || axis[0] == -1.0) {
            return bad(format!("concatenation on axis {axis:?}, not the features'"));
        }
        let mut width = 0;
        for i in 0..parts - 1 {
            let Value::Data(x) = self.input(n, i)? else { return bad(format!("input {i} is a constant")) };
            let end = x.layer.map_or(self.chains[x.chain].is_empty(), |l| l + 1 == self.chains[x.chain].len());
            if x.chain != i || x.a != 1.0 || x.b != 0.0 || !end || x.dims.len() != 1 {
                return bad(format!(
                    "input {i} is not the whole, flattened embedding of input {i} ({})",
                    self.inputs.get(i).unwrap_or(&"none")
                ));
            }
            width += x.dims[0];
        }
        if parts - 1 != self.inputs.len() || self.chains.len() != self.inputs.len() {
            return bad(format!("{} embeddings for {} inputs", parts - 1, self.inputs.len()));
        }
        self.chains.push(Vec::new());
        Ok(Value::Data(Affine { chain: self.inputs.len(), layer: None, a: 1.0, b: 0.0, dims: vec![width] }))
    }

    fn binary(&mut self, n: &pb::NodeDef, x: Value, y: Value) -> Result<Value, GraphError> {
        let scalar = |v: &Value| match v {
            Value::Const { values, .. } if values.len() == 1 => Some(values[0]),
            _ => None,
        };
        let op = n.op.as_str();
        Ok(match (&x, &y) {
            (Value::Const { .. }, Value::Const { .. }) => {
                let (Some(p), Some(q)) = (scalar(&x), scalar(&y)) else {
                    return Err(GraphError::Mismatch(format!("{} ({op}) of non-scalar constants", n.name)));
                };
                let r = match op {
                    "RealDiv" => p / q,
                    "Mul" => p * q,
                    "Sub" => p - q,
                    "Maximum" => p.max(q),
                    "Minimum" => p.min(q),
                    _ => p + q,
                };
                Value::Const { dims: vec![], values: vec![r] }
            }
            (Value::Data(d), c @ Value::Const { .. }) | (c @ Value::Const { .. }, Value::Data(d)) => {
                let Some(k) = scalar(c) else {
                    return Err(GraphError::Mismatch(format!("{} ({op}) by a constant that is not a scalar", n.name)));
                };
                let data_first = matches!(x, Value::Data(_));
                let (a, b) = match (op, data_first) {
                    ("RealDiv", true) if k != 0.0 => (d.a / k, d.b / k),
                    ("Mul", _) => (d.a * k, d.b * k),
                    ("Sub", true) => (d.a, d.b - k),
                    ("Sub", false) => (-d.a, k - d.b),
                    ("Add" | "AddV2", _) => (d.a, d.b + k),
                    _ => return Err(GraphError::Mismatch(format!("{} ({op}) of the data and a constant", n.name))),
                };
                Value::Data(Affine { a, b, ..d.clone() })
            }
            (Value::Data(p), Value::Data(q))
                if (p.chain, p.layer) == (q.chain, q.layer) && matches!(op, "Add" | "AddV2" | "Sub") =>
            {
                let s = if op == "Sub" { -1.0 } else { 1.0 };
                Value::Data(Affine { a: p.a + s * q.a, b: p.b + s * q.b, ..p.clone() })
            }
            _ => {
                return Err(GraphError::Mismatch(format!(
                    "{} ({op}) of two values that are not one affine map",
                    n.name
                )));
            }
        })
    }
}

/// The policy tower of DeepRacer's frozen graph `bytes`, checked against the network `meta`
/// names, as a Paddock model: that tower, and a fresh value tower from `seed`.
pub fn read(bytes: &[u8], meta: &ModelMetadata, seed: u64) -> Result<ActorCritic, GraphError> {
    if bytes.len() > MAX_GRAPH_BYTES {
        return Err(GraphError::NotAGraph(format!("{} bytes, over the {MAX_GRAPH_BYTES}-byte limit", bytes.len())));
    }
    let g = GraphDef::decode(bytes).map_err(|e| GraphError::NotAGraph(e.to_string()))?;
    if g.node.is_empty() {
        return Err(GraphError::NotAGraph("no nodes".into()));
    }
    read_graph(&g, meta, seed)
}

/// [`read`] of a decoded graph.
pub fn read_graph(g: &GraphDef, meta: &ModelMetadata, seed: u64) -> Result<ActorCritic, GraphError> {
    let names = Names::of(meta)?;
    let nodes: HashMap<&str, &pb::NodeDef> = g.node.iter().map(|n| (n.name.as_str(), n)).collect();
    let Some(out) = nodes.get(names.output.as_str()).copied() else {
        let outputs: Vec<&str> =
            g.node.iter().filter(|n| n.name.ends_with("/policy")).map(|n| n.name.as_str()).collect();
        return Err(GraphError::Mismatch(format!(
            "no output node {} (nodes named …/policy: {outputs:?})",
            names.output
        )));
    };
    for input in &names.inputs {
        if !nodes.contains_key(input.as_str()) {
            return Err(GraphError::Mismatch(format!("no input placeholder {input}")));
        }
    }
    let inputs: Vec<&str> = names.inputs.iter().map(|s| s.as_str()).collect();
    let chains = vec![Vec::new(); inputs.len()];
    let mut r = Reader { nodes, inputs, memo: HashMap::new(), path: Vec::new(), chains, softmax: false };
    // Deep graphs are short chains (tens of nodes); the recursion is bounded by
    // MAX_GRAPH_DEPTH and refuses cycles.
    let Value::Data(last) = r.value(out)? else {
        return Err(GraphError::Mismatch("the output does not depend on the input".into()));
    };
    // The output: the last layer of the one chain, or of the layers after the merger.
    let end = if names.inputs.len() > 1 { names.inputs.len() } else { 0 };
    if last.a != 1.0
        || last.b != 0.0
        || last.chain != end
        || last.layer.map(|l| l + 1) != r.chains.get(end).map(|c| c.len())
    {
        return Err(GraphError::Mismatch(if r.chains.len() <= end {
            "the inputs' embeddings are never merged".into()
        } else {
            "the output is not the last layer's".into()
        }));
    }
    let discrete = matches!(meta.action_space, ActionSpace::Discrete(_));
    if r.softmax != discrete {
        return Err(GraphError::Mismatch(format!(
            "the output {} a softmax, but the action space is {}",
            if r.softmax { "is" } else { "is not" },
            if discrete { "discrete" } else { "continuous" }
        )));
    }
    let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(seed);
    let mut model = ActorCritic::new(meta, 0, &mut rng);
    if let Head::Squashed { .. } = model.head {
        // SAC's graph holds the means' rows of the last layer; the log-stds' stay fresh.
        let last = r.chains.get_mut(end).and_then(|c| c.last_mut());
        if let (Some(Read::Dense { inp, out, w, b }), Some(&Layer::Dense { inp: n_in, out: 4, offset })) =
            (last, model.pi.layers.last())
            && *out == 2
            && *inp == n_in
        {
            let p = &model.pi.params;
            w.extend_from_slice(&p[offset + 2 * n_in..offset + 4 * n_in]);
            b.extend_from_slice(&p[offset + 4 * n_in + 2..offset + 4 * n_in + 4]);
            *out = 4;
        }
    }
    for (section, read) in model.pi.sections().into_iter().zip(&r.chains) {
        fill(&mut model.pi, section, read)?;
    }
    Ok(model)
}

/// Copy the read layers into the layers `range` of `net`, which must be the same layers.
fn fill(net: &mut Net, range: std::ops::Range<usize>, read: &[Read]) -> Result<(), GraphError> {
    let at = range.start;
    let describe = |l: &Layer| match *l {
        Layer::Scale { factor, .. } => format!("scale {factor}"),
        Layer::Conv2d { filters, kernel, stride, input: [_, _, c], .. } => {
            format!("conv {kernel}×{kernel}×{c}→{filters} stride {stride}")
        }
        Layer::Dense { inp, out, .. } => format!("dense {inp}→{out}"),
        Layer::Relu { .. } => "relu".into(),
    };
    let describe_read = |l: &Read| match l {
        Read::Scale(f) => format!("scale {f}"),
        Read::Conv { kernel, stride, c, filters, .. } => {
            format!("conv {kernel}×{kernel}×{c}→{filters} stride {stride}")
        }
        Read::Dense { inp, out, .. } => format!("dense {inp}→{out}"),
        Read::Relu => "relu".into(),
    };
    let layers = &net.layers[range];
    let want: Vec<String> = layers.iter().map(describe).collect();
    let got: Vec<String> = read.iter().map(describe_read).collect();
    let same_scale = |a: f32, b: f32| ((a - b) / b).abs() < 1e-5;
    let fits = want.len() == got.len()
        && layers.iter().zip(read).all(|(l, r)| match (l, r) {
            (Layer::Scale { factor, .. }, Read::Scale(f)) => same_scale(*f, *factor),
            _ => describe(l) == describe_read(r),
        });
    if !fits {
        let first = want.iter().zip(&got).position(|(a, b)| a != b).unwrap_or(want.len().min(got.len()));
        return Err(GraphError::Mismatch(format!(
            "layer {}: the metadata's network has {}, the graph {} ({} layers against {})",
            at + first,
            want.get(first).map_or("nothing", |s| s.as_str()),
            got.get(first).map_or("nothing", |s| s.as_str()),
            want.len(),
            got.len()
        )));
    }
    for (l, r) in layers.to_vec().iter().zip(read) {
        match (l, r) {
            (Layer::Conv2d { offset, .. }, Read::Conv { w, b, .. })
            | (Layer::Dense { offset, .. }, Read::Dense { w, b, .. }) => {
                net.params[*offset..*offset + w.len()].copy_from_slice(w);
                net.params[*offset + w.len()..*offset + w.len() + b.len()].copy_from_slice(b);
            }
            _ => {}
        }
    }
    if net.params.iter().any(|v| !v.is_finite()) {
        return Err(GraphError::Mismatch("weights that are not finite".into()));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::Tape;
    use faer::Par;

    fn meta(sensor: &str, network: &str, continuous: bool) -> ModelMetadata {
        let space = if continuous {
            r#"{"steering_angle": {"low": -30, "high": 30}, "speed": {"low": 0.5, "high": 2}}"#.to_string()
        } else {
            r#"[{"steering_angle": -30, "speed": 1}, {"steering_angle": 0, "speed": 2}, {"steering_angle": 30, "speed": 1}]"#
                .to_string()
        };
        let kind = if continuous { "continuous" } else { "discrete" };
        let text = format!(
            r#"{{"action_space": {space}, "sensor": ["{sensor}"], "neural_network": "{network}",
                "training_algorithm": "clipped_ppo", "action_space_type": "{kind}", "version": "5"}}"#
        );
        ModelMetadata::parse(&text, "model_metadata.json").unwrap()
    }

    fn model(m: &ModelMetadata, seed: u64) -> ActorCritic {
        let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(seed);
        let mut a = ActorCritic::new(m, 0, &mut rng);
        // Biases that are not zero, so that a lost bias shows.
        let n = a.pi.params.len();
        for (i, p) in a.pi.params.iter_mut().enumerate() {
            *p += ((i * 7919 % 1000) as f32 / 1000.0 - 0.5) * 1e-3 * (n as f32).recip().sqrt();
        }
        a
    }

    fn output(m: &ActorCritic, x: &[f32]) -> Vec<f32> {
        let mut tape = Tape::default();
        m.pi.forward(x, 1, &mut tape, Par::Seq);
        tape.output().to_vec()
    }

    /// Issue 30: every network, sensor and action space goes out and comes back bit for bit.
    #[test]
    fn every_network_sensor_and_action_space_goes_out_and_comes_back_bit_for_bit() {
        for network in
            ["DEEP_CONVOLUTIONAL_NETWORK_SHALLOW", "DEEP_CONVOLUTIONAL_NETWORK", "DEEP_CONVOLUTIONAL_NETWORK_DEEP"]
        {
            for (sensor, continuous) in [
                ("FRONT_FACING_CAMERA", false),
                ("FRONT_FACING_CAMERA", true),
                ("STEREO_CAMERAS", false),
                ("observation", true),
            ] {
                let m = meta(sensor, network, continuous);
                let a = model(&m, 3);
                let bytes = write(&a, &m).unwrap();
                let g = GraphDef::decode(bytes.as_slice()).unwrap();
                let names = Names::of(&m).unwrap();
                assert!(g.node.iter().any(|n| n.name == names.input && n.op == "Placeholder"), "{network} {sensor}");
                let out = g.node.iter().find(|n| n.name == names.output).unwrap();
                assert_eq!(out.op, if continuous { "Identity" } else { "Softmax" });
                let ops: std::collections::BTreeSet<&str> = g.node.iter().map(|n| n.op.as_str()).collect();
                for op in &ops {
                    assert!(
                        [
                            "Placeholder",
                            "Const",
                            "RealDiv",
                            "Conv2D",
                            "BiasAdd",
                            "Relu",
                            "Reshape",
                            "MatMul",
                            "Softmax",
                            "Identity"
                        ]
                        .contains(op),
                        "{op}"
                    );
                }
                let back = read(&bytes, &m, 9).unwrap();
                assert_eq!(back.pi, a.pi, "{network} {sensor} continuous {continuous}");
                assert_eq!(back.head, a.head);
            }
        }
    }

    /// Replace node `name`'s first input `from` with `to` in `g`.
    fn rewire(g: &mut GraphDef, name: &str, to: &str) {
        let n = g.node.iter_mut().find(|n| n.name == name).unwrap();
        n.input[0] = to.into();
    }

    fn push(g: &mut GraphDef, w: Writer) {
        g.node.extend(w.nodes);
    }

    /// Issue 30: a graph as TensorFlow writes it reads the same, rescaler offsets and Keras dense
    /// layers included.
    #[test]
    fn a_graph_as_tensorflow_writes_it_reads_the_same_rescaler_offsets_and_keras_dense_included() {
        let m = meta("FRONT_FACING_CAMERA", "DEEP_CONVOLUTIONAL_NETWORK", false);
        let a = model(&m, 4);
        let mut g = graph(&a, &m).unwrap();
        let names = Names::of(&m).unwrap();
        let emb = format!("{}/{}", names.scope, names.sensor);
        let mut w = Writer { nodes: vec![] };
        // embedder.py: input / 255 − offset 0.
        let zero = w.constant("off/y", &[], &[0.0]);
        w.node("off/sub", "Sub", &[&format!("{emb}/truediv"), &zero], vec![float_type()]);
        // general_network.py's gradient rescaler before the head: (1−r)·sg(x) + r·x, r = 1.
        let x = format!("{}/middleware_fc_embedder/BatchnormActivationDropout_1_activation/Relu", names.scope);
        let one = w.constant("r/one", &[], &[1.0]);
        let r = w.constant("r/r", &[], &[1.0]);
        let one_minus = w.node("r/sub", "Sub", &[&one, &r], vec![float_type()]);
        let sg = w.node("r/sg", "StopGradient", &[&x], vec![float_type()]);
        let left = w.node("r/mul", "Mul", &[&one_minus, &sg], vec![float_type()]);
        let right = w.node("r/mul_1", "Mul", &[&r, &x], vec![float_type()]);
        w.node("r/add", "AddV2", &[&left, &right], vec![float_type()]);
        // Keras's Dense on an image in place of the 1×1 convolution (Conv2d_8): the data's
        // shape read at run time, a matrix product per pixel, reshaped back.
        let conv = format!("{emb}/Conv2d_8");
        let before = g.node.iter().find(|n| n.name == format!("{conv}/Conv2D")).unwrap().input[0].clone();
        let kernel = g.node.iter().find(|n| n.name == format!("{conv}/kernel")).unwrap().clone();
        let pb::attr_value::Value::Tensor(t) = kernel.attr["value"].value.clone().unwrap() else { panic!() };
        let (_, k) = tensor_values(&t, "k").unwrap();
        let k2 = w.constant("td/kernel", &[64, 64], &k);
        let shp = w.node("td/Shape", "Shape", &[&before], vec![float_type()]);
        let perm = w.int_constant("td/perm", &[4], &[0, 1, 2, 3]);
        let tr = w.node("td/transpose", "Transpose", &[&before, &perm], vec![float_type()]);
        let flat = w.int_constant("td/flat", &[2], &[-1, 64]);
        let r1 = w.node("td/Reshape", "Reshape", &[&tr, &flat], vec![float_type()]);
        let mm = w.node("td/MatMul", "MatMul", &[&r1, &k2], vec![float_type()]);
        w.node("td/Reshape_1", "Reshape", &[&mm, &shp], vec![float_type()]);
        push(&mut g, w);
        rewire(&mut g, &format!("{emb}/Conv2d_0/Conv2D"), "off/sub");
        rewire(&mut g, &format!("{}/ppo_head_0/policy_fc/MatMul", names.scope), "r/add");
        rewire(&mut g, &format!("{conv}/BiasAdd"), "td/Reshape_1");
        let back = read(&g.encode_to_vec(), &m, 1).unwrap();
        let x: Vec<f32> = (0..120 * 160).map(|i| (i * 31 % 256) as f32).collect();
        let (p, q) = (output(&a, &x), output(&back, &x));
        for (p, q) in p.iter().zip(&q) {
            assert!((p - q).abs() <= 1e-5 * p.abs().max(1.0), "{p} against {q}");
        }
    }

    /// Issue 30: a graph that is not the network is refused with what differs.
    #[test]
    fn a_graph_that_is_not_the_network_is_refused_with_what_differs() {
        let shallow = meta("FRONT_FACING_CAMERA", "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW", false);
        let deep = meta("FRONT_FACING_CAMERA", "DEEP_CONVOLUTIONAL_NETWORK_DEEP", false);
        let bytes = write(&model(&shallow, 1), &shallow).unwrap();
        let e = read(&bytes, &deep, 1).unwrap_err().to_string();
        assert!(e.contains("layer 3") && e.contains("conv 4×4×32→32 stride 2") && e.contains("conv 4×4×32→64"), "{e}");
        // Continuous metadata for a softmax graph; another sensor's input.
        let cont = meta("FRONT_FACING_CAMERA", "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW", true);
        let e = read(&bytes, &cont, 1).unwrap_err().to_string();
        assert!(e.contains("softmax") || e.contains("dense 512→2"), "{e}");
        let stereo = meta("STEREO_CAMERAS", "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW", false);
        assert!(read(&bytes, &stereo, 1).unwrap_err().to_string().contains("STEREO_CAMERAS"));
        // An op that is not DeepRacer's, by name.
        let mut g = GraphDef::decode(bytes.as_slice()).unwrap();
        g.node.iter_mut().find(|n| n.op == "Relu").unwrap().op = "Tanh".into();
        let e = read(&g.encode_to_vec(), &shallow, 1).unwrap_err().to_string();
        assert!(e.contains("op Tanh is not in DeepRacer's networks"), "{e}");
        // Issue 35 (the fuzzer's stack overflow): a node that is its own input, and a chain of
        // identities longer than any network's, are refused, not followed.
        let mut g = GraphDef::decode(bytes.as_slice()).unwrap();
        let relu = g.node.iter().find(|n| n.op == "Relu").unwrap().name.clone();
        rewire(&mut g, &relu, &relu);
        let e = read(&g.encode_to_vec(), &shallow, 1).unwrap_err().to_string();
        assert!(e.contains("is its own input: the graph has a cycle"), "{e}");
        let mut g = GraphDef::decode(bytes.as_slice()).unwrap();
        let into = g.node.iter().find(|n| n.op == "Relu").unwrap().input[0].clone();
        let mut last = into;
        for i in 0..10_000 {
            let mut n = g.node.iter().find(|n| n.op == "Relu").unwrap().clone();
            n.name = format!("chain/{i}");
            n.op = "Identity".into();
            n.input = vec![last];
            last = n.name.clone();
            g.node.push(n);
        }
        rewire(&mut g, &relu, &last);
        let m = shallow.clone();
        let e = std::thread::Builder::new()
            .stack_size(2 << 20)
            .spawn(move || read(&g.encode_to_vec(), &m, 1).unwrap_err().to_string())
            .unwrap()
            .join()
            .expect("no stack overflow on a thread's default stack");
        assert!(e.contains("over 256 nodes from the output"), "{e}");
        // Not a graph at all.
        assert!(matches!(read(b"\xff\xff\xff", &shallow, 1), Err(GraphError::NotAGraph(_))));
        assert!(matches!(read(b"", &shallow, 1), Err(GraphError::NotAGraph(_))));
    }

    /// Issue 32: a SAC policy goes out as DeepRacer freezes it and its means come back.
    #[test]
    fn a_sac_policy_goes_out_as_deepracer_freezes_it_and_its_means_come_back() {
        for (sensor, network) in [
            ("FRONT_FACING_CAMERA", "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW"),
            ("STEREO_CAMERAS", "DEEP_CONVOLUTIONAL_NETWORK"),
        ] {
            let text = format!(
                r#"{{"action_space": {{"steering_angle": {{"low": -30, "high": 30}}, "speed": {{"low": 1, "high": 2}}}},
                    "sensor": ["{sensor}"], "neural_network": "{network}", "training_algorithm": "sac",
                    "action_space_type": "continuous", "version": "4"}}"#
            );
            let m = ModelMetadata::parse(&text, "model_metadata.json").unwrap();
            let a = model(&m, 4);
            let bytes = write(&a, &m).unwrap();
            let g = GraphDef::decode(bytes.as_slice()).unwrap();
            // DeepRacer's names for SAC (`FROZEN_HEAD_OUTPUT_GRAPH_FORMAT_MAPPING`).
            let input = format!("main_level/agent/policy/online/network_0/{sensor}/{sensor}");
            assert!(g.node.iter().any(|n| n.name == input && n.op == "Placeholder"), "{sensor}");
            let out = "main_level/agent/policy/online/network_0/sac_policy_head_0/policy";
            assert_eq!(g.node.iter().find(|n| n.name == out).map(|n| n.op.as_str()), Some("Identity"));
            let back = read(&bytes, &m, 9).unwrap();
            assert_eq!(back.head, a.head);
            // Every layer but the last as it was; the last's two means' rows too.
            let last = a.pi.layers.len() - 1;
            let Layer::Dense { inp, offset, .. } = a.pi.layers[last] else { panic!("a dense output") };
            assert_eq!(back.pi.params[..offset + 2 * inp], a.pi.params[..offset + 2 * inp], "{sensor}");
            let bias = offset + 4 * inp;
            assert_eq!(back.pi.params[bias..bias + 2], a.pi.params[bias..bias + 2]);
            let x: Vec<f32> = (0..a.pi.in_size()).map(|i| (i * 37 % 256) as f32).collect();
            let (p, q) = (output(&a, &x), output(&back, &x));
            assert_eq!(p[..2], q[..2], "the means");
        }
    }

    /// Issue 30: what a car graph cannot hold is refused by name.
    #[test]
    fn what_a_car_graph_cannot_hold_is_refused_by_name() {
        let state = ModelMetadata::default_state_vector();
        let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(1);
        let e = write(&ActorCritic::new(&state, 20, &mut rng), &state).unwrap_err().to_string();
        assert!(e.contains("STATE_VECTOR"), "{e}");
    }

    /// Issue 31: camera and LiDAR graphs come back whole and a wrong merger is refused.
    #[test]
    fn camera_and_lidar_graphs_come_back_whole_and_a_wrong_merger_is_refused() {
        let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(31);
        for (sensors, network) in [
            ("FRONT_FACING_CAMERA\", \"SECTOR_LIDAR", "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW"),
            ("STEREO_CAMERAS\", \"LIDAR", "DEEP_CONVOLUTIONAL_NETWORK"),
            ("FRONT_FACING_CAMERA\", \"DISCRETIZED_SECTOR_LIDAR", "DEEP_CONVOLUTIONAL_NETWORK_DEEP"),
        ] {
            let m = meta(sensors, network, false);
            let model = ActorCritic::new(&m, 0, &mut rng);
            let bytes = write(&model, &m).unwrap();
            assert_eq!(Names::of(&m).unwrap().inputs.len(), 2);
            assert_eq!(read(&bytes, &m, 1).unwrap().pi, model.pi, "{sensors}");
        }
        let m = meta("FRONT_FACING_CAMERA\", \"SECTOR_LIDAR", "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW", false);
        let bytes = write(&ActorCritic::new(&m, 0, &mut rng), &m).unwrap();
        // Read as a LIDAR model (64 inputs, not 8): refused naming the layer.
        let other = meta("FRONT_FACING_CAMERA\", \"LIDAR", "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW", false);
        let mut g = GraphDef::decode(bytes.as_slice()).unwrap();
        for n in g.node.iter_mut() {
            n.name = n.name.replace("SECTOR_LIDAR", "LIDAR");
            n.input.iter_mut().for_each(|i| *i = i.replace("SECTOR_LIDAR", "LIDAR"));
        }
        let e = read(&g.encode_to_vec(), &other, 1).unwrap_err().to_string();
        assert!(e.contains("dense 64→256") && e.contains("dense 8→256"), "{e}");
        // The embeddings merged in the other order: refused.
        let mut g = GraphDef::decode(bytes.as_slice()).unwrap();
        let merger = g.node.iter_mut().find(|n| n.op == "ConcatV2").unwrap();
        merger.input.swap(0, 1);
        let e = read(&g.encode_to_vec(), &m, 1).unwrap_err().to_string();
        assert!(e.contains("merger (ConcatV2): input 0 is not the whole, flattened embedding of input 0"), "{e}");
    }
}
