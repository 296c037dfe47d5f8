//! Generates ONNX's message types from `proto/onnx.proto` (ONNX's own schema; protox parses
//! it, prost-build writes the code; no protoc needed).

fn main() {
    println!("cargo:rerun-if-changed=proto/onnx.proto");
    let fds = protox::compile(["proto/onnx.proto"], ["proto"]).expect("proto/onnx.proto compiles");
    prost_build::Config::new().compile_fds(fds).expect("prost-build generates ONNX's messages");
}
