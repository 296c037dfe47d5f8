//! Cross-crate tests live in `tests/tests/`; this library holds what they share with the
//! fuzzers in `fuzz/`: the fuzz targets ([`fuzz`]).

pub mod fuzz;
