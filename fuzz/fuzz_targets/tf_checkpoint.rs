//! libFuzzer on `tests::fuzz::tf_checkpoint`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| tests::fuzz::tf_checkpoint(data));
