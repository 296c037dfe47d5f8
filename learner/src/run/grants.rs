//! Flow control: for each policy version the learner grants the live workers, between them,
//! the episodes the next update still needs ([`Credit`]), in rounds. A round is spent when
//! every worker it granted delivered its share or went away; then the shortfall, if any, is
//! granted anew to those alive. A round is void when nothing came for much longer than rounds
//! take and than episodes have come apart (a batch lost while a peer's subscription was still
//! on its way, say); lap-long episodes leave long silences that are not stalls. The current
//! round's grant is announced again every second (workers treat it as idempotent). Pure: the
//! caller passes the time, so the rules are tested on tables.

use policy::exchange::Credit;
use std::collections::BTreeMap;
use std::time::{Duration, Instant};

/// How often the current grant is announced again.
const ANNOUNCE_EVERY: Duration = Duration::from_secs(1);

/// A grant round in progress.
struct Round {
    credit: Credit,
    delivered: BTreeMap<String, u64>,
    started: Instant,
    last_delivery: Instant,
    /// The longest silence so far between the round's start or a delivery and the next delivery.
    longest_gap: f64,
    /// Every worker delivered its share, and the round's time was taken.
    timed: bool,
}

/// The rounds of one run.
pub(super) struct Grants {
    round: Option<Round>,
    /// The last round's number: they count up from the run's base, through every version
    /// (a restarted learner's grants are never taken for repeats of its predecessor's, nor a
    /// new round of the same version for a repeat of the last).
    number: u64,
    last_announced: Option<Instant>,
    /// How long rounds take to be delivered in full (a moving average).
    round_seconds: Option<f64>,
    /// The longest silence between deliveries in the rounds that ended: it follows a longer
    /// one at once and a shorter one slowly, as episodes grow from a few steps to whole laps
    /// (the round in progress counts too, in [`Grants::stall_after`]).
    gap_seconds: Option<f64>,
}

/// How much of the longest silence so far a round that saw shorter ones keeps.
const GAP_KEEP: f64 = 0.9;

impl Grants {
    /// No round yet; round numbers start above `base`.
    pub(super) fn new(base: u64) -> Grants {
        Grants { round: None, number: base, last_announced: None, round_seconds: None, gap_seconds: None }
    }

    /// Round numbers above the wall clock's milliseconds × 1000 when the run starts.
    pub(super) fn from_clock() -> Grants {
        let base = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_millis() as u64 * 1000)
            .unwrap_or(0);
        Grants::new(base)
    }

    /// `n` episodes arrived from `worker` under the grant `credit` (version, round) at `now`.
    pub(super) fn delivered(&mut self, credit: (u64, u64), worker: &str, n: u64, now: Instant) {
        let Some(r) = self.round.as_mut().filter(|r| (r.credit.version, r.credit.round) == credit) else { return };
        *r.delivered.entry(worker.to_string()).or_default() += n;
        r.longest_gap = r.longest_gap.max(now.duration_since(r.last_delivery).as_secs_f64());
        r.last_delivery = now;
        let full = r.credit.episodes.iter().all(|(w, n)| r.delivered.get(w).copied().unwrap_or(0) >= *n);
        if full && !r.timed {
            r.timed = true;
            let took = now.duration_since(r.started).as_secs_f64();
            self.round_seconds = Some(self.round_seconds.map_or(took, |s| 0.8 * s + 0.2 * took));
        }
    }

    /// The silence after which a round is taken for stalled: twice a round's time and three
    /// times the longest silence between deliveries lately, at least 10 s (30 s before any
    /// came).
    fn stall_after(&self) -> f64 {
        let now = self.round.as_ref().map(|r| r.longest_gap).filter(|g| *g > 0.0);
        let gap = [self.gap_seconds, now].into_iter().flatten().reduce(f64::max);
        match (self.round_seconds, gap) {
            (None, None) => 30.0,
            (r, g) => (2.0 * r.unwrap_or(0.0)).max(3.0 * g.unwrap_or(0.0)).max(10.0),
        }
    }

    /// The round in progress ends: the next one starts from its silences, a shorter longest
    /// one fading in slowly.
    fn end_round(&mut self) {
        if let Some(r) = self.round.take() {
            self.gap_seconds = Some(self.gap_seconds.map_or(r.longest_gap, |g| r.longest_gap.max(GAP_KEEP * g)));
        }
    }

    /// No round in progress (after an update, or when the run stops): the next call of
    /// [`Grants::due`] grants afresh, at once.
    pub(super) fn clear(&mut self) {
        self.end_round();
        self.last_announced = None;
    }

    /// The grant to announce at `now`, if any: a new round for `shortfall` episodes of
    /// `version` when the current one is spent (or void, or there is none), split evenly over
    /// `workers`; else the current round's, once a second.
    pub(super) fn due(&mut self, version: u64, shortfall: u64, workers: &[String], now: Instant) -> Option<Credit> {
        let stall_after = self.stall_after();
        let spent = self.round.as_ref().is_none_or(|r| {
            let delivered = (r.credit.episodes.iter())
                .all(|(w, n)| r.delivered.get(w).copied().unwrap_or(0) >= *n || !workers.contains(w));
            let stalled = now.duration_since(r.last_delivery).as_secs_f64() > stall_after;
            if stalled && !delivered && shortfall > 0 {
                tracing::warn!(
                    version = r.credit.version,
                    "no episodes for {stall_after:.0} s: granting the shortfall again"
                );
            }
            stalled || delivered
        });
        if shortfall > 0 && spent {
            self.number += 1;
            self.end_round();
            self.round = split(version, self.number, shortfall, workers).map(|credit| Round {
                credit,
                delivered: BTreeMap::new(),
                started: now,
                last_delivery: now,
                longest_gap: 0.0,
                timed: false,
            });
            tracing::debug!(version, shortfall, workers = ?workers, granted = self.round.is_some(), "grant round");
            self.last_announced = None;
        }
        let r = self.round.as_ref()?;
        if self.last_announced.is_some_and(|t| now.duration_since(t) < ANNOUNCE_EVERY) {
            return None;
        }
        self.last_announced = Some(now);
        Some(r.credit.clone())
    }
}

/// `need` episodes of `version` split over `workers` (the first ones take the remainder), as
/// round `number`; `None` with nobody to grant or nothing needed.
fn split(version: u64, number: u64, need: u64, workers: &[String]) -> Option<Credit> {
    if workers.is_empty() || need == 0 {
        return None;
    }
    let n = workers.len() as u64;
    let episodes =
        workers.iter().enumerate().map(|(i, w)| (w.clone(), need / n + u64::from((i as u64) < need % n))).collect();
    Some(Credit { version, round: number, episodes, checks_closed_through: 0 })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(ws: &[&str]) -> Vec<String> {
        ws.iter().map(|w| w.to_string()).collect()
    }

    fn shares(c: &Credit) -> Vec<(String, u64)> {
        c.episodes.iter().map(|(w, n)| (w.clone(), *n)).collect()
    }

    /// Issue 29: the shortfall is split over the workers alive.
    #[test]
    fn the_shortfall_is_split_over_the_workers_alive() {
        // (need, workers, shares)
        type Row<'a> = (u64, &'a [&'a str], &'a [(&'a str, u64)]);
        let table: [Row; 4] = [
            (20, &["a", "b"], &[("a", 10), ("b", 10)]),
            (20, &["a", "b", "c"], &[("a", 7), ("b", 7), ("c", 6)]),
            (2, &["a", "b", "c"], &[("a", 1), ("b", 1), ("c", 0)]),
            (5, &["a"], &[("a", 5)]),
        ];
        for (need, workers, want) in table {
            let c = split(3, 1, need, &names(workers)).unwrap();
            let want: Vec<(String, u64)> = want.iter().map(|(w, n)| (w.to_string(), *n)).collect();
            assert_eq!(shares(&c), want, "{need} over {workers:?}");
        }
        assert_eq!(split(3, 1, 0, &names(&["a"])), None);
        assert_eq!(split(3, 1, 20, &[]), None);
    }

    /// Issue 32: a new round after `clear` is numbered above the last, even for the same version.
    #[test]
    fn a_new_round_after_clear_is_numbered_above_the_last_even_for_the_same_version() {
        let t0 = Instant::now();
        let a = names(&["a"]);
        let mut g = Grants::new(1000);
        assert_eq!(g.due(4, 20, &a, t0).map(|c| (c.version, c.round)), Some((4, 1001)));
        // SAC grants the next round, of the same version, as its update starts: a worker must
        // not take it for a repeat of the one it just delivered.
        g.clear();
        assert_eq!(g.due(4, 20, &a, t0).map(|c| (c.version, c.round)), Some((4, 1002)));
        g.clear();
        assert_eq!(g.due(5, 20, &a, t0).map(|c| (c.version, c.round)), Some((5, 1003)));
    }

    /// Issue 29: a round is announced every second until spent, then the shortfall is granted anew.
    #[test]
    fn a_round_is_announced_every_second_until_spent_then_the_shortfall_is_granted_anew() {
        let t0 = Instant::now();
        let at = |s: f64| t0 + Duration::from_secs_f64(s);
        let ab = names(&["a", "b"]);
        let mut g = Grants::new(1000);
        // (seconds, version, shortfall, workers, deliveries before: (worker, episodes), the
        // announcement wanted: None, or (round, shares))
        type Row<'a> = (f64, u64, u64, &'a [String], &'a [(&'a str, u64)], Option<(u64, &'a [(&'a str, u64)])>);
        let table: Vec<Row> = vec![
            (0.0, 1, 20, &ab, &[], Some((1001, &[("a", 10), ("b", 10)]))),
            // Within the second: nothing new; after it: the same grant again.
            (0.5, 1, 20, &ab, &[], None),
            (1.0, 1, 20, &ab, &[], Some((1001, &[("a", 10), ("b", 10)]))),
            // a delivered its share, b half of it: the round is not spent.
            (1.5, 1, 5, &ab, &[("a", 10), ("b", 5)], None),
            (2.0, 1, 5, &ab, &[], Some((1001, &[("a", 10), ("b", 10)]))),
            // b went away: the round is spent; the shortfall goes to a, in a new round.
            (2.2, 1, 5, &ab[..1], &[], Some((1002, &[("a", 5)]))),
            // a delivers; nothing is short: no new round; the spent one is announced once a
            // second still (harmless: a worker has nothing left of it to start).
            (2.4, 1, 0, &ab[..1], &[("a", 5)], None),
            (3.2, 1, 0, &ab[..1], &[], Some((1002, &[("a", 5)]))),
            // The round was delivered in full; a shortfall again (episodes dropped, say) is
            // granted anew to the workers alive.
            (14.0, 1, 3, &ab, &[], Some((1003, &[("a", 2), ("b", 1)]))),
        ];
        for (i, (s, version, short, workers, deliveries, want)) in table.into_iter().enumerate() {
            for (w, n) in deliveries {
                let round = g.round.as_ref().map(|r| r.credit.round).unwrap();
                g.delivered((version, round), w, *n, at(s));
            }
            let got = g.due(version, short, workers, at(s));
            let want = want.map(|(round, shares)| Credit {
                version,
                round,
                episodes: shares.iter().map(|(w, n)| (w.to_string(), *n)).collect(),
                checks_closed_through: 0,
            });
            assert_eq!(got, want, "row {i} at {s} s");
        }
        // Deliveries under another grant (an older round, another version) change nothing.
        let before = g.round.as_ref().unwrap().delivered.clone();
        g.delivered((1, 1001), "a", 4, at(15.0));
        g.delivered((2, 1003), "a", 4, at(15.0));
        assert_eq!(g.round.as_ref().unwrap().delivered, before);
    }

    /// Issue 55: lap-long episodes leave silences of many seconds between deliveries; a round
    /// is taken for stalled only after a silence well beyond those its last rounds saw, and a
    /// round is timed when delivered in full, not at its first episode.
    #[test]
    fn silences_like_the_last_rounds_are_waited_out_and_a_longer_one_is_a_stall() {
        let t0 = Instant::now();
        let at = |s: f64| t0 + Duration::from_secs_f64(s);
        let a = names(&["a"]);
        let mut g = Grants::new(0);
        // Round 1: one short episode at once, the other 19 a lap later.
        let r1 = g.due(1, 20, &a, at(0.0)).unwrap().round;
        g.delivered((1, r1), "a", 1, at(0.5));
        g.delivered((1, r1), "a", 19, at(12.5));
        assert_eq!(g.round_seconds, Some(12.5), "timed when delivered in full");
        assert_eq!(g.stall_after(), 36.0, "three times the 12 s silence");
        // The update; round 2 starts, one episode comes at once, then silence.
        g.clear();
        let r2 = g.due(2, 20, &a, at(13.0)).unwrap().round;
        assert!(r2 > r1);
        g.delivered((2, r2), "a", 1, at(13.5));
        // (seconds, the round announced: None when within the second)
        for (s, want) in [(30.0, Some(r2)), (49.0, Some(r2)), (49.6, Some(r2 + 1))] {
            assert_eq!(g.due(2, 19, &a, at(s)).map(|c| c.round), want, "at {s} s");
        }
        // Rounds of short episodes bring the threshold down slowly, to 10 s at the least.
        for v in 3..40 {
            g.clear();
            let r = g.due(v, 20, &a, at(100.0 * v as f64)).unwrap().round;
            g.delivered((v, r), "a", 20, at(100.0 * v as f64 + 0.5));
        }
        assert_eq!(g.stall_after(), 10.0);
    }

    /// Issue 29: after an update the next version is granted at once, in a new round.
    #[test]
    fn after_an_update_the_next_version_is_granted_at_once_in_a_new_round() {
        let t0 = Instant::now();
        let mut g = Grants::new(50);
        let a = names(&["a"]);
        assert_eq!(g.due(1, 20, &a, t0).map(|c| c.round), Some(51));
        g.clear();
        let c = g.due(2, 20, &a, t0 + Duration::from_millis(10)).expect("granted at once");
        assert_eq!((c.version, c.round), (2, 52));
        // With no worker alive, nothing is granted.
        g.clear();
        assert_eq!(g.due(3, 20, &[], t0), None);
    }
}
