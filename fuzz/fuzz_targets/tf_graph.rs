//! libFuzzer on `tests::fuzz::tf_graph`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| tests::fuzz::tf_graph(data));
