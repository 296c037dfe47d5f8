//! libFuzzer on `tests::fuzz::sim_config`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| tests::fuzz::sim_config(data));
