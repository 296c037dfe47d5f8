//! Requests the console refused, counted by reason: every refusal is logged and counted, and
//! `GET /api/v1/health` shows the counts.

use std::collections::BTreeMap;
use std::sync::Mutex;

static REFUSED: Mutex<BTreeMap<&'static str, u64>> = Mutex::new(BTreeMap::new());

/// Count one refused request.
pub fn refused(reason: &'static str) {
    *REFUSED.lock().expect("counters").entry(reason).or_default() += 1;
    tracing::warn!(reason, "refused a request");
}

/// The counts so far.
pub fn all() -> BTreeMap<&'static str, u64> {
    REFUSED.lock().expect("counters").clone()
}
