//! libFuzzer on `tests::fuzz::cdr`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| tests::fuzz::cdr(data));
