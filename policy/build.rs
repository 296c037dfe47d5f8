//! Generates TensorFlow's graph messages from its own schema files (`proto/tensorflow/`,
//! copied unmodified; pure Rust: protox parses them, prost-build writes the code).

fn main() {
    println!("cargo:rerun-if-changed=proto/tensorflow");
    let fds = protox::compile(["tensorflow/core/framework/graph.proto"], ["proto"])
        .expect("TensorFlow's graph.proto compiles");
    prost_build::Config::new().compile_fds(fds).expect("prost-build generates TensorFlow's messages");
}
