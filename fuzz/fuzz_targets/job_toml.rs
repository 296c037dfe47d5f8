//! libFuzzer on `tests::fuzz::job_toml`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| tests::fuzz::job_toml(data));
