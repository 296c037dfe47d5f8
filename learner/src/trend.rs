//! When to stop: DeepRacer's advice is to stop when track completion stops improving. This
//! reads the evaluations' mean progress as they come and says whether training still
//! improves, has reached a plateau (no evaluation beat the best by `min_gain` points for
//! `plateau_evals` evaluations), or has collapsed after a peak (the latest evaluation fell
//! `collapse_drop` points or more below a best of at least `collapse_floor` %), as a long
//! run of the default job can. A pure function of the evaluations, tested on tables.

use serde::Serialize;

/// How the evaluations are going.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Verdict {
    /// Still improving (or too early to say).
    #[default]
    Improving,
    /// No evaluation improved on the best for `evals` evaluations.
    Plateau {
        /// The best mean progress.
        best: f64,
        /// Its iteration.
        best_iteration: u64,
        /// Evaluations since.
        evals: usize,
    },
    /// The latest evaluation fell far below the best.
    Collapse {
        /// The best mean progress.
        best: f64,
        /// Its iteration.
        best_iteration: u64,
        /// The latest mean progress.
        now: f64,
    },
}

impl Verdict {
    /// One line for logs, `job status` and reports (empty while improving).
    pub fn describe(&self) -> String {
        match self {
            Verdict::Improving => String::new(),
            Verdict::Plateau { best, best_iteration, evals } => format!(
                "plateau: evaluation progress has not improved for {evals} evaluations (best {best:.1} % at iteration {best_iteration})"
            ),
            Verdict::Collapse { best, best_iteration, now } => format!(
                "collapse: evaluation progress fell to {now:.1} % from {best:.1} % at iteration {best_iteration} (the best model is kept)"
            ),
        }
    }
}

/// The thresholds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrendRules {
    /// Evaluations without improvement that make a plateau.
    pub plateau_evals: usize,
    /// Percentage points an evaluation must beat the best by to count as improvement.
    pub min_gain: f64,
    /// Percentage points below the best that make a collapse.
    pub collapse_drop: f64,
    /// A collapse needs a best of at least this (%).
    pub collapse_floor: f64,
}

impl Default for TrendRules {
    fn default() -> Self {
        TrendRules { plateau_evals: 5, min_gain: 1.0, collapse_drop: 25.0, collapse_floor: 50.0 }
    }
}

/// The evaluations so far.
#[derive(Clone, Debug, Default)]
pub struct Trend {
    rules: TrendRules,
    best: Option<(u64, f64)>,
    since_best: usize,
}

impl Trend {
    /// An empty history under `rules`.
    pub fn new(rules: TrendRules) -> Trend {
        Trend { rules, best: None, since_best: 0 }
    }

    /// Take an evaluation (its iteration and mean progress) and say how things stand.
    pub fn push(&mut self, iteration: u64, progress: f64) -> Verdict {
        match self.best {
            Some((_, b)) if progress < b + self.rules.min_gain => self.since_best += 1,
            _ => {
                if self.best.is_none_or(|(_, b)| progress > b) {
                    self.best = Some((iteration, progress));
                }
                self.since_best = 0;
            }
        }
        let (best_iteration, best) = self.best.expect("set above");
        if best >= self.rules.collapse_floor && progress <= best - self.rules.collapse_drop {
            Verdict::Collapse { best, best_iteration, now: progress }
        } else if self.since_best >= self.rules.plateau_evals.max(1) {
            Verdict::Plateau { best, best_iteration, evals: self.since_best }
        } else {
            Verdict::Improving
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 11: plateaus and collapses of evaluation progress are told apart.
    #[test]
    fn plateaus_and_collapses_are_told_apart() {
        let rules = TrendRules { plateau_evals: 3, ..TrendRules::default() };
        // (evaluations' mean progress, the verdict after the last one)
        let table: [(&[f64], &str); 7] = [
            (&[10.0, 20.0, 30.0, 45.0], "improving"),
            (&[40.0, 60.0, 60.5, 59.0, 60.2], "plateau"),
            (&[40.0, 60.0, 60.5, 59.0], "improving"),
            (&[40.0, 60.0, 62.0, 59.0, 61.5], "improving"),
            (&[50.0, 100.0, 100.0, 70.0], "collapse"),
            (&[20.0, 40.0, 10.0], "improving"), // a drop from a low best is noise, not a collapse
            (&[50.0, 100.0, 100.0, 100.0, 100.0], "plateau"),
        ];
        for (evals, want) in table {
            let mut t = Trend::new(rules);
            let mut v = Verdict::Improving;
            for (i, p) in evals.iter().enumerate() {
                v = t.push(i as u64 + 1, *p);
            }
            let got = match v {
                Verdict::Improving => "improving",
                Verdict::Plateau { .. } => "plateau",
                Verdict::Collapse { .. } => "collapse",
            };
            assert_eq!(got, want, "{evals:?}: {}", v.describe());
        }
        let mut t = Trend::new(rules);
        for (i, p) in [50.0, 100.0, 90.0, 60.0].into_iter().enumerate() {
            let v = t.push(10 * (i as u64 + 1), p);
            if i == 3 {
                assert_eq!(v, Verdict::Collapse { best: 100.0, best_iteration: 20, now: 60.0 });
                assert!(v.describe().contains("fell to 60.0 % from 100.0 % at iteration 20"));
            }
        }
    }
}
