//! Every decoder and file parser ([`tests::fuzz`]'s targets), fed random inputs for a bounded
//! number of cases on every run of the suite.
//!
//! The coverage-guided fuzzing is `coordinator bench fuzz` (libFuzzer); this is its quick
//! counterpart, with `proptest`: each target gets random bytes and mutations of its seeds
//! (bytes flipped, inserted, dropped; truncated), and must return a value or an error: never panic. The
//! test binary's allocator is `cap`'s, limited to [`HEAP_LIMIT`]: an input that makes a parser
//! allocate beyond it (a length prefix taken at its word) aborts the run. Cases per target:
//! `PADDOCK_FUZZ_CASES` (default 20 000, about two seconds here: CI's bound on time).

use cap::Cap;
use proptest::prelude::*;
use std::alloc::System;
use tests::fuzz;

#[global_allocator]
static ALLOC: Cap<System> = Cap::new(System, HEAP_LIMIT);

/// The whole test process's heap: far above what any target needs for these small inputs.
const HEAP_LIMIT: usize = 1 << 30;

fn cases() -> u32 {
    std::env::var("PADDOCK_FUZZ_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(20_000)
}

fn config() -> ProptestConfig {
    ProptestConfig { cases: cases(), failure_persistence: None, ..ProptestConfig::default() }
}

/// A mutation of one of `seeds`: flips, insertions, removals and a truncation.
fn mutated(seeds: Vec<Vec<u8>>) -> impl Strategy<Value = Vec<u8>> {
    let n = seeds.len();
    (
        0..n,
        prop::collection::vec((any::<prop::sample::Index>(), any::<u8>(), 0..3u8), 0..12),
        prop::option::of(any::<prop::sample::Index>()),
    )
        .prop_map(move |(i, edits, cut)| {
            let mut b = seeds[i].clone();
            for (at, byte, kind) in edits {
                if b.is_empty() {
                    b.push(byte);
                    continue;
                }
                let k = at.index(b.len());
                match kind {
                    0 => b[k] = byte,
                    1 => b.insert(k, byte),
                    _ => {
                        b.remove(k);
                    }
                }
            }
            if let Some(c) = cut {
                let k = c.index(b.len() + 1);
                b.truncate(k);
            }
            b
        })
}

/// Random bytes or a mutation of a seed.
fn inputs(seeds: Vec<Vec<u8>>) -> impl Strategy<Value = Vec<u8>> {
    prop_oneof![prop::collection::vec(any::<u8>(), 0..512), mutated(seeds)]
}

macro_rules! targets {
    ($($(#[doc = $doc:literal])* $test:ident => $target:literal),* $(,)?) => {
        proptest! {
            #![proptest_config(config())]
            $(
                $(#[doc = $doc])*
                #[test]
                fn $test(bytes in inputs(fuzz::seeds($target))) {
                    assert!(fuzz::run($target, &bytes));
                }
            )*
        }

        #[test]
        fn every_target_is_fuzzed_here_and_has_seeds() {
            let here = [$($target),*];
            for t in fuzz::TARGETS {
                assert!(here.contains(&t), "{t} has no proptest");
                assert!(fuzz::seeds(t).iter().any(|s| !s.is_empty()), "{t} has no seed");
            }
        }
    };
}

targets! {
    /// Issue 10: protobuf messages, random or mutated, parse or are refused: never a panic.
    protobuf_messages_never_panic => "protobuf",
    /// Issue 10: the car's CDR messages, random or mutated, parse or are refused: never a panic.
    the_cars_cdr_messages_never_panic => "cdr",
    /// Issue 10: track .npy files, random or mutated, parse or are refused: never a panic.
    track_npy_files_never_panic => "npy",
    /// Issue 10: model_metadata.json files, random or mutated, parse or are refused: never a panic.
    model_metadata_json_never_panic => "model_metadata",
    /// Issue 10: hyperparameters.json files, random or mutated, parse or are refused: never a panic.
    hyperparameters_json_never_panic => "hyperparameters",
    /// Issue 10: job TOML files, random or mutated, parse or are refused: never a panic.
    job_toml_never_panic => "job_toml",
    /// Issue 10: car TOML files, random or mutated, parse or are refused: never a panic.
    car_toml_never_panic => "car_toml",
    /// Issue 10: simulator config TOML files, random or mutated, parse or are refused: never a panic.
    sim_config_toml_never_panic => "sim_config",
    /// Issue 10: a model folder's weights, random or mutated, parse or are refused: never a panic.
    model_folder_weights_never_panic => "safetensors",
    /// Issue 35: TensorFlow graphs, random or mutated, parse or are refused: never a panic.
    tf_graphs_never_panic => "tf_graph",
    /// Issue 35: model archives, random or mutated, parse or are refused: never a panic.
    model_archives_never_panic => "model_archive",
    /// Issue 35: signatures, random or mutated, parse or are refused: never a panic.
    signatures_never_panic => "signature",
    /// Issue 53: TensorFlow checkpoints, random or mutated, parse or are refused: never a panic.
    tf_checkpoints_never_panic => "tf_checkpoint",
}

/// The allocator's limit is real: a request beyond it fails (and the run would abort).
#[test]
fn the_heap_limit_is_in_force() {
    assert_eq!(ALLOC.limit(), HEAP_LIMIT);
    assert!(ALLOC.allocated() < HEAP_LIMIT / 4, "the fuzz targets' baseline");
    let mut v: Vec<u8> = Vec::new();
    assert!(v.try_reserve_exact(HEAP_LIMIT).is_err(), "a reservation beyond the limit is refused");
}
