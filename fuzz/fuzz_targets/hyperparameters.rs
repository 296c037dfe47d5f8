//! libFuzzer on `tests::fuzz::hyperparameters`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| tests::fuzz::hyperparameters(data));
