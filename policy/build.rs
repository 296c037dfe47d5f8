//! Generates TensorFlow's graph messages from its own schema files (`proto/tensorflow/`,
//! copied unmodified; pure Rust: protox parses them, prost-build writes the code).

fn main() {
    println!("cargo:rerun-if-changed=proto/tensorflow");
    let fds = protox::compile(["tensorflow/core/framework/graph.proto"], ["proto"])
        .expect("TensorFlow's graph.proto compiles");
    // Maps as BTreeMap: a node's attributes are encoded in key order, so the same model is
    // the same graph bytes in every process.
    prost_build::Config::new().btree_map(["."]).compile_fds(fds).expect("prost-build generates TensorFlow's messages");
}
