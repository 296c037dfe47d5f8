//! libFuzzer on `tests::fuzz::model_archive`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| tests::fuzz::model_archive(data));
