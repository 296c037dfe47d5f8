//! The learner's and the workers' vocabulary ([`policy::exchange`]) on the wire, and back.
//!
//! Decoding a message's bytes is not enough: every message coming back is checked against
//! the job it claims to be for (its id, its model's observation size, its worlds, the sender
//! the key names), and anything that does not fit is an error the caller counts and drops.

use crate::{DecodeError, keys, trajectory_from_wire, trajectory_to_wire};
use policy::exchange as ex;
use policy::folder::{self, Manifest};
use std::sync::Arc;

/// The most episodes one grant may hold per agent, trials one request may ask for, and
/// trajectories one batch may carry: far above any real job, low enough to refuse nonsense.
pub const SANITY_LIMIT: u64 = 100_000;

/// What a received message is checked against.
#[derive(Clone, Copy, Debug)]
pub struct JobView<'a> {
    /// The job's id.
    pub job_id: &'a str,
    /// Its model's observation size.
    pub obs_size: usize,
    /// Its worlds.
    pub worlds: &'a [String],
}

fn invalid<T>(m: String) -> Result<T, DecodeError> {
    Err(DecodeError::Invalid(m))
}

fn same_job(got: &str, want: &str) -> Result<(), DecodeError> {
    if got != want {
        return invalid(format!("message for job {got:?} on job {want:?}'s key"));
    }
    Ok(())
}

/// A grant on the wire.
pub fn credit_to_wire(job: &str, c: &ex::Credit) -> crate::Credit {
    crate::Credit {
        protocol_version: crate::PROTOCOL_VERSION,
        job_id: job.into(),
        policy_version: c.version,
        round: c.round,
        grants: c.episodes.iter().map(|(a, n)| crate::Grant { agent_id: a.clone(), episodes: *n }).collect(),
    }
}

/// A grant back, for `job`.
pub fn credit_from_wire(w: crate::Credit, job: &str) -> Result<ex::Credit, DecodeError> {
    same_job(&w.job_id, job)?;
    let mut episodes = std::collections::BTreeMap::new();
    for g in w.grants {
        if !keys::is_valid_name(&g.agent_id) || g.episodes > SANITY_LIMIT {
            return invalid(format!("grant of {} episodes to {:?}", g.episodes, g.agent_id));
        }
        episodes.insert(g.agent_id, g.episodes);
    }
    Ok(ex::Credit { version: w.policy_version, round: w.round, episodes })
}

/// An evaluation request on the wire.
pub fn eval_request_to_wire(job: &str, r: &ex::EvalRequest) -> crate::EvalRequest {
    crate::EvalRequest {
        protocol_version: crate::PROTOCOL_VERSION,
        job_id: job.into(),
        id: r.id,
        agent_id: r.worker.clone(),
        policy_version: r.version,
        world: r.world.clone(),
        trials: r.trials,
        seed: r.seed,
    }
}

/// An evaluation request back: for `job`, for `agent` (the key's), on one of the job's worlds.
pub fn eval_request_from_wire(
    w: crate::EvalRequest,
    job: &JobView<'_>,
    agent: &str,
) -> Result<ex::EvalRequest, DecodeError> {
    same_job(&w.job_id, job.job_id)?;
    if w.agent_id != agent {
        return invalid(format!("request for {:?} on {agent:?}'s key", w.agent_id));
    }
    if !job.worlds.contains(&w.world) {
        return invalid(format!("evaluation on {:?}, not one of the job's worlds", w.world));
    }
    if w.trials == 0 || w.trials as u64 > SANITY_LIMIT {
        return invalid(format!("{} evaluation trials", w.trials));
    }
    Ok(ex::EvalRequest {
        id: w.id,
        worker: w.agent_id,
        version: w.policy_version,
        world: w.world,
        trials: w.trials,
        seed: w.seed,
    })
}

/// An evaluation report on the wire.
pub fn eval_report_to_wire(job: &str, r: &ex::EvalReport) -> crate::EvalReport {
    let (trials, error) = match &r.trials {
        Ok(t) => (
            t.iter()
                .map(|t| crate::EvalTrial {
                    progress: t.progress,
                    lap_time: t.lap_time,
                    off_track: t.off_track,
                    steps: t.steps,
                    status: t.status.clone(),
                })
                .collect(),
            String::new(),
        ),
        Err(e) => (Vec::new(), e.clone()),
    };
    crate::EvalReport {
        protocol_version: crate::PROTOCOL_VERSION,
        job_id: job.into(),
        id: r.id,
        agent_id: r.worker.clone(),
        policy_version: r.version,
        world: r.world.clone(),
        trials,
        error,
    }
}

/// An evaluation report back: for `job`, from `agent` (the key's).
pub fn eval_report_from_wire(
    w: crate::EvalReport,
    job: &JobView<'_>,
    agent: &str,
) -> Result<ex::EvalReport, DecodeError> {
    same_job(&w.job_id, job.job_id)?;
    if w.agent_id != agent {
        return invalid(format!("report from {:?} on {agent:?}'s key", w.agent_id));
    }
    if !job.worlds.contains(&w.world) {
        return invalid(format!("report for {:?}, not one of the job's worlds", w.world));
    }
    let ok = |t: &crate::EvalTrial| {
        t.progress.is_finite()
            && (0.0..=100.0 + 1e-6).contains(&t.progress)
            && t.lap_time.is_none_or(|l| l.is_finite() && l >= 0.0)
    };
    if w.trials.len() as u64 > SANITY_LIMIT || !w.trials.iter().all(ok) {
        return invalid("evaluation trials out of range (progress 0–100 %, finite lap times)".into());
    }
    let trials = if w.error.is_empty() {
        Ok(w.trials
            .into_iter()
            .map(|t| ex::Trial {
                progress: t.progress,
                lap_time: t.lap_time,
                off_track: t.off_track,
                steps: t.steps,
                status: t.status,
            })
            .collect())
    } else {
        Err(w.error)
    };
    Ok(ex::EvalReport { id: w.id, worker: w.agent_id, version: w.policy_version, world: w.world, trials })
}

/// Experience on the wire.
pub fn experience_to_wire(job: &str, e: &ex::Experience, obs_size: usize) -> crate::ExperienceBatch {
    crate::ExperienceBatch {
        protocol_version: crate::PROTOCOL_VERSION,
        job_id: job.into(),
        agent_id: e.worker.clone(),
        seq: e.seq,
        trajectories: e.trajectories.iter().map(|t| trajectory_to_wire(t, obs_size)).collect(),
        env_steps: e.env_steps,
        seconds: e.seconds,
        credit_version: e.credit.0,
        credit_round: e.credit.1,
    }
}

/// Experience back: for `job`, from `agent` (the key's). Trajectories that do not fit the job
/// (observation size, world, lengths, non-finite numbers) are left out and returned as errors
/// for the caller to count; the rest are kept.
pub fn experience_from_wire(
    b: crate::ExperienceBatch,
    job: &JobView<'_>,
    agent: &str,
) -> Result<(ex::Experience, Vec<DecodeError>), DecodeError> {
    same_job(&b.job_id, job.job_id)?;
    if b.agent_id != agent {
        return invalid(format!("experience from {:?} on {agent:?}'s key", b.agent_id));
    }
    if b.trajectories.len() as u64 > SANITY_LIMIT || b.env_steps > SANITY_LIMIT * 100_000 || !b.seconds.is_finite() {
        return invalid("batch figures out of range".into());
    }
    let mut kept = Vec::with_capacity(b.trajectories.len());
    let mut refused = Vec::new();
    for w in b.trajectories {
        match trajectory_from_wire(w, job.obs_size) {
            Ok(t) if !job.worlds.contains(&t.world) => {
                refused.push(DecodeError::Invalid(format!("episode on {:?}, not one of the job's worlds", t.world)))
            }
            Ok(t) => kept.push(t),
            Err(e) => refused.push(e),
        }
    }
    Ok((
        ex::Experience {
            worker: b.agent_id,
            seq: b.seq,
            credit: (b.credit_version, b.credit_round),
            trajectories: kept,
            env_steps: b.env_steps,
            seconds: b.seconds,
        },
        refused,
    ))
}

/// A policy version on the wire (the model folder's three files).
pub fn policy_to_wire(job: &str, p: &ex::PolicyVersion, manifest: &Manifest) -> crate::PolicyUpdate {
    let f =
        policy::ModelFolder { metadata: (*p.metadata).clone(), model: (*p.model).clone(), manifest: manifest.clone() };
    let (metadata, manifest, weights) = folder::to_parts(&f);
    crate::PolicyUpdate {
        protocol_version: crate::PROTOCOL_VERSION,
        job_id: job.into(),
        policy_version: p.version,
        weights,
        model_metadata_json: metadata,
        manifest_json: manifest,
    }
}

/// A policy version back: for `job`, its weights matching its metadata and checksum, and
/// taking the job's observation size.
pub fn policy_from_wire(u: crate::PolicyUpdate, job: &JobView<'_>) -> Result<ex::PolicyVersion, DecodeError> {
    same_job(&u.job_id, job.job_id)?;
    let f = folder::from_parts(&u.model_metadata_json, &u.manifest_json, &u.weights, std::path::Path::new("<network>"))
        .map_err(|e| DecodeError::Invalid(e.to_string()))?;
    if f.manifest.obs_size != job.obs_size {
        return invalid(format!(
            "policy takes {} inputs, the job's observation has {}",
            f.manifest.obs_size, job.obs_size
        ));
    }
    if f.manifest.policy_version != u.policy_version {
        return invalid(format!("policy v{} whose manifest says v{}", u.policy_version, f.manifest.policy_version));
    }
    Ok(ex::PolicyVersion { version: u.policy_version, model: Arc::new(f.model), metadata: Arc::new(f.metadata) })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job() -> (String, Vec<String>) {
        ("job1".into(), vec!["reinvent_wood".into(), "reinvent_carpet".into()])
    }

    #[test]
    fn messages_that_do_not_fit_the_job_are_refused() {
        let (id, worlds) = job();
        let view = JobView { job_id: &id, obs_size: 3, worlds: &worlds };
        let t = policy::Trajectory {
            world: "reinvent_wood".into(),
            obs: vec![0.0; 6],
            choices: vec![policy::Choice::Discrete(0); 2],
            logp: vec![-1.0; 2],
            values: vec![0.0; 2],
            rewards: vec![1.0; 2],
            done: true,
            ..Default::default()
        };
        let mut off_world = t.clone();
        off_world.world = "Vegas_track".into();
        let e = ex::Experience {
            worker: "a1".into(),
            seq: 1,
            credit: (3, 1),
            trajectories: vec![t.clone(), off_world],
            env_steps: 4,
            seconds: 0.5,
        };
        let wire = experience_to_wire(&id, &e, 3);
        let (back, refused) = experience_from_wire(wire.clone(), &view, "a1").unwrap();
        assert_eq!(back.trajectories, vec![t]);
        assert_eq!(refused.len(), 1, "the episode on a world the job does not train is dropped");
        assert_eq!(back.credit, (3, 1));
        // Another job's id, another sender than the key names: refused whole.
        assert!(experience_from_wire(wire.clone(), &JobView { job_id: "job2", ..view }, "a1").is_err());
        assert!(experience_from_wire(wire, &view, "a2").is_err());

        let c = ex::Credit { version: 4, round: 2, episodes: [("a1".to_string(), 10u64)].into() };
        assert_eq!(credit_from_wire(credit_to_wire(&id, &c), &id).unwrap(), c);
        let mut huge = credit_to_wire(&id, &c);
        huge.grants[0].episodes = u64::MAX;
        assert!(credit_from_wire(huge, &id).is_err());

        let r = ex::EvalRequest {
            id: 7,
            worker: "a1".into(),
            version: 4,
            world: "reinvent_carpet".into(),
            trials: 3,
            seed: 9,
        };
        assert_eq!(eval_request_from_wire(eval_request_to_wire(&id, &r), &view, "a1").unwrap(), r);
        let elsewhere = ex::EvalRequest { world: "Vegas_track".into(), ..r.clone() };
        assert!(eval_request_from_wire(eval_request_to_wire(&id, &elsewhere), &view, "a1").is_err());

        let rep = ex::EvalReport {
            id: 7,
            worker: "a1".into(),
            version: 4,
            world: "reinvent_carpet".into(),
            trials: Ok(vec![ex::Trial {
                progress: 100.0,
                lap_time: Some(9.5),
                off_track: 0,
                steps: 140,
                status: "lap_complete".into(),
            }]),
        };
        assert_eq!(eval_report_from_wire(eval_report_to_wire(&id, &rep), &view, "a1").unwrap(), rep);
        let mut lie = eval_report_to_wire(&id, &rep);
        lie.trials[0].progress = 1e9;
        assert!(eval_report_from_wire(lie, &view, "a1").is_err(), "progress over 100 % is refused");
    }
}
