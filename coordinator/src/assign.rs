//! Which worlds each agent drives. With at least as many agents as worlds, agents spread
//! evenly, one world each (counts differ by at most one; a lost agent's world is filled at
//! once from the most crowded world). With fewer agents than worlds, every agent drives every
//! world at once, its environments split over them from its own offset, so no agent hops
//! between worlds and nothing it had running is thrown away. A job with the adaptive schedule
//! gives every agent every world and weighs the worlds by their last evaluation
//! ([`weights`]): the agents split their environments by the weights. Pure functions, tested
//! here.

use crate::jobs::AgentWork;
use protocol::Job;
use protocol::{Assignment, PROTOCOL_VERSION, WorldSpec};
use std::collections::BTreeMap;

/// Which worlds each agent drives (see the module doc): one each, balanced, when there are
/// at least as many agents as worlds; every world otherwise.
pub fn assign(
    agents: &[String],
    worlds: &[String],
    current: &BTreeMap<String, AgentWork>,
) -> BTreeMap<String, Vec<String>> {
    let mut out: BTreeMap<String, Vec<String>> = BTreeMap::new();
    if worlds.is_empty() {
        return out;
    }
    if agents.len() < worlds.len() {
        return agents.iter().map(|a| (a.clone(), worlds.to_vec())).collect();
    }
    let mut one: BTreeMap<String, String> = BTreeMap::new();
    for a in agents {
        if let Some(w) = current.get(a).filter(|c| c.worlds.len() == 1 && worlds.contains(&c.worlds[0])) {
            one.insert(a.clone(), w.worlds[0].clone());
        }
    }
    let count = |m: &BTreeMap<String, String>, w: &str| m.values().filter(|x| *x == w).count();
    for a in agents {
        if !one.contains_key(a) {
            let w = worlds.iter().min_by_key(|w| count(&one, w)).expect("worlds not empty").clone();
            one.insert(a.clone(), w);
        }
    }
    // Even out: move agents from the most to the least crowded world.
    loop {
        let max = worlds.iter().max_by_key(|w| count(&one, w)).expect("not empty").clone();
        let min = worlds.iter().min_by_key(|w| count(&one, w)).expect("not empty").clone();
        if count(&one, &max) <= count(&one, &min) + 1 {
            break;
        }
        let mover = one.iter().rev().find(|(_, w)| **w == max).map(|(a, _)| a.clone()).expect("max has agents");
        one.insert(mover, min);
    }
    for (a, w) in one {
        out.insert(a, vec![w]);
    }
    out
}

/// The agents a job takes: every one, or at most `cap` (when not 0), those it already has
/// first so that a new agent does not move one that is working.
pub fn capped(agents: &[String], current: &BTreeMap<String, AgentWork>, cap: u32) -> Vec<String> {
    if cap == 0 || agents.len() <= cap as usize {
        return agents.to_vec();
    }
    let (mut kept, others): (Vec<String>, Vec<String>) = agents.iter().cloned().partition(|a| current.contains_key(a));
    kept.extend(others);
    kept.truncate(cap as usize);
    kept.sort();
    kept
}

/// A job that runs or waits, as the queue reads it.
#[derive(Clone, Debug, PartialEq)]
pub struct Queued {
    /// The job.
    pub id: String,
    /// Who made it (empty: the CLI, or a console without users).
    pub owner: String,
    /// When it was started (Unix seconds).
    pub started: f64,
    /// It has begun (it has the agents, or had them): it keeps them until it ends.
    pub began: bool,
}

/// The order in which jobs get the cluster: those that have begun first (oldest first), then
/// the waiting ones round-robin by owner: the owner served longest ago first (never served:
/// before any), each owner's jobs oldest first. `served` holds when each owner last got the
/// cluster. One job at a time has the agents and the learners; the rest wait their turn.
pub fn queue(jobs: &[Queued], served: &BTreeMap<String, f64>) -> Vec<String> {
    let mut begun: Vec<&Queued> = jobs.iter().filter(|j| j.began).collect();
    begun.sort_by(|a, b| a.started.total_cmp(&b.started));
    let mut out: Vec<String> = begun.iter().map(|j| j.id.clone()).collect();
    let mut waiting: Vec<&Queued> = jobs.iter().filter(|j| !j.began).collect();
    waiting.sort_by(|a, b| a.started.total_cmp(&b.started));
    let mut last: BTreeMap<&str, f64> = served.iter().map(|(k, v)| (k.as_str(), *v)).collect();
    for j in &begun {
        last.insert(j.owner.as_str(), f64::INFINITY);
    }
    // Virtual times after every real one: each turn given moves its owner to the back.
    let mut turn = f64::MAX / 2.0;
    while !waiting.is_empty() {
        let next = (0..waiting.len())
            .min_by(|&a, &b| {
                let key =
                    |i: usize| (last.get(waiting[i].owner.as_str()).copied().unwrap_or(f64::MIN), waiting[i].started);
                key(a).partial_cmp(&key(b)).unwrap_or(std::cmp::Ordering::Equal)
            })
            .expect("not empty");
        let j = waiting.remove(next);
        turn += 1.0;
        last.insert(j.owner.as_str(), turn);
        out.push(j.id.clone());
    }
    out
}

/// One world's last evaluation, as the adaptive schedule reads it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WorldEval {
    /// Mean progress (%).
    pub progress: f64,
    /// Mean lap time when every trial lapped (s).
    pub lap_time: Option<f64>,
    /// The world's reference lap (s; its racing line's), to compare laps of different
    /// tracks.
    pub reference: f64,
}

/// What a world's weakness is at least: worlds that all lap near their best split evenly.
const BASE_WEAKNESS: f64 = 0.1;

/// The adaptive schedule's weights: each world's share of the environments, from its last
/// evaluation. A world's weakness is the progress it still misses (1 − progress / 100) plus a
/// quarter of how much slower its laps are than those of the world lapping nearest its
/// reference (reference / lap time): lowest progress first, then the slowest lap. Every world
/// keeps `floor` of an even share; the rest goes by weakness, each counted 0.1 more so that
/// worlds all lapping near their best split evenly rather than by noise. Even while any world
/// has no evaluation.
pub fn weights(evals: &[Option<WorldEval>], floor: f64) -> Vec<f64> {
    let n = evals.len();
    let even = vec![1.0 / n.max(1) as f64; n];
    let Some(evals) = evals.iter().copied().collect::<Option<Vec<WorldEval>>>() else { return even };
    let speed = |e: &WorldEval| e.lap_time.filter(|l| *l > 0.0).map(|l| e.reference / l);
    let fastest = evals.iter().filter_map(speed).fold(0.0, f64::max);
    let weak: Vec<f64> = evals
        .iter()
        .map(|e| {
            let missing = (1.0 - e.progress / 100.0).clamp(0.0, 1.0);
            let slower = match speed(e) {
                Some(v) if fastest > 0.0 => 1.0 - v / fastest,
                _ => 0.0,
            };
            missing + 0.25 * slower.clamp(0.0, 1.0)
        })
        .map(|w| w + BASE_WEAKNESS)
        .collect();
    let total: f64 = weak.iter().sum();
    let floor = if floor.is_finite() { floor.clamp(0.0, 1.0) } else { 0.0 };
    weak.iter().map(|w| floor / n as f64 + (1.0 - floor) * w / total).collect()
}

/// The assignment message for `agent`'s share of a job; `weights` split its environments
/// over the worlds (the adaptive schedule; empty: round-robin).
pub fn assignment(doc: &Job, agent: &str, work: &AgentWork, weights: &[f64]) -> anyhow::Result<Assignment> {
    let sim: sim_agent::SimConfig = sim_agent::config::parse_toml(&doc.sim_config_toml, "the job's sim config")?;
    Ok(Assignment {
        protocol_version: PROTOCOL_VERSION,
        job_id: doc.id.clone(),
        agent_id: agent.into(),
        worlds: work
            .worlds
            .iter()
            .map(|w| WorldSpec {
                name: w.clone(),
                reversed: doc.reversed,
                steering_noise_deg: sim.noise.steering_deg,
                speed_noise_fraction: sim.noise.speed_fraction,
            })
            .collect(),
        offset: work.offset,
        envs: doc.envs_per_agent,
        job_worlds: doc.worlds.clone(),
        seed: doc.seed ^ work.generation.wrapping_mul(0x9E37_79B9),
        generation: work.generation,
        weights: if weights.len() == work.worlds.len() { weights.to_vec() } else { Vec::new() },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(v: &[&str]) -> Vec<String> {
        v.iter().map(|s| s.to_string()).collect()
    }

    fn work(plan: &BTreeMap<String, Vec<String>>) -> BTreeMap<String, AgentWork> {
        plan.iter().map(|(a, w)| (a.clone(), AgentWork { worlds: w.clone(), offset: 0, generation: 1 })).collect()
    }

    /// Issue 52: waiting jobs take turns by owner, the owner served longest ago first; a job
    /// that has begun keeps the cluster.
    #[test]
    fn waiting_jobs_take_turns_by_owner() {
        let j = |id: &str, owner: &str, started: f64, began: bool| Queued {
            id: id.into(),
            owner: owner.into(),
            started,
            began,
        };
        let served = |v: &[(&str, f64)]| v.iter().map(|(k, t)| (k.to_string(), *t)).collect::<BTreeMap<_, _>>();
        // (jobs, when each owner was last served, the order)
        for (jobs, last, want) in [
            // Ann's three jobs came first; Bob's and Cy's still go second and third.
            (
                vec![
                    j("a1", "ann", 1.0, false),
                    j("a2", "ann", 2.0, false),
                    j("a3", "ann", 3.0, false),
                    j("b1", "bob", 4.0, false),
                    j("c1", "cy", 5.0, false),
                ],
                served(&[]),
                vec!["a1", "b1", "c1", "a2", "a3"],
            ),
            // Ann's job runs: it keeps the cluster; Bob goes next though Ann's second is older.
            (
                vec![j("a1", "ann", 1.0, true), j("a2", "ann", 2.0, false), j("b1", "bob", 3.0, false)],
                served(&[("ann", 100.0)]),
                vec!["a1", "b1", "a2"],
            ),
            // Bob was served last: Ann's waiting job goes before his.
            (
                vec![j("b2", "bob", 1.0, false), j("a2", "ann", 2.0, false)],
                served(&[("ann", 100.0), ("bob", 200.0)]),
                vec!["a2", "b2"],
            ),
            // One owner: oldest first.
            (vec![j("x2", "", 2.0, false), j("x1", "", 1.0, false)], served(&[]), vec!["x1", "x2"]),
        ] {
            assert_eq!(queue(&jobs, &last), want, "{jobs:?}");
        }
    }

    /// Issue 51: a job capped at N agents takes N, those it has first; 0 is every agent.
    #[test]
    fn a_job_capped_at_n_agents_takes_n_keeping_those_it_has() {
        let all = names(&["a1", "a2", "a3", "a4"]);
        let has = |v: &[&str]| work(&v.iter().map(|a| (a.to_string(), names(&["w"]))).collect());
        // (agents it has, cap, agents it takes)
        for (current, cap, want) in [
            (vec![], 0, vec!["a1", "a2", "a3", "a4"]),
            (vec![], 2, vec!["a1", "a2"]),
            (vec!["a3", "a4"], 2, vec!["a3", "a4"]),
            (vec!["a4"], 2, vec!["a1", "a4"]),
            (vec!["a2"], 9, vec!["a1", "a2", "a3", "a4"]),
            (vec!["a2", "a3", "a4"], 1, vec!["a2"]),
        ] {
            assert_eq!(capped(&all, &has(&current), cap), names(&want), "{current:?} capped at {cap}");
        }
    }

    #[test]
    fn six_agents_three_worlds_two_each_and_a_lost_agent_is_replaced() {
        let worlds = names(&["carpet", "concrete", "wood"]);
        let agents = names(&["a", "b", "c", "d", "e", "f"]);
        let plan = assign(&agents, &worlds, &BTreeMap::new());
        for w in &worlds {
            assert_eq!(plan.values().filter(|x| x[..] == [w.clone()]).count(), 2, "{plan:?}");
        }
        // Lose both agents of one world: it is refilled at once from the others.
        let current = work(&plan);
        let wood: Vec<String> = plan.iter().filter(|(_, w)| w[0] == "wood").map(|(a, _)| a.clone()).collect();
        let left: Vec<String> = agents.iter().filter(|a| !wood.contains(a)).cloned().collect();
        let plan2 = assign(&left, &worlds, &current);
        for w in &worlds {
            let n = plan2.values().filter(|x| x[0] == *w).count();
            assert!((1..=2).contains(&n), "{plan2:?}");
        }
        // Agents that keep their world are not moved (no episodes thrown away).
        let kept = plan2.iter().filter(|(a, w)| plan[*a] == **w).count();
        assert!(kept >= 3, "{plan:?} -> {plan2:?}");
    }

    /// Issue 34: the schedule weighs the weakest world most and keeps a floor for each.
    #[test]
    fn the_schedule_weighs_the_weakest_world_most_and_keeps_a_floor_for_each() {
        let e = |progress: f64, lap: Option<f64>| Some(WorldEval { progress, lap_time: lap, reference: 5.0 });
        let short = |progress: f64, lap: f64| Some(WorldEval { progress, lap_time: Some(lap), reference: 2.5 });
        // Each weakness counts 0.1 more (BASE_WEAKNESS).
        let split = |weak: &[f64], floor: f64| -> Vec<f64> {
            let total: f64 = weak.iter().map(|w| w + 0.1).sum();
            weak.iter().map(|w| floor / weak.len() as f64 + (1.0 - floor) * (w + 0.1) / total).collect()
        };
        // (evaluations, floor, the weights wanted)
        let table: Vec<(Vec<Option<WorldEval>>, f64, Vec<f64>)> = vec![
            // Not every world evaluated yet: even.
            (vec![e(50.0, None), None, e(100.0, Some(10.0))], 0.5, vec![1.0 / 3.0; 3]),
            // Nothing weaker than another: even.
            (vec![e(100.0, Some(10.0)), e(100.0, Some(10.0))], 0.5, vec![0.5, 0.5]),
            // Progress first: 40 % and 80 % miss 0.6 and 0.2; the lapping world keeps its floor
            // and the base weakness.
            (vec![e(40.0, None), e(80.0, None), e(100.0, Some(10.0))], 0.5, split(&[0.6, 0.2, 0.0], 0.5)),
            // Then the slowest lap against its reference: at half its line's pace against a
            // quarter (a shorter line in the same time is the slower lap).
            (vec![e(100.0, Some(10.0)), short(100.0, 10.0)], 0.0, split(&[0.0, 0.25 * 0.5], 0.0)),
            // No floor: the weakest takes nearly all.
            (vec![e(0.0, None), e(100.0, Some(5.0))], 0.0, split(&[1.0, 0.0], 0.0)),
        ];
        for (evals, floor, want) in table {
            let got = weights(&evals, floor);
            assert!((got.iter().sum::<f64>() - 1.0).abs() < 1e-9, "{got:?}");
            for (g, w) in got.iter().zip(&want) {
                assert!((g - w).abs() < 1e-9, "{evals:?} floor {floor}: {got:?}, want {want:?}");
            }
        }
    }

    /// Issue 8: fewer agents than worlds drive every world at once.
    #[test]
    fn fewer_agents_than_worlds_drive_every_world_at_once() {
        let worlds = names(&["carpet", "concrete", "wood"]);
        let agents = names(&["a", "b"]);
        let plan = assign(&agents, &worlds, &BTreeMap::new());
        assert_eq!(plan.len(), 2, "both agents work");
        for w in plan.values() {
            assert_eq!(w, &worlds, "every agent drives every world: {plan:?}");
        }
        // The plan is stable: asked again, nobody moves (nothing running is thrown away).
        assert_eq!(assign(&agents, &worlds, &work(&plan)), plan);
    }
}
