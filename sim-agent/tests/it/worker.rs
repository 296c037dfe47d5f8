//! The sim worker simulates only what the learner granted, runs evaluations when
//! asked, and follows a restarted learner back to an older version.

use policy::exchange::{ChainedVerify, Credit, EvalRequest, PolicyVersion};
use policy::{ActorCritic, ModelMetadata};
use rand::SeedableRng;
use sim_agent::worker::{Worker, WorkerInbound, WorkerOutbound, WorkerSetup};
use sim_agent::{BuiltinReward, EnvSpec, RewardFn, SimConfig};
use std::sync::Arc;

fn worker(envs: usize, worlds: &[&str]) -> Worker {
    let meta = ModelMetadata::default_state_vector();
    Worker::new(WorkerSetup {
        id: "w1".into(),
        worlds: worlds
            .iter()
            .map(|w| EnvSpec::from_world(&tracks::world(w).unwrap(), tracks::Direction::Forward))
            .collect(),
        offset: 0,
        weights: Vec::new(),
        envs,
        threads: 1,
        cfg: Arc::new(SimConfig::default()),
        reward: RewardFn::Builtin(BuiltinReward::CenterLine),
        space: meta.action_space.clone(),
        seed: 3,
        first_seq: 0,
        gpu: None,
    })
    .unwrap()
}

fn policy(version: u64) -> WorkerInbound {
    let meta = ModelMetadata::default_state_vector();
    let obs = sim_agent::obs::obs_dim(&SimConfig::default().observation);
    let model = ActorCritic::new(&meta, obs, &mut rand_chacha::ChaCha8Rng::seed_from_u64(version));
    WorkerInbound::Policy(PolicyVersion { version, model: Arc::new(model), metadata: Arc::new(meta) })
}

/// Request `id`: `trials` evaluation trials of `version` on `world`, with noise `seed`.
fn eval(id: u64, version: u64, world: &str, trials: u32, seed: u64) -> WorkerInbound {
    WorkerInbound::Eval(EvalRequest {
        id,
        worker: "w1".into(),
        version,
        world: world.into(),
        trials,
        seed,
        then_verify: None,
    })
}

fn credit(version: u64, round: u64, episodes: u64) -> WorkerInbound {
    closing(version, round, episodes, 0)
}

/// A grant that also says the learner closed the checks of every version up to `through`.
fn closing(version: u64, round: u64, episodes: u64, through: u64) -> WorkerInbound {
    WorkerInbound::Credit(Credit {
        version,
        round,
        episodes: [("w1".to_string(), episodes)].into(),
        checks_closed_through: through,
    })
}

/// Issue 8: a worker simulates only what it was granted.
#[test]
fn a_worker_simulates_only_what_it_was_granted() {
    let mut w = worker(4, &["reinvent_base"]);
    // Nothing granted: nothing simulated.
    w.take(policy(0));
    assert!(w.work().unwrap().is_none());
    assert_eq!(w.env_steps(), 0);
    w.take(credit(0, 1, 6));
    let Some(WorkerOutbound::Experience(e)) = w.work().unwrap() else { panic!("experience expected") };
    assert!(e.trajectories.len() >= 6, "{} episodes for a grant of 6", e.trajectories.len());
    assert!(e.trajectories.len() < 6 + 4, "no more than the grant plus the environments' last step");
    assert_eq!((e.credit, e.seq), ((0, 1), 1));
    assert!(e.trajectories.iter().all(|t| t.done && t.world == "reinvent_base" && t.policy_version == 0));
    let steps = w.env_steps();
    // The grant is spent: repeats of it change nothing, and nothing is simulated.
    w.take(credit(0, 1, 6));
    assert!(w.work().unwrap().is_none());
    assert_eq!(w.env_steps(), steps);
    // Another grant for a version not yet held waits for the policy.
    w.take(credit(1, 1, 2));
    assert!(w.work().unwrap().is_none());
    w.take(policy(1));
    let Some(WorkerOutbound::Experience(e)) = w.work().unwrap() else { panic!("experience expected") };
    assert_eq!(e.credit, (1, 1));
    // Episodes that were running when the grant ran out finish under the next one.
    assert!(e.trajectories.iter().all(|t| t.policy_version <= 1));
    // Someone else's grant is not ours.
    w.take(WorkerInbound::Credit(Credit {
        version: 1,
        round: 2,
        episodes: [("w2".to_string(), 5)].into(),
        checks_closed_through: 0,
    }));
    assert!(w.work().unwrap().is_none());
}

/// Issue 8: a worker evaluates when asked and follows a restarted learner.
#[test]
fn a_worker_evaluates_when_asked_and_follows_a_restarted_learner() {
    let mut w = worker(4, &["reinvent_carpet", "reinvent_wood"]);
    w.take(policy(0));
    w.take(policy(1));
    w.take(credit(1, 1, 4));
    // Environments spread over both worlds.
    let Some(WorkerOutbound::Experience(e)) = w.work().unwrap() else { panic!("experience expected") };
    let worlds: std::collections::BTreeSet<&str> = e.trajectories.iter().map(|t| t.world.as_str()).collect();
    assert!(worlds.len() == 2 || e.trajectories.len() < 2, "{worlds:?}");
    // An evaluation request of a version held: trials come back.
    w.take(eval(9, 0, "reinvent_wood", 2, 1));
    let Some(WorkerOutbound::Eval(r)) = w.work().unwrap() else { panic!("report expected") };
    assert_eq!((r.id, r.version, r.world.as_str()), (9, 0, "reinvent_wood"));
    assert_eq!(r.trials.as_ref().unwrap().len(), 2);
    // A repeated request (the report was lost on the way) is answered again without driving.
    let steps = w.env_steps();
    w.take(eval(9, 0, "reinvent_wood", 2, 1));
    let Some(WorkerOutbound::Eval(again)) = w.work().unwrap() else { panic!("report expected") };
    assert_eq!(again, r);
    assert_eq!(w.env_steps(), steps);
    // A restarted learner resumes at an older version with a new grant: the worker follows it.
    w.take(policy(0));
    assert_eq!(w.version(), Some(0));
    w.take(credit(0, 1, 3));
    let Some(WorkerOutbound::Experience(e)) = w.work().unwrap() else { panic!("experience expected") };
    assert_eq!(e.credit, (0, 1));
}

/// Issue 32: an off-policy learner (SAC) grants the next round while it updates, so a worker always
/// holds a grant: an evaluation request waits through one round of episodes at most, then
/// runs before the next round (it once waited for minutes, and runs ended without one).
#[test]
fn an_evaluation_waits_through_one_round_of_episodes_at_most() {
    let mut w = worker(2, &["reinvent_base"]);
    w.take(policy(1));
    w.take(credit(1, 1, 2));
    w.take(eval(3, 1, "reinvent_base", 1, 1));
    // The round in hand first: the learner is waiting for it.
    let Some(WorkerOutbound::Experience(e)) = w.work().unwrap() else { panic!("experience expected") };
    assert_eq!(e.credit, (1, 1));
    // The next round was granted meanwhile: the evaluation, which waited through a round, goes first.
    w.take(credit(1, 2, 2));
    let Some(WorkerOutbound::Eval(r)) = w.work().unwrap() else { panic!("the evaluation expected first") };
    assert_eq!((r.id, r.version), (3, 1));
    let Some(WorkerOutbound::Experience(e)) = w.work().unwrap() else { panic!("experience expected") };
    assert_eq!(e.credit, (1, 2));
}

/// Issue 55: a verification chained to an evaluation runs as soon as the evaluation lapped
/// enough, before the round of episodes granted meanwhile, and gives the trials the same
/// request asked alone gives; one whose evaluation did not lap enough never runs.
#[test]
fn a_chained_verification_runs_at_once_when_its_evaluation_lapped_enough() {
    let chained = |laps: u32| {
        let WorkerInbound::Eval(r) = eval(5, 1, "reinvent_base", 2, 3) else { unreachable!() };
        WorkerInbound::Eval(EvalRequest { then_verify: Some(ChainedVerify { id: 6, trials: 3, seed: 77, laps }), ..r })
    };
    // No laps needed: the verification follows the evaluation, before the grant.
    let mut w = worker(2, &["reinvent_base"]);
    w.take(policy(1));
    w.take(chained(0));
    let Some(WorkerOutbound::Eval(r)) = w.work().unwrap() else { panic!("the evaluation expected") };
    assert_eq!((r.id, r.trials.as_ref().map(Vec::len)), (5, Ok(2)));
    w.take(credit(1, 1, 2));
    let steps = w.env_steps();
    let Some(WorkerOutbound::Eval(v)) = w.work().unwrap() else { panic!("the chained verification expected") };
    assert_eq!((v.id, v.version, v.world.as_str()), (6, 1, "reinvent_base"));
    assert_eq!(w.env_steps(), steps, "no episode before the verification");
    // The same trials as the verification asked for alone (its noise, its count).
    let mut alone = worker(2, &["reinvent_base"]);
    alone.take(policy(1));
    alone.take(eval(6, 1, "reinvent_base", 3, 77));
    let Some(WorkerOutbound::Eval(a)) = alone.work().unwrap() else { panic!("report expected") };
    // (The sim-trace's wall clock aside.)
    let driven = |r: &policy::exchange::EvalReport| -> Vec<(f64, u64, String, Vec<f32>)> {
        r.trials.as_ref().unwrap().iter().map(|t| (t.progress, t.steps, t.status.clone(), t.rewards.clone())).collect()
    };
    assert_eq!((v.id, driven(&v).len()), (a.id, 3));
    assert_eq!(driven(&v), driven(&a));
    // The learner asking for it again is answered from what was run.
    w.take(eval(6, 1, "reinvent_base", 3, 77));
    let Some(WorkerOutbound::Eval(again)) = w.work().unwrap() else { panic!("report expected") };
    assert_eq!(again, v);
    let Some(WorkerOutbound::Experience(_)) = w.work().unwrap() else { panic!("experience expected") };

    // Every trial must lap, and an untrained policy laps none: no verification.
    let mut w = worker(2, &["reinvent_base"]);
    w.take(policy(1));
    w.take(chained(2));
    let Some(WorkerOutbound::Eval(r)) = w.work().unwrap() else { panic!("the evaluation expected") };
    w.take(credit(1, 1, 2));
    assert_eq!(r.trials.as_ref().map(|t| t.iter().filter(|t| t.lap_time.is_some()).count()), Ok(0));
    let Some(WorkerOutbound::Experience(_)) = w.work().unwrap() else { panic!("experience, no verification") };

    // Two worlds of one checkpoint on this worker: both evaluations first, then the
    // verifications; and when the second world misses its target, the first world's chained
    // verification is dropped (the learner verifies only a checkpoint that met it everywhere).
    let on = |id: u64, world: &str, laps: u32| {
        let WorkerInbound::Eval(r) = eval(id, 1, world, 2, 3) else { unreachable!() };
        WorkerInbound::Eval(EvalRequest {
            then_verify: Some(ChainedVerify { id: id + 100, trials: 2, seed: 77, laps }),
            ..r
        })
    };
    for (second, want) in [(0, vec![1, 2, 101, 102]), (2, vec![1, 2])] {
        let mut w = worker(2, &["reinvent_base"]);
        w.take(policy(1));
        w.take(on(1, "reinvent_base", 0));
        w.take(on(2, "reinvent_wood", second));
        let Some(WorkerOutbound::Eval(first)) = w.work().unwrap() else { panic!("the first evaluation expected") };
        w.take(credit(1, 1, 2));
        let mut ran = vec![first.id];
        loop {
            match w.work().unwrap() {
                Some(WorkerOutbound::Eval(r)) => ran.push(r.id),
                Some(WorkerOutbound::Experience(_)) => break,
                other => panic!("{other:?}"),
            }
        }
        assert_eq!(ran, want, "the second world needing {second} laps");
    }
}

/// Issue 55: a grant saying the learner closed a version's checks (another worker's world
/// missed, so the checkpoint cannot be verified) drops that version's verification queued
/// here, and stops one running at the step the grant is read, with nothing reported; a grant
/// that closes older versions only leaves it running. What came meanwhile is taken after.
#[test]
fn a_worker_drops_the_checks_of_versions_its_learner_closed() {
    let chained = || {
        let WorkerInbound::Eval(r) = eval(5, 1, "reinvent_base", 2, 3) else { unreachable!() };
        WorkerInbound::Eval(EvalRequest {
            then_verify: Some(ChainedVerify { id: 6, trials: 3, seed: 77, laps: 0 }),
            ..r
        })
    };
    let evaluated = || {
        let mut w = worker(2, &["reinvent_base"]);
        w.take(policy(1));
        w.take(chained());
        let Some(WorkerOutbound::Eval(r)) = w.work().unwrap() else { panic!("the evaluation expected") };
        assert_eq!(r.id, 5);
        w
    };
    // Queued: dropped when the grant comes.
    let mut w = evaluated();
    w.take(closing(1, 1, 2, 1));
    let Some(WorkerOutbound::Experience(_)) = w.work().unwrap() else { panic!("episodes, the verification dropped") };

    // Running: stopped at the fifth step, or not at all when the grant closes older versions.
    for (through, stops) in [(1, true), (0, false)] {
        let mut w = evaluated();
        let steps = w.env_steps();
        let mut polls = 0;
        let out = w
            .work_with(&mut || {
                polls += 1;
                (polls == 5).then(|| closing(1, 1, 2, through))
            })
            .unwrap();
        assert_eq!(w.env_steps(), steps, "no episode during the check");
        match out {
            None => {
                assert!(stops, "closing v{through}");
                assert_eq!(polls, 5, "the batch stops at the step the grant is read");
            }
            Some(WorkerOutbound::Eval(v)) => {
                assert!(!stops, "closing v{through}");
                assert_eq!((v.id, v.trials.as_ref().map(Vec::len)), (6, Ok(3)));
                assert!(polls > 5);
            }
            other => panic!("{other:?}"),
        }
        let m = w.take_deferred().expect("the grant, kept for later");
        assert!(w.take_deferred().is_none());
        w.take(m);
        let Some(WorkerOutbound::Experience(e)) = w.work().unwrap() else { panic!("the granted episodes expected") };
        assert_eq!(e.credit, (1, 1));
    }
}

/// Issue 55: a request for a newer version closes the older checks, queued or running: the
/// learner checks one checkpoint at a time, and a stopping learner sends no grant to say so.
#[test]
fn a_request_for_a_newer_version_closes_the_older_checks() {
    let evaluated = || {
        let mut w = worker(2, &["reinvent_base"]);
        w.take(policy(1));
        let WorkerInbound::Eval(r) = eval(5, 1, "reinvent_base", 2, 3) else { unreachable!() };
        w.take(WorkerInbound::Eval(EvalRequest {
            then_verify: Some(ChainedVerify { id: 6, trials: 3, seed: 77, laps: 0 }),
            ..r
        }));
        let Some(WorkerOutbound::Eval(r)) = w.work().unwrap() else { panic!("the evaluation expected") };
        assert_eq!(r.id, 5);
        w.take(policy(2));
        w
    };
    let next_report = |w: &mut Worker| match w.work().unwrap() {
        Some(WorkerOutbound::Eval(r)) => r.id,
        other => panic!("a report expected, got {other:?}"),
    };
    // Queued: v1's verification is dropped, v2's evaluation runs.
    let mut w = evaluated();
    w.take(eval(9, 2, "reinvent_base", 2, 4));
    assert_eq!(next_report(&mut w), 9);
    // A request for the same version closes nothing: the verification runs first.
    let mut w = evaluated();
    w.take(eval(9, 1, "reinvent_wood", 2, 4));
    assert_eq!(next_report(&mut w), 6);
    // Running: the batch stops at the step the request is read; the request is kept.
    let mut w = evaluated();
    let mut polls = 0;
    let out = w
        .work_with(&mut || {
            polls += 1;
            (polls == 5).then(|| eval(9, 2, "reinvent_base", 2, 4))
        })
        .unwrap();
    assert!(out.is_none(), "stopped, got {out:?}");
    assert_eq!(polls, 5);
    let m = w.take_deferred().expect("the request, kept for later");
    w.take(m);
    assert_eq!(next_report(&mut w), 9);
}

/// Issue 55: a run that trains with the camera randomised checks its models as `coordinator
/// evaluate`, the console and DeepRacer's evaluation see them: the camera's nominal light,
/// texture and pose, without image noise. The worker's trials are the nominal camera's, frame
/// for frame, not the randomised one's.
#[test]
fn a_workers_checks_see_the_nominal_camera_when_training_randomises_it() {
    use sim_agent::rollout::{EvalPlan, evaluate};
    let meta = ModelMetadata::default_camera();
    let mut cfg = SimConfig::default();
    cfg.observation.kind = sim_agent::config::ObservationKind::Camera;
    cfg.camera.randomize = true;
    let obs = sim_agent::obs::obs_dim(&cfg.observation);
    let model = Arc::new(ActorCritic::new(&meta, obs, &mut rand_chacha::ChaCha8Rng::seed_from_u64(3)));
    let spec = EnvSpec::from_world(&tracks::world("reinvent_base").unwrap(), tracks::Direction::Forward);
    let mut w = Worker::new(WorkerSetup {
        id: "w1".into(),
        worlds: vec![spec.clone()],
        offset: 0,
        weights: Vec::new(),
        envs: 1,
        threads: 1,
        cfg: Arc::new(cfg.clone()),
        reward: RewardFn::Builtin(BuiltinReward::CenterLine),
        space: meta.action_space.clone(),
        seed: 3,
        first_seq: 0,
        gpu: None,
    })
    .expect("lavapipe or a GPU");
    w.take(WorkerInbound::Policy(PolicyVersion { version: 1, model: model.clone(), metadata: Arc::new(meta.clone()) }));
    w.take(eval(5, 1, "reinvent_base", 2, 3));
    let Some(WorkerOutbound::Eval(r)) = w.work().unwrap() else { panic!("the evaluation expected") };
    let got: Vec<(u64, u64, Vec<Vec<u8>>)> = r
        .trials
        .unwrap()
        .iter()
        .map(|t| (t.steps, t.progress.to_bits(), t.frames.iter().map(|f| f.gray.clone()).collect()))
        .collect();
    let alone = |randomize: bool| {
        let cfg = Arc::new(SimConfig {
            camera: sim_agent::config::CameraConfig { randomize, ..cfg.camera.clone() },
            ..cfg.clone()
        });
        let plan = EvalPlan {
            rules: sim_agent::EvalRules::default(),
            count: 2,
            seed: 3,
            threads: 1,
            all_frames: false,
            spread: false,
            give_up_after_misses: None,
        };
        let t = evaluate(&model, &meta.action_space, &spec, &cfg, &plan, None).unwrap();
        t.iter()
            .map(|t| (t.steps, t.progress.to_bits(), t.log.frames.iter().map(|f| f.gray.clone()).collect()))
            .collect::<Vec<(u64, u64, Vec<Vec<u8>>)>>()
    };
    let nominal = alone(false);
    assert!(!nominal[0].2.is_empty(), "the first trial keeps what the car saw");
    assert!(got == nominal, "the worker's checks are the nominal camera's");
    assert!(nominal != alone(true), "a randomised camera sees other frames");
}

/// Issue 33: a checkpoint that met the lap target is verified by the worker that evaluated it,
/// however many versions training has published since (a worker keeps only the newest few).
#[test]
fn a_worker_keeps_the_version_it_evaluated_for_its_verification() {
    let mut w = worker(1, &["reinvent_base"]);
    w.take(policy(1));
    w.take(eval(1, 1, "reinvent_base", 1, 1));
    let Some(WorkerOutbound::Eval(r)) = w.work().unwrap() else { panic!("report expected") };
    assert!(r.trials.is_ok(), "{r:?}");
    for v in 2..=8 {
        w.take(policy(v));
    }
    // v1 is long out of the newest versions, and still verified.
    w.take(eval(2, 1, "reinvent_base", 4, 99));
    let Some(WorkerOutbound::Eval(r)) = w.work().unwrap() else { panic!("report expected") };
    assert_eq!((r.id, r.version), (2, 1));
    assert_eq!(r.trials.as_ref().map(Vec::len), Ok(4), "{r:?}");
    // A version it never evaluated and no longer holds is refused, saying so.
    w.take(eval(3, 2, "reinvent_base", 1, 1));
    let Some(WorkerOutbound::Eval(r)) = w.work().unwrap() else { panic!("report expected") };
    assert!(r.trials.as_ref().is_err_and(|e| e.contains("no longer held")), "{r:?}");
}

/// Issue 34: the schedule's weights move environments at their episodes' ends and none is lost.
#[test]
fn the_schedules_weights_move_environments_at_their_episodes_ends_and_none_is_lost() {
    use sim_agent::worker::{replan, shares};
    // Pure parts: the split, and the fewest moves.
    for (envs, weights, want) in [
        (8, vec![0.5, 0.25, 0.25], vec![4, 2, 2]),
        (8, vec![0.6, 0.2, 0.2], vec![5, 2, 1]),
        (3, vec![0.98, 0.01, 0.01], vec![1, 1, 1]),
        (4, vec![f64::NAN, 0.0, -1.0], vec![2, 1, 1]),
        (2, vec![0.1, 0.1, 0.8], vec![0, 0, 2]),
    ] {
        assert_eq!(shares(envs, &weights), want, "{envs} by {weights:?}");
    }
    assert_eq!(replan(&[0, 1, 2, 0, 1, 2], &[4, 1, 1]), vec![0, 1, 2, 0, 0, 0]);
    assert_eq!(replan(&[0, 0, 0, 0], &[1, 3]), vec![0, 1, 1, 1]);
    // A worker on three worlds, evenly, then weighted 6:1:1 over 8 environments.
    let mut w = worker(8, &["reinvent_base", "reinvent_wood", "Oval_track"]);
    w.take(policy(0));
    w.take(credit(0, 1, 8));
    let Some(WorkerOutbound::Experience(first)) = w.work().unwrap() else { panic!("experience expected") };
    w.take(WorkerInbound::Weights(vec![0.75, 0.125, 0.125]));
    let mut seen = Vec::new();
    for round in 2..8 {
        w.take(credit(0, round, 16));
        let Some(WorkerOutbound::Experience(e)) = w.work().unwrap() else { panic!("experience expected") };
        seen.extend(e.trajectories);
    }
    // Every environment's episodes come in order without a gap (none thrown away on the move),
    // and the last ones follow the weights.
    let mut by_env: std::collections::BTreeMap<u32, Vec<(u64, String)>> = Default::default();
    for t in first.trajectories.iter().chain(&seen) {
        by_env.entry(t.env).or_default().push((t.episode, t.world.clone()));
    }
    for (env, eps) in &by_env {
        let numbers: Vec<u64> = eps.iter().map(|e| e.0).collect();
        assert!(numbers.windows(2).all(|p| p[1] == p[0] + 1), "env {env}: {numbers:?}");
    }
    let last: Vec<&str> = by_env.values().map(|eps| eps.last().unwrap().1.as_str()).collect();
    let on = |world: &str| last.iter().filter(|w| **w == world).count();
    assert_eq!((on("reinvent_base"), on("reinvent_wood"), on("Oval_track")), (6, 1, 1), "{last:?}");
}

/// Issue 55: a verification's trials stop once more have missed than it can take and still
/// hold. What comes back is exactly the trials that had ended by then, the same bits as in the
/// whole run; the share a chained verification needs is the evaluation's (3 of 3 → 10 of 10,
/// 2 of 3 → 7 of 10).
#[test]
fn a_verification_stops_once_it_can_no_longer_hold() {
    use policy::exchange::laps_needed;
    use sim_agent::rollout::{EvalPlan, evaluate};
    for (laps, of, trials, needed) in [(3, 3, 10, 10), (2, 3, 10, 7), (1, 3, 10, 4), (0, 3, 10, 0), (5, 3, 10, 10)] {
        assert_eq!(laps_needed(laps, of, trials), needed, "{laps} of {of} → of {trials}");
    }
    let meta = ModelMetadata::default_state_vector();
    let cfg = Arc::new(SimConfig::default());
    let obs = sim_agent::obs::obs_dim(&cfg.observation);
    // An untrained policy whose trials leave the track between steps 39 and 48.
    let model = Arc::new(ActorCritic::new(&meta, obs, &mut rand_chacha::ChaCha8Rng::seed_from_u64(9)));
    let spec = EnvSpec::from_world(&tracks::world("reinvent_base").unwrap(), tracks::Direction::Forward);
    let run = |give_up_after_misses| {
        let plan = EvalPlan {
            rules: sim_agent::EvalRules::default(),
            count: 8,
            seed: 11,
            threads: 1,
            all_frames: false,
            spread: false,
            give_up_after_misses,
        };
        let t = evaluate(&model, &meta.action_space, &spec, &cfg, &plan, None).unwrap();
        t.into_iter().map(|t| (t.steps, t.progress.to_bits(), t.lap_time, t.off_track)).collect::<Vec<_>>()
    };
    let whole = run(None);
    assert_eq!(whole.len(), 8);
    assert!(whole.iter().all(|t| t.2.is_none()), "an untrained policy laps nothing: {whole:?}");
    let mut ends: Vec<u64> = whole.iter().map(|t| t.0).collect();
    ends.sort();
    for k in [0, 3, 7] {
        // The trials end on the step the (k+1)th miss came; those that ended by then come back.
        let stop = ends[k];
        let want: Vec<_> = whole.iter().filter(|t| t.0 <= stop).cloned().collect();
        assert_eq!(run(Some(k)), want, "giving up after {k} misses");
    }
    assert!(run(Some(0)).len() < 8, "the trials end apart, so giving up at once leaves some out: {ends:?}");
}
