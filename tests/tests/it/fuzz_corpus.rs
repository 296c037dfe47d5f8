//! What the fuzzers kept, replayed: every input in `fuzz/corpus/TARGET` (the inputs libFuzzer
//! found new coverage with), `fuzz/seeds/TARGET` and `fuzz/artifacts/TARGET` (any crash it
//! found, kept as a regression input) goes through its target again, under the test binary's
//! heap limit. Seconds, not minutes.

use std::path::Path;
use tests::fuzz;

fn inputs(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let Ok(d) = std::fs::read_dir(dir) else { return vec![] };
    let mut v: Vec<(String, Vec<u8>)> = d
        .filter_map(|e| e.ok())
        .filter(|e| e.path().is_file())
        .map(|e| (e.path().display().to_string(), std::fs::read(e.path()).unwrap()))
        .collect();
    v.sort();
    v
}

/// Issue 35: every kept fuzz input is replayed.
#[test]
fn every_kept_fuzz_input_is_replayed() {
    let root = fuzz::repo("fuzz");
    let mut replayed = 0;
    for t in fuzz::TARGETS {
        let mut n = 0;
        for kind in ["seeds", "corpus", "artifacts"] {
            for (name, bytes) in inputs(&root.join(kind).join(t)) {
                eprintln!("{name}");
                assert!(fuzz::run(t, &bytes));
                n += 1;
            }
        }
        assert!(n > 0, "{t}: nothing kept under fuzz/seeds, fuzz/corpus or fuzz/artifacts");
        replayed += n;
    }
    eprintln!("replayed {replayed} inputs");
}

/// Issue 35: every seed the code makes is committed under `fuzz/seeds/TARGET` for libFuzzer to
/// start from (`PADDOCK_WRITE_SEEDS=1` writes them again; a model's weights are not byte-for-byte
/// the same from one build to the next, so only their presence is checked).
#[test]
fn the_fuzz_seeds_are_committed() {
    let root = fuzz::repo("fuzz/seeds");
    let write = std::env::var("PADDOCK_WRITE_SEEDS").is_ok_and(|v| v == "1");
    for t in fuzz::TARGETS {
        let dir = root.join(t);
        for (i, seed) in fuzz::seeds(t).into_iter().enumerate() {
            let path = dir.join(format!("seed-{i}"));
            if write {
                std::fs::create_dir_all(&dir).unwrap();
                std::fs::write(&path, &seed).unwrap();
            }
            assert!(path.is_file(), "{}: missing (PADDOCK_WRITE_SEEDS=1 writes the seeds)", path.display());
        }
    }
}
