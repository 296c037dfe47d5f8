//! A model's policy tower as ONNX, for runtimes such as OpenVINO and onnxruntime.
//!
//! The graph takes DeepRacer's input, `observation` of shape `[N, 120, 160, C]` (NHWC, grey
//! levels 0–255, C = 1 or 2 for stereo; `[N, n]` for a state-vector model), and gives `logits`
//! (`[N, actions]`, or the two Gaussian means of a continuous space) and, for a discrete
//! space, `probabilities` (their softmax: DeepRacer's policy output); for a SAC model,
//! `logits` are the two means and the two log-stds, and `action` is `tanh` of the means (in
//! [-1, 1]; the car maps it linearly onto the action ranges, as the simulator does). Layers
//! map one to one:
//! the in-graph `/255` is `Mul`; Paddock's NHWC convolutions are ONNX's NCHW `Conv` between
//! two `Transpose`s (weights `[f, ky, kx, c]` become `[f, c, ky, kx]`); dense layers are
//! `Gemm` with `transB` (Paddock keeps `W` as `out × in`), after a `Flatten` of the NHWC
//! activations, so that the flattening order is Paddock's. Opset 13; `N` is symbolic.
//!
//! A camera + LiDAR model has one input per sensor, named as `model_metadata.json` names them
//! (`FRONT_FACING_CAMERA` `[N, 120, 160, 1]`, `SECTOR_LIDAR` `[N, 8]`, …): each goes through
//! its embedder, and the embedders' outputs are concatenated (`Concat`, in DeepRacer's sorted
//! input order) into the middleware.

use policy::ActorCritic;
use policy::model::Head;
use policy::nn::{InputShape, Layer, Net};
use prost::Message;

#[allow(missing_docs, clippy::all)]
mod pb {
    include!(concat!(env!("OUT_DIR"), "/onnx.rs"));
}

const FLOAT: i32 = 1; // TensorProto.DataType.FLOAT

fn tensor(name: &str, dims: &[usize], values: Vec<f32>) -> pb::TensorProto {
    pb::TensorProto {
        name: Some(name.into()),
        dims: dims.iter().map(|d| *d as i64).collect(),
        data_type: Some(FLOAT),
        float_data: values,
        ..Default::default()
    }
}

/// A one-element INT64 tensor (`Slice`'s starts, ends and axes).
fn int64_tensor(name: &str, v: i64) -> pb::TensorProto {
    pb::TensorProto {
        name: Some(name.into()),
        dims: vec![1],
        data_type: Some(7), // TensorProto.DataType.INT64
        int64_data: vec![v],
        ..Default::default()
    }
}

fn node(op: &str, inputs: &[&str], output: &str, attributes: Vec<pb::AttributeProto>) -> pb::NodeProto {
    pb::NodeProto {
        op_type: Some(op.into()),
        input: inputs.iter().map(|s| s.to_string()).collect(),
        output: vec![output.into()],
        name: Some(output.into()),
        attribute: attributes,
        ..Default::default()
    }
}

fn ints(name: &str, v: &[i64]) -> pb::AttributeProto {
    pb::AttributeProto {
        name: Some(name.into()),
        r#type: Some(pb::attribute_proto::AttributeType::Ints as i32),
        ints: v.to_vec(),
        ..Default::default()
    }
}

fn int(name: &str, v: i64) -> pb::AttributeProto {
    pb::AttributeProto {
        name: Some(name.into()),
        r#type: Some(pb::attribute_proto::AttributeType::Int as i32),
        i: Some(v),
        ..Default::default()
    }
}

fn value_info(name: &str, dims: &[Option<usize>]) -> pb::ValueInfoProto {
    use pb::tensor_shape_proto::{Dimension, dimension::Value};
    let dim = dims
        .iter()
        .map(|d| Dimension {
            value: Some(match d {
                Some(n) => Value::DimValue(*n as i64),
                None => Value::DimParam("N".into()),
            }),
            ..Default::default()
        })
        .collect();
    pb::ValueInfoProto {
        name: Some(name.into()),
        r#type: Some(pb::TypeProto {
            value: Some(pb::type_proto::Value::TensorType(pb::type_proto::Tensor {
                elem_type: Some(FLOAT),
                shape: Some(pb::TensorShapeProto { dim }),
            })),
            ..Default::default()
        }),
        ..Default::default()
    }
}

/// What a run of layers has made of its value so far.
#[derive(Clone, Copy)]
struct Form {
    nchw: bool,
    flat: bool,
}

/// The ONNX nodes of layer `i` of `net` on `cur`; its output's name.
fn emit(
    net: &Net,
    i: usize,
    cur: &str,
    form: &mut Form,
    nodes: &mut Vec<pb::NodeProto>,
    init: &mut Vec<pb::TensorProto>,
) -> String {
    let out = format!("l{i}");
    let mut cur = cur.to_string();
    match net.layers[i] {
        Layer::Scale { factor, .. } => {
            init.push(tensor(&format!("l{i}.factor"), &[], vec![factor]));
            nodes.push(node("Mul", &[&cur, &format!("l{i}.factor")], &out, vec![]));
        }
        Layer::Relu { .. } => nodes.push(node("Relu", &[&cur], &out, vec![])),
        Layer::Conv2d { input: [_, _, c], filters, kernel: k, stride, offset } => {
            if !form.nchw {
                let t = format!("l{i}.nchw");
                nodes.push(node("Transpose", &[&cur], &t, vec![ints("perm", &[0, 3, 1, 2])]));
                cur = t;
                form.nchw = true;
            }
            let w = &net.params[offset..offset + filters * k * k * c];
            let mut wt = vec![0.0f32; w.len()];
            for f in 0..filters {
                for ky in 0..k {
                    for kx in 0..k {
                        for ch in 0..c {
                            wt[((f * c + ch) * k + ky) * k + kx] = w[((f * k + ky) * k + kx) * c + ch];
                        }
                    }
                }
            }
            let b = net.params[offset + w.len()..offset + w.len() + filters].to_vec();
            init.push(tensor(&format!("l{i}.weight"), &[filters, c, k, k], wt));
            init.push(tensor(&format!("l{i}.bias"), &[filters], b));
            nodes.push(node(
                "Conv",
                &[&cur, &format!("l{i}.weight"), &format!("l{i}.bias")],
                &out,
                vec![ints("kernel_shape", &[k as i64, k as i64]), ints("strides", &[stride as i64, stride as i64])],
            ));
        }
        Layer::Dense { inp, out: n, offset } => {
            cur = flatten(&cur, &format!("l{i}"), form, nodes);
            init.push(tensor(&format!("l{i}.weight"), &[n, inp], net.params[offset..offset + inp * n].to_vec()));
            init.push(tensor(&format!("l{i}.bias"), &[n], net.params[offset + inp * n..offset + inp * n + n].to_vec()));
            nodes.push(node(
                "Gemm",
                &[&cur, &format!("l{i}.weight"), &format!("l{i}.bias")],
                &out,
                vec![int("transB", 1)],
            ));
        }
    }
    out
}

/// `cur` as `[N, features]` in Paddock's (NHWC) order.
fn flatten(cur: &str, prefix: &str, form: &mut Form, nodes: &mut Vec<pb::NodeProto>) -> String {
    let mut cur = cur.to_string();
    if form.nchw {
        let t = format!("{prefix}.nhwc");
        nodes.push(node("Transpose", &[&cur], &t, vec![ints("perm", &[0, 2, 3, 1])]));
        cur = t;
        form.nchw = false;
    }
    if !form.flat {
        let t = format!("{prefix}.flat");
        nodes.push(node("Flatten", &[&cur], &t, vec![int("axis", 1)]));
        cur = t;
        form.flat = true;
    }
    cur
}

/// The policy tower of `model` as an ONNX model's bytes; `name` goes in the graph's name.
/// A camera + LiDAR model takes one input per sensor, named as DeepRacer names them.
pub fn policy_to_onnx(model: &ActorCritic, name: &str) -> Vec<u8> {
    let net: &Net = &model.pi;
    let mut nodes = Vec::new();
    let mut init = Vec::new();
    let sections = net.sections();
    let shape = |s: InputShape| match s {
        InputShape::Image(h, w, c) => vec![None, Some(h), Some(w), Some(c)],
        InputShape::Flat(n) => vec![None, Some(n)],
    };
    let (inputs, cur) = if net.inputs.is_empty() {
        let first_shape = match net.layers.iter().find(|l| matches!(l, Layer::Conv2d { .. })) {
            Some(Layer::Conv2d { input: [h, w, c], .. }) => vec![None, Some(*h), Some(*w), Some(*c)],
            _ => vec![None, Some(net.in_size())],
        };
        let mut form = Form { nchw: false, flat: first_shape.len() == 2 };
        let mut cur = "observation".to_string();
        for i in 0..net.layers.len() {
            cur = emit(net, i, &cur, &mut form, &mut nodes, &mut init);
        }
        (vec![value_info("observation", &first_shape)], cur)
    } else {
        // Each sensor through its embedder, flattened; side by side; then the rest.
        let mut merged = Vec::new();
        for (e, range) in net.inputs.iter().zip(&sections) {
            let mut form = Form { nchw: false, flat: matches!(e.shape, InputShape::Flat(_)) };
            let mut cur = e.name.clone();
            for i in range.clone() {
                cur = emit(net, i, &cur, &mut form, &mut nodes, &mut init);
            }
            merged.push(flatten(&cur, &format!("{}.out", e.name), &mut form, &mut nodes));
        }
        let ins: Vec<&str> = merged.iter().map(|s| s.as_str()).collect();
        nodes.push(node("Concat", &ins, "merged", vec![int("axis", 1)]));
        let mut form = Form { nchw: false, flat: true };
        let mut cur = "merged".to_string();
        for i in sections.last().expect("the rest").clone() {
            cur = emit(net, i, &cur, &mut form, &mut nodes, &mut init);
        }
        (net.inputs.iter().map(|e| value_info(&e.name, &shape(e.shape))).collect(), cur)
    };
    let actions = net.out_size();
    nodes.push(node("Identity", &[&cur], "logits", vec![]));
    let mut outputs = vec![value_info("logits", &[None, Some(actions)])];
    match model.head {
        Head::Categorical(_) => {
            nodes.push(node("Softmax", &["logits"], "probabilities", vec![int("axis", 1)]));
            outputs.push(value_info("probabilities", &[None, Some(actions)]));
        }
        Head::Squashed { .. } => {
            // SAC: the means are the first two outputs; the action is their tanh.
            for (name, v) in [("means.starts", 0), ("means.ends", 2), ("means.axes", 1)] {
                init.push(int64_tensor(name, v));
            }
            nodes.push(node("Slice", &["logits", "means.starts", "means.ends", "means.axes"], "means", vec![]));
            nodes.push(node("Tanh", &["means"], "action", vec![]));
            outputs.push(value_info("action", &[None, Some(2)]));
        }
        Head::Gaussian { .. } => {}
    }
    let graph = pb::GraphProto {
        name: Some(name.into()),
        node: nodes,
        initializer: init,
        input: inputs,
        output: outputs,
        ..Default::default()
    };
    pb::ModelProto {
        ir_version: Some(8),
        producer_name: Some("paddock".into()),
        producer_version: Some(env!("CARGO_PKG_VERSION").into()),
        opset_import: vec![pb::OperatorSetIdProto { domain: Some(String::new()), version: Some(13) }],
        graph: Some(graph),
        ..Default::default()
    }
    .encode_to_vec()
}
