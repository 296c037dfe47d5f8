//! libFuzzer on `tests::fuzz::car_toml`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| tests::fuzz::car_toml(data));
