//! A learner told to use N threads runs its network maths on N threads, not on every
//! core (`Par::rayon(n)` splits work n ways but runs it on rayon's global pool). The pool is
//! one per process, and the runner (cargo-nextest) runs every test in a process of its own.

use std::collections::HashSet;
use std::sync::Mutex;

/// Issue 8: the maths runs on the threads it was given.
#[test]
fn the_maths_runs_on_the_threads_it_was_given() {
    // Three: not the core count of the machines this runs on (1, 2, 16).
    assert_eq!(learner::use_threads(Some(3)), 3);
    assert_eq!(rayon::current_num_threads(), 3);
    // A second call leaves the pool as it is, and says what the maths runs on.
    assert_eq!(learner::use_threads(Some(5)), 3);
    assert_eq!(learner::use_threads(None), 3);
    assert_eq!(rayon::current_num_threads(), 3);
    // Work spread as finely as it goes lands on the pool's three named threads.
    let seen = Mutex::new(HashSet::new());
    rayon::scope(|s| {
        for _ in 0..256 {
            s.spawn(|_| {
                std::thread::sleep(std::time::Duration::from_millis(1));
                seen.lock().unwrap().insert(std::thread::current().name().map(str::to_owned));
            });
        }
    });
    let seen = seen.into_inner().unwrap();
    assert!(!seen.is_empty() && seen.len() <= 3, "{seen:?}");
    assert!(seen.iter().all(|n| n.as_deref().is_some_and(|n| n.starts_with("maths-"))), "{seen:?}");
}
