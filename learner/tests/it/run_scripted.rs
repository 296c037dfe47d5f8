//! The training run ([`learner::run::run`]) against a scripted worker: a [`Link`] that answers
//! every grant at once with made-up episodes (acted by the published policy, so PPO's ratios
//! are real) and every evaluation request with trials of a chosen progress. No simulator and
//! no network: each run takes well under a second, so the stop rules and the learning-rate
//! schedule are checked as tables here, through the whole run (standing, stop, final
//! evaluation, model folder, metrics), and the CLI and cluster tests keep one case each.

use faer::Par;
use learner::Hyperparameters;
use learner::hyperparams::LrSchedule;
use learner::run::{Inbound, Link, LinkError, Quiet, RunSpec, RunStatus, Start, StopRules, Summary, TargetLaps};
use policy::exchange::{Credit, EvalReport, EvalRequest, Experience, PolicyVersion, Trial};
use policy::folder::Manifest;
use policy::signature::Signer;
use policy::{ModelMetadata, Trajectory};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::collections::{BTreeMap, VecDeque};
use std::path::Path;
use std::time::Duration;

const WORLD: &str = "reinvent_base";
const WORKER: &str = "scripted";
const OBS: usize = 6;

/// What the scripted worker's episodes and evaluations look like.
#[derive(Clone, Copy, Debug)]
struct Script {
    /// Steps per episode (each with reward 1).
    steps: usize,
    /// Progress (%) every episode ends at.
    progress: f64,
    /// Progress of evaluation `n` (from 0): trials of 100 % lap.
    eval: fn(u64) -> f64,
    /// Trials of evaluation `n` that lap when its progress is under 100 %.
    eval_laps: fn(u64) -> u32,
    /// Trials of verification `n` (from 0) that lap (the rest end at 60 %).
    verify: fn(u64) -> u32,
}

/// A worker that does at once whatever it is granted or asked.
struct Scripted {
    script: Script,
    rng: ChaCha8Rng,
    policy: Option<PolicyVersion>,
    /// Episodes already delivered per (version, round): a grant is announced again and again.
    delivered: BTreeMap<(&'static str, u64, u64), u64>,
    inbox: VecDeque<Inbound>,
    seq: u64,
    evals: u64,
    verifications: u64,
    /// Every evaluation run, in order: those asked for and those chained to them.
    asked: Vec<EvalRequest>,
    /// Every evaluation request the learner sent, in order.
    sent: Vec<EvalRequest>,
    /// Calls to `next` an evaluation's report waits for (0: at once), as trials take time.
    hold: usize,
    /// A world whose evaluations and verifications take this many calls instead.
    slow_world: Option<(&'static str, usize)>,
    /// Every grant announced, in order.
    credits: Vec<Credit>,
    /// Evaluations whose trials are still running, with the calls they have left.
    held: Vec<(usize, EvalRequest)>,
    /// Versions published and grants made while an evaluation's trials were running.
    published_while_checking: u64,
    granted_while_checking: u64,
    /// Two workers instead of one, each episode drawn from its worker, version and number
    /// alone; `true` delivers the second worker's share of each grant first.
    pair: Option<bool>,
}

/// The workers of a scripted worker with [`Scripted::pair`].
const PAIR: [&str; 2] = ["agent-1", "agent-2"];

impl Scripted {
    fn new(script: Script) -> Scripted {
        Scripted {
            script,
            rng: ChaCha8Rng::seed_from_u64(5),
            policy: None,
            delivered: BTreeMap::new(),
            inbox: VecDeque::new(),
            seq: 0,
            evals: 0,
            verifications: 0,
            asked: Vec::new(),
            sent: Vec::new(),
            hold: 0,
            slow_world: None,
            credits: Vec::new(),
            held: Vec::new(),
            published_while_checking: 0,
            granted_while_checking: 0,
            pair: None,
        }
    }

    fn episode(&mut self, version: u64, n: u64) -> Trajectory {
        let mut rng = self.rng.clone();
        let t = self.episode_from(version, n, &mut rng);
        self.rng = rng;
        t
    }

    fn episode_from(&self, version: u64, n: u64, rng: &mut ChaCha8Rng) -> Trajectory {
        let p = self.policy.as_ref().expect("a policy is published before any grant");
        let steps = self.script.steps;
        let obs: Vec<f32> = (0..steps * OBS).map(|_| rng.random_range(-1.0..1.0)).collect();
        let acts = p.model.act(&obs, steps, false, rng, Par::Seq);
        Trajectory {
            world: WORLD.into(),
            env: 0,
            episode: n,
            policy_version: version,
            obs,
            choices: acts.iter().map(|a| a.choice).collect(),
            logp: acts.iter().map(|a| a.logp).collect(),
            values: acts.iter().map(|a| a.value).collect(),
            rewards: vec![1.0; steps],
            done: true,
            progress: self.script.progress,
            lap_complete: self.script.progress >= 100.0,
            track_len: 17.7,
            trace: vec![],
        }
    }
}

impl Link for Scripted {
    fn publish(&mut self, policy: &PolicyVersion, _: &Manifest, _: &Signer) -> Result<(), LinkError> {
        self.published_while_checking += u64::from(!self.held.is_empty());
        self.policy = Some(policy.clone());
        Ok(())
    }

    fn grant(&mut self, credit: &Credit) -> Result<(), LinkError> {
        self.granted_while_checking += u64::from(!self.held.is_empty());
        self.credits.push(credit.clone());
        let order: Vec<&'static str> = match self.pair {
            Some(true) => PAIR.iter().rev().copied().collect(),
            Some(false) => PAIR.to_vec(),
            None => vec![WORKER],
        };
        for worker in order {
            let want = credit.episodes.get(worker).copied().unwrap_or(0);
            let done = self.delivered.entry((worker, credit.version, credit.round)).or_default();
            let more = want.saturating_sub(*done);
            *done = want;
            if more == 0 {
                continue;
            }
            let trajectories: Vec<Trajectory> = match self.pair {
                // Each worker's episodes from its own stream, whatever order they go in.
                Some(_) => {
                    let mut rng = ChaCha8Rng::seed_from_u64(credit.version * 1000 + u64::from(worker == PAIR[1]));
                    (0..more).map(|i| self.episode_from(credit.version, i, &mut rng)).collect()
                }
                None => (0..more).map(|i| self.episode(credit.version, i)).collect(),
            };
            self.seq += 1;
            let env_steps = trajectories.iter().map(|t| t.rewards.len() as u64).sum();
            self.inbox.push_back(Inbound::Experience(Experience {
                worker: worker.into(),
                seq: self.seq,
                credit: (credit.version, credit.round),
                trajectories,
                env_steps,
                seconds: 0.01,
                frame: None,
            }));
        }
        Ok(())
    }

    fn request_eval(&mut self, req: &EvalRequest) -> Result<(), LinkError> {
        self.sent.push(req.clone());
        self.run(req);
        Ok(())
    }

    fn next(&mut self, timeout: Duration) -> Result<Option<Inbound>, LinkError> {
        for (left, _) in &mut self.held {
            *left -= 1;
        }
        let (done, running): (Vec<_>, Vec<_>) = std::mem::take(&mut self.held).into_iter().partition(|(l, _)| *l == 0);
        self.held = running;
        for (_, req) in done {
            self.answer(&req);
        }
        match self.inbox.pop_front() {
            Some(m) => Ok(Some(m)),
            None => {
                std::thread::sleep(timeout.min(Duration::from_millis(5)));
                Ok(None)
            }
        }
    }

    fn status(&mut self, _: &RunStatus) -> Result<(), LinkError> {
        Ok(())
    }

    fn workers(&mut self) -> Vec<String> {
        match self.pair {
            Some(_) => PAIR.map(String::from).to_vec(),
            None => vec![WORKER.into()],
        }
    }
}

impl Scripted {
    /// Run `req`: report at once, or after the calls its trials take.
    fn run(&mut self, req: &EvalRequest) {
        let hold = match self.slow_world {
            Some((world, calls)) if req.world == world => calls,
            _ => self.hold,
        };
        if hold == 0 {
            self.answer(req);
        } else if !self.held.iter().any(|(_, r)| r.id == req.id) {
            self.held.push((hold, req.clone()));
        }
    }

    /// Run `req` and report; then, as a sim worker does, the verification chained to it when
    /// its trials lapped enough.
    fn answer(&mut self, req: &EvalRequest) {
        self.asked.push(req.clone());
        // A checkpoint's evaluation has the spec's 3 trials; its verification more.
        let lapping = if req.trials == 3 {
            self.evals += 1;
            let n = self.evals - 1;
            if (self.script.eval)(n) >= 100.0 { 3 } else { (self.script.eval_laps)(n) }
        } else {
            self.verifications += 1;
            (self.script.verify)(self.verifications - 1)
        };
        let progress_of = |i: u32| match req.trials {
            3 if i >= lapping => (self.script.eval)(self.evals - 1),
            _ if i < lapping => 100.0,
            _ => 60.0,
        };
        let trial = |i| {
            let progress = progress_of(i);
            Trial {
                progress,
                lap_time: (progress >= 100.0).then_some(12.0),
                steps: 100,
                status: if progress >= 100.0 { "lap_complete" } else { "off_track" }.into(),
                track_len: 17.7,
                ..Default::default()
            }
        };
        let trials: Vec<Trial> = (0..req.trials).map(trial).collect();
        let chained = req.chained(&trials);
        self.inbox.push_back(Inbound::Eval(EvalReport {
            id: req.id,
            worker: req.worker.clone(),
            version: req.version,
            world: req.world.clone(),
            trials: Ok(trials),
        }));
        if let Some(v) = chained {
            match self.slow_world {
                Some(_) => self.run(&v),
                None => self.answer(&v),
            }
        }
    }
}

fn spec(out: &Path, stop: StopRules, hyper: Hyperparameters) -> RunSpec {
    RunSpec {
        name: "scripted".into(),
        metadata: ModelMetadata::default_state_vector(),
        hyper,
        obs_size: OBS,
        observation: serde_json::json!({}),
        sim_toml: String::new(),
        worlds: vec![WORLD.into()],
        out: out.to_path_buf(),
        start: Start::New { clone_from: None },
        seed: 1,
        max_policy_lag: 4,
        eval_trials: 3,
        eval_seconds: 0.0,
        stop,
        checks_first: false,
        par: Par::Seq,
        gpu: None,
        adopt: None,
        signing_key: None,
        tracks: vec![],
    }
}

/// Small updates: 10 episodes each, one epoch.
fn quick() -> Hyperparameters {
    Hyperparameters { num_episodes_between_training: 10, num_epochs: 1, batch_size: 32, ..Default::default() }
}

/// Stop rules that never fire on their own within a test (a long time limit, nothing else).
fn never() -> StopRules {
    StopRules { minutes: 30.0, ..StopRules::default() }
}

fn run_with(dir: &Path, name: &str, stop: StopRules, hyper: Hyperparameters, script: Script) -> Summary {
    run_asked(dir, name, stop, hyper, script).0
}

/// A run, and the evaluation requests it made.
fn run_asked(
    dir: &Path,
    name: &str,
    stop: StopRules,
    hyper: Hyperparameters,
    script: Script,
) -> (Summary, Vec<EvalRequest>, Vec<EvalRequest>) {
    let out = dir.join(name);
    let mut link = Scripted::new(script);
    let s =
        learner::run::run(&spec(&out, stop, hyper), &mut link, &mut Quiet).unwrap_or_else(|e| panic!("{name}: {e:#}"));
    (s, link.asked, link.sent)
}

fn lines(path: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

const HALFWAY: Script = Script { steps: 20, progress: 30.0, eval: |_| 50.0, eval_laps: |_| 0, verify: |_| 10 };

/// Issue 29: every stop condition ends the run with its reason, an evaluation and a model.
#[test]
fn every_stop_condition_ends_the_run_with_its_reason_an_evaluation_and_a_model() {
    let dir = tempfile::tempdir().unwrap();
    let h = quick();
    // (row, rules, hyperparameters, script, the reason's words)
    let table: Vec<(&str, StopRules, Hyperparameters, Script, &str)> = vec![
        ("episodes", StopRules { max_episodes: Some(60), ..never() }, h.clone(), HALFWAY, "60 episodes reached"),
        (
            "env_steps",
            StopRules { env_steps_budget: Some(1500), ..never() },
            h.clone(),
            HALFWAY,
            "compute budget of 1500 env steps",
        ),
        (
            "progress",
            StopRules { target_progress: Some(25.0), ..never() },
            h.clone(),
            HALFWAY,
            "mean progress 30.0 % over the last 20 episodes reached the target 25",
        ),
        (
            "reward",
            StopRules { target_reward: Some(15.0), ..never() },
            h.clone(),
            HALFWAY,
            "mean reward 20.0 over the last 20 episodes reached the target 15",
        ),
        ("minutes", StopRules { minutes: 0.02, ..StopRules::default() }, h.clone(), HALFWAY, "time limit of 0.02 min"),
        (
            "term_cond_max_episodes",
            never(),
            Hyperparameters { term_cond_max_episodes: 40, ..h.clone() },
            HALFWAY,
            "term_cond_max_episodes (40)",
        ),
        (
            "term_cond_avg_score",
            never(),
            Hyperparameters { term_cond_avg_score: 12.0, ..h.clone() },
            HALFWAY,
            "term_cond_avg_score (12)",
        ),
        (
            "laps",
            StopRules { target_laps: Some(TargetLaps { laps: 3, evaluations: 2, verify_trials: 0 }), ..never() },
            h.clone(),
            Script { eval: |n| if n >= 2 { 100.0 } else { 40.0 }, ..HALFWAY },
            "target laps reached: 3 laps in 2 consecutive evaluations",
        ),
        (
            "verified",
            StopRules { target_laps: Some(TargetLaps { laps: 3, evaluations: 1, verify_trials: 10 }), ..never() },
            h.clone(),
            Script { eval: |n| if n >= 2 { 100.0 } else { 40.0 }, ..HALFWAY },
            "target laps reached and verified",
        ),
        (
            "plateau",
            StopRules { plateau_evals: Some(2), ..never() },
            h.clone(),
            HALFWAY,
            "plateau: evaluation progress has not improved",
        ),
        (
            "collapse",
            StopRules { stop_on_collapse: true, ..never() },
            h.clone(),
            Script { eval: |n| if n < 3 { 100.0 } else { 10.0 }, ..HALFWAY },
            "collapse: evaluation progress fell to 10.0 %",
        ),
    ];
    for (row, stop, hyper, script, want) in table {
        let s = run_with(dir.path(), row, stop, hyper, script);
        assert!(s.stop_reason.contains(want), "{row}: stopped because {:?}, want {want:?}", s.stop_reason);
        let out = dir.path().join(row);
        // Whatever stopped it: the final model was evaluated and saved, the records are whole.
        assert!(out.join("model/model.safetensors").exists(), "{row}: no model");
        let evals = lines(&out.join("evaluations.jsonl"));
        assert!(!evals.is_empty(), "{row}: no evaluation");
        let metrics = lines(&out.join("metrics.jsonl"));
        assert_eq!(metrics.len() as u64, s.iterations, "{row}: one metrics line per update");
        let episodes: u64 = metrics.iter().map(|m| m["episodes"].as_u64().unwrap()).sum();
        assert_eq!(episodes, s.episodes, "{row}: the episodes trained on, counted once");
        assert_eq!(s.env_steps, 20 * s.episodes_received, "{row}: every step delivered counted");
        assert_eq!(s.dropped_stale, 0, "{row}");
    }
}

/// Issue 29: a run with nothing to stop it goes on.
#[test]
fn a_run_with_nothing_to_stop_it_goes_on() {
    // The scripted worker never meets a target: 25 updates and still running when the
    // episodes run out (a budget far above them), so no rule fires early by mistake.
    let dir = tempfile::tempdir().unwrap();
    let stop = StopRules {
        max_episodes: Some(250),
        target_progress: Some(99.0),
        target_reward: Some(1000.0),
        target_laps: Some(TargetLaps { laps: 3, evaluations: 2, verify_trials: 10 }),
        ..never()
    };
    let s = run_with(dir.path(), "long", stop, quick(), HALFWAY);
    assert!(s.stop_reason.contains("250 episodes reached"), "{}", s.stop_reason);
    assert_eq!(s.iterations, 25);
}

/// Issue 29: the learning rate cools down over the second half of the budget unless a target ends
/// the job.
#[test]
fn the_learning_rate_cools_down_over_the_second_half_of_the_budget_unless_a_target_ends_the_job() {
    // A budget of 100 episodes is 10 updates of 10. The first half trains at `lr`; from
    // there the rate falls in a straight line towards zero at the budget's end, so the
    // job's last model is not caught mid-stride. "constant" keeps DeepRacer's fixed rate, and
    // so does a job that stops at a target (here one it never reaches): its budget is a cap.
    let dir = tempfile::tempdir().unwrap();
    let budget = StopRules { max_episodes: Some(100), ..never() };
    let cooldown = [1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.8, 0.6, 0.4, 0.2].map(|f| 3e-4 * f);
    for (row, hyper, stop, want) in [
        ("cooldown", quick(), budget.clone(), cooldown),
        (
            "constant",
            Hyperparameters { lr: 2e-4, lr_schedule: LrSchedule::Constant, ..quick() },
            budget.clone(),
            [2e-4; 10],
        ),
        ("target", quick(), StopRules { target_reward: Some(1e6), ..budget.clone() }, [3e-4; 10]),
    ] {
        run_with(dir.path(), row, stop, hyper, HALFWAY);
        let lrs: Vec<f64> =
            lines(&dir.path().join(row).join("metrics.jsonl")).iter().map(|m| m["lr"].as_f64().unwrap()).collect();
        assert_eq!(lrs.len(), want.len(), "{row}: {lrs:?}");
        for (got, want) in lrs.iter().zip(want) {
            assert!((got - want).abs() < 1e-9, "{row}: {lrs:?}");
        }
    }
}

/// Issue 33: the run stops at the first checkpoint that holds its verification and that is the
/// model.
#[test]
fn the_run_stops_at_the_first_checkpoint_that_holds_its_verification_and_that_is_the_model() {
    // Evaluations lap from the second on. The first lapping checkpoint's verification laps 9
    // of 10 trials: not held, training goes on. The next lapping checkpoint's laps 10 of 10:
    // the run stops there, that checkpoint is the model, and no later version is evaluated.
    let dir = tempfile::tempdir().unwrap();
    let stop = StopRules { target_laps: Some(TargetLaps { laps: 3, evaluations: 1, verify_trials: 10 }), ..never() };
    let script =
        Script { eval: |n| if n >= 1 { 100.0 } else { 40.0 }, verify: |k| if k == 0 { 9 } else { 10 }, ..HALFWAY };
    let (s, asked, sent) = run_asked(dir.path(), "verify", stop, quick(), script);
    assert!(s.stop_reason.contains("target laps reached and verified"), "{}", s.stop_reason);
    // Run, in order: evaluation, evaluation, its verification, evaluation, its verification.
    let trials: Vec<u32> = asked.iter().map(|r| r.trials).collect();
    assert_eq!(trials, [3, 3, 10, 3, 10], "{asked:?}");
    // Issue 55: each verification came chained to its evaluation, run by the worker as soon as
    // that lapped, and the learner took its report (come before the evaluation closed) without
    // asking for it again.
    assert_eq!(sent.iter().map(|r| r.trials).collect::<Vec<_>>(), [3, 3, 3], "{sent:?}");
    assert!(sent.iter().all(|r| r.then_verify.is_some_and(|v| v.trials == 10 && v.laps == 3)), "{sent:?}");
    for (eval, verify) in [(&asked[1], &asked[2]), (&asked[3], &asked[4])] {
        assert_eq!(verify.version, eval.version, "the same checkpoint is verified");
        assert_eq!(verify.worker, eval.worker, "by the worker that evaluated it");
        assert_ne!(verify.seed, eval.seed, "with fresh noise");
    }
    assert!(asked[3].version > asked[1].version);
    let verified = asked[4].version;
    let out = dir.path().join("verify");
    let evals = lines(&out.join("evaluations.jsonl"));
    let flags: Vec<bool> = evals.iter().map(|e| e["verification"].as_bool().unwrap()).collect();
    assert_eq!(flags, [false, false, true, false, true]);
    assert_eq!(evals[2]["min_laps"], 9);
    assert_eq!(evals[4]["min_laps"], 10);
    // The model, the best checkpoint and the summary are the verified checkpoint.
    let manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("model/manifest.json")).unwrap()).unwrap();
    assert_eq!(manifest["policy_version"], verified, "{manifest}");
    assert_eq!(manifest["training"]["verified_trials"], 10, "{manifest}");
    assert_eq!(s.best.as_ref().map(|b| b.policy_version), Some(verified));
    assert!(s.verified.as_deref().is_some_and(|v| v.contains("lapped 10 of 10")), "{:?}", s.verified);
    let index: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("checkpoints/deepracer_checkpoints.json")).unwrap())
            .unwrap();
    assert_eq!(index["best_checkpoint"]["policy_version"], verified, "{index}");
    assert!(s.policy_version >= verified);
}

/// Issue 55: once an evaluation laps a trial on every world, the lap target is in sight and
/// every new version is evaluated, whatever the clock says; before that, the clock decides.
#[test]
fn every_version_is_evaluated_once_the_lap_target_is_in_sight() {
    let dir = tempfile::tempdir().unwrap();
    let target = Some(TargetLaps { laps: 3, evaluations: 1, verify_trials: 10 });
    // The clock falls at the first update only; the run ends at 60 episodes (6 updates).
    let stop = StopRules { target_laps: target, max_episodes: Some(60), ..never() };
    let hourly = |out: &Path| RunSpec { eval_seconds: 3600.0, ..spec(out, stop.clone(), quick()) };
    // (row, laps of the first evaluation, the trials asked in order, their versions)
    type Row = (&'static str, fn(u64) -> u32, &'static [u32], &'static [u64]);
    let table: [Row; 2] = [
        // The first evaluation lapped 1 of 3: the next version is evaluated at once, laps
        // 3 of 3 and is verified; the run stops there.
        ("in sight", |n| u32::from(n == 0), &[3, 3, 10], &[1, 2, 2]),
        // It lapped none: nothing more until the run stops, and then the last version.
        ("not in sight", |_| 0, &[3, 3], &[1, 6]),
    ];
    for (row, eval_laps, trials, versions) in table {
        let out = dir.path().join(row.replace(' ', "-"));
        let script = Script { eval: |n| if n >= 1 { 100.0 } else { 40.0 }, eval_laps, ..HALFWAY };
        let mut link = Scripted::new(script);
        let s = learner::run::run(&hourly(&out), &mut link, &mut Quiet).unwrap_or_else(|e| panic!("{row}: {e:#}"));
        assert_eq!(link.asked.iter().map(|r| r.trials).collect::<Vec<_>>(), trials, "{row}: {:?}", link.asked);
        assert_eq!(link.asked.iter().map(|r| r.version).collect::<Vec<_>>(), versions, "{row}: {:?}", link.asked);
        let verified = s.stop_reason.contains("target laps reached and verified");
        assert_eq!(verified, row == "in sight", "{row}: {}", s.stop_reason);
    }
}

/// Issue 55: a verification lost on one world (it lapped too few) closes at once: training goes
/// on without waiting for the other worlds' trials, and the next grant tells the workers that
/// version's checks are closed, so that the worker still verifying another world drops them.
#[test]
fn a_verification_lost_on_one_world_closes_without_waiting_for_the_others() {
    let dir = tempfile::tempdir().unwrap();
    let stop = StopRules { target_laps: Some(TargetLaps { laps: 3, evaluations: 1, verify_trials: 10 }), ..never() };
    // Every evaluation laps. The first verification laps none on reinvent_base, answered at
    // once; reinvent_wood's checks take 40 calls. The next checkpoint's verification holds.
    let script = Script { eval: |_| 100.0, verify: |k| if k == 0 { 0 } else { 10 }, ..HALFWAY };
    let out = dir.path().join("lost");
    let mut link = Scripted::new(script);
    link.slow_world = Some(("reinvent_wood", 40));
    let spec =
        RunSpec { checks_first: true, worlds: vec![WORLD.into(), "reinvent_wood".into()], ..spec(&out, stop, quick()) };
    let s = learner::run::run(&spec, &mut link, &mut Quiet).unwrap_or_else(|e| panic!("{e:#}"));
    assert!(s.stop_reason.contains("target laps reached and verified: ckpt_000002"), "{}", s.stop_reason);
    let evals = lines(&out.join("evaluations.jsonl"));
    let first = evals.iter().find(|e| e["verification"] == true).expect("the first verification's record");
    assert_eq!(first["policy_version"], 1, "{first}");
    // reinvent_wood's trials were not waited for: none counted.
    let worlds: Vec<(String, u64, u64)> = first["worlds"]
        .as_array()
        .unwrap()
        .iter()
        .map(|w| (w[0].as_str().unwrap().to_string(), w[3].as_u64().unwrap(), w[4].as_u64().unwrap()))
        .collect();
    assert_eq!(worlds, [(WORLD.to_string(), 0, 10), ("reinvent_wood".to_string(), 0, 0)]);
    // Granted while reinvent_wood's verification of v1 still ran, saying v1's checks are closed.
    assert!(link.granted_while_checking > 0, "the learner waited for the verification's every world");
    let after = link.credits.iter().find(|c| c.version == 1).expect("a grant for v1's episodes");
    assert_eq!(after.checks_closed_through, 1, "{after:?}");
    // Grants before any check closed say none is.
    assert_eq!(link.credits[0].checks_closed_through, 0, "{:?}", link.credits[0]);
}

/// Issue 55: where the workers share the learner's cores (`coordinator train`, `up`), an
/// evaluation that may stop the run goes first: no update and no grant while its trials run,
/// so they have the cores. A learner on a machine of its own trains on through them.
#[test]
fn an_update_waits_for_a_check_that_may_stop_the_run_only_where_the_workers_share_its_cores() {
    let dir = tempfile::tempdir().unwrap();
    let stop = StopRules { target_laps: Some(TargetLaps { laps: 3, evaluations: 1, verify_trials: 10 }), ..never() };
    let script = Script { eval: |n| if n >= 1 { 100.0 } else { 40.0 }, verify: |_| 10, ..HALFWAY };
    for checks_first in [true, false] {
        let out = dir.path().join(format!("checks-first-{checks_first}"));
        let mut link = Scripted::new(script);
        link.hold = 40;
        let spec = RunSpec { checks_first, ..spec(&out, stop.clone(), quick()) };
        let s = learner::run::run(&spec, &mut link, &mut Quiet).unwrap_or_else(|e| panic!("{checks_first}: {e:#}"));
        assert!(s.stop_reason.contains("target laps reached and verified"), "{checks_first}: {}", s.stop_reason);
        assert_eq!(link.evals, 2, "{checks_first}: the second checkpoint's evaluation laps and is verified");
        let during = (link.published_while_checking, link.granted_while_checking);
        if checks_first {
            assert_eq!(during, (0, 0), "nothing published or granted while trials ran");
        } else {
            assert!(during.0 > 0 && during.1 > 0, "a learner of its own trained on: {during:?}");
        }
    }
}

/// Issue 55: two workers that deliver the same episodes make the same updates whichever
/// delivers first (under `up` the agents' batches cross the network in either order), and
/// other episodes make other updates.
#[test]
fn the_same_episodes_make_the_same_update_whichever_worker_delivers_first() {
    let dir = tempfile::tempdir().unwrap();
    let model = |name: &str, second_first: bool, steps: usize| {
        let out = dir.path().join(name);
        let mut link = Scripted::new(Script { steps, ..HALFWAY });
        link.pair = Some(second_first);
        let stop = StopRules { max_episodes: Some(40), ..never() };
        let s = learner::run::run(&spec(&out, stop, quick()), &mut link, &mut Quiet).unwrap();
        assert_eq!((s.iterations, s.episodes), (4, 40), "{name}");
        // The tensors' bytes: the header's metadata is a map written in no fixed order.
        let bytes = std::fs::read(out.join("model/model.safetensors")).unwrap();
        let header = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
        bytes[8 + header..].to_vec()
    };
    let first = model("first", false, 20);
    assert_eq!(first, model("second", true, 20), "the same episodes in the other order");
    assert_ne!(first, model("longer", false, 21), "other episodes");
}
