//! Which worlds each agent drives. With at least as many agents as worlds, agents spread
//! evenly, one world each (counts differ by at most one; a lost agent's world is filled at
//! once from the most crowded world). With fewer agents than worlds, every agent drives every
//! world at once, its environments split over them from its own offset, so no agent hops
//! between worlds and nothing it had running is thrown away. Pure functions, tested here.

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

/// The assignment message for `agent`'s share of a job.
pub fn assignment(doc: &Job, agent: &str, work: &AgentWork) -> anyhow::Result<Assignment> {
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
                reversed: false,
                steering_noise_deg: sim.noise.steering_deg,
                speed_noise_fraction: sim.noise.speed_fraction,
            })
            .collect(),
        offset: work.offset,
        envs: doc.envs_per_agent,
        job_worlds: doc.worlds.clone(),
        seed: doc.seed ^ work.generation.wrapping_mul(0x9E37_79B9),
        generation: work.generation,
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

    #[test]
    fn issue_8_fewer_agents_than_worlds_drive_every_world_at_once() {
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
