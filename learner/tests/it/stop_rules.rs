//! Every stop condition means one thing, decided in one place (`StopRules::check`),
//! whichever transport the run uses. A table of standings and the reason each gives.

use learner::Hyperparameters;
use learner::run::{Standing, StopRules, TargetLaps};
use learner::trend::Verdict;

/// Issue 8: each stop rule fires on its own figure and not before.
#[test]
fn each_stop_rule_fires_on_its_own_figure_and_not_before() {
    let rules = StopRules {
        minutes: 2.0,
        max_episodes: Some(500),
        target_progress: Some(90.0),
        target_reward: Some(300.0),
        window: 20,
        env_steps_budget: Some(1_000_000),
        target_laps: Some(TargetLaps { laps: 3, evaluations: 2, verify_trials: 0 }),
        plateau_evals: Some(5),
        stop_on_collapse: true,
    };
    let hyper = Hyperparameters { term_cond_max_episodes: 800, term_cond_avg_score: 250.0, ..Default::default() };
    let quiet = Standing {
        seconds: 10.0,
        episodes: 100,
        env_steps: 5_000,
        window: Some((50.0, 100.0)),
        lap_streak: 0,
        verified: None,
        verdict: Verdict::Improving,
    };
    let plateau = Verdict::Plateau { best: 80.0, best_iteration: 12, evals: 5 };
    let collapse = Verdict::Collapse { best: 100.0, best_iteration: 40, now: 30.0 };
    // (what changes, the reason's words; None: no stop)
    let table: Vec<(Standing, Option<&str>)> = vec![
        (quiet.clone(), None),
        (Standing { seconds: 120.0, ..quiet.clone() }, Some("time limit of 2 min")),
        (Standing { episodes: 500, ..quiet.clone() }, Some("500 episodes reached")),
        (Standing { window: Some((90.0, 100.0)), ..quiet.clone() }, Some("reached the target 90")),
        // The window must be full: no target decisions on a handful of episodes.
        (Standing { window: None, ..quiet.clone() }, None),
        (Standing { window: Some((50.0, 300.0)), ..quiet.clone() }, Some("reached the target 300")),
        (Standing { env_steps: 1_000_000, ..quiet.clone() }, Some("compute budget of 1000000 env steps")),
        (Standing { lap_streak: 1, ..quiet.clone() }, None),
        (Standing { lap_streak: 2, ..quiet.clone() }, Some("target laps reached")),
        // Plateaus and collapses stop a run that asks for it.
        (Standing { verdict: plateau.clone(), ..quiet.clone() }, Some("plateau: evaluation progress has not improved")),
        (Standing { verdict: collapse.clone(), ..quiet.clone() }, Some("collapse: evaluation progress fell to 30.0 %")),
    ];
    for (standing, want) in table {
        let got = rules.check(&hyper, &standing);
        match want {
            None => assert_eq!(got, None, "{standing:?}"),
            Some(w) => assert!(got.as_deref().is_some_and(|g| g.contains(w)), "{standing:?}: {got:?}, want {w:?}"),
        }
    }
    // With a verification (the default), the streak alone never stops the run: the verified
    // checkpoint does.
    let verifying =
        StopRules { target_laps: Some(TargetLaps { laps: 3, evaluations: 1, verify_trials: 10 }), ..rules.clone() };
    assert_eq!(verifying.check(&hyper, &Standing { lap_streak: 5, ..quiet.clone() }), None);
    let held = Standing { lap_streak: 1, verified: Some("ckpt_000004 (v4) lapped 10 of 10".into()), ..quiet.clone() };
    let r = verifying.check(&hyper, &held);
    assert!(r.as_deref().is_some_and(|r| r.contains("target laps reached and verified: ckpt_000004")), "{r:?}");
    // DeepRacer's own conditions, from hyperparameters.json.
    let loose = StopRules { max_episodes: None, target_reward: None, ..rules.clone() };
    let r = loose.check(&hyper, &Standing { episodes: 800, ..quiet.clone() });
    assert!(r.as_deref().is_some_and(|r| r.contains("term_cond_max_episodes")), "{r:?}");
    let r = loose.check(&hyper, &Standing { window: Some((50.0, 250.0)), ..quiet.clone() });
    assert!(r.as_deref().is_some_and(|r| r.contains("term_cond_avg_score")), "{r:?}");
    // A run that did not ask to stop at plateaus or collapses is told about them, not stopped.
    let told = StopRules { plateau_evals: None, stop_on_collapse: false, ..rules.clone() };
    assert_eq!(told.check(&hyper, &Standing { verdict: plateau, ..quiet.clone() }), None);
    assert_eq!(told.check(&hyper, &Standing { verdict: collapse, ..quiet.clone() }), None);
}

/// Issue 33: a verification needs the target's share of its trials.
#[test]
fn a_verification_needs_the_targets_share_of_its_trials() {
    // (laps of the evaluation's trials, trials per evaluation, verification trials, laps needed)
    let table =
        [(3, 3, 10, 10), (2, 3, 10, 7), (1, 3, 10, 4), (3, 3, 3, 3), (5, 3, 10, 10), (1, 1, 10, 10), (3, 3, 1, 1)];
    for (laps, eval_trials, trials, want) in table {
        let t = TargetLaps { laps, evaluations: 1, verify_trials: trials };
        assert_eq!(t.needed(eval_trials, trials), want, "{laps} of {eval_trials}, verified with {trials}");
    }
}
