//! Generates the message types from `proto/paddock.proto` (pure Rust: protox parses the file,
//! prost-build writes the code; no protoc needed).

fn main() {
    println!("cargo:rerun-if-changed=proto/paddock.proto");
    let fds = protox::compile(["proto/paddock.proto"], ["proto"]).expect("proto/paddock.proto compiles");
    prost_build::Config::new().compile_fds(fds).expect("prost-build generates the messages");
}
