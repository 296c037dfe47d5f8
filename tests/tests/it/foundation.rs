//! A car can be run around any DeepRacer track (every built-in world, both
//! directions) under a reward function, with DeepRacer's rules deciding the episode.

use sim_agent::config::SimConfig;
use sim_agent::driver::PurePursuit;
use sim_agent::{BuiltinReward, Env, EnvSpec, EpisodeStatus, EvalRules, Mode};
use std::sync::Arc;
use tracks::Direction;

/// Issue 2: the scripted driver laps every closed world in both directions.
#[test]
fn the_scripted_driver_laps_every_closed_world_in_both_directions() {
    let driver = PurePursuit { max_speed: 2.0, ..PurePursuit::default() };
    for world in tracks::worlds() {
        for direction in [Direction::Forward, Direction::Reversed] {
            let spec = EnvSpec::from_world(&world, direction);
            let closed = spec.track.is_closed();
            let mut env =
                Env::new(spec, Arc::new(SimConfig::default()), Mode::Evaluation(EvalRules::default()), 1, 0.0).unwrap();
            let mut last = None;
            for _ in 0..5_000 {
                let o = env.step(driver.act(&env), BuiltinReward::CenterLine).unwrap();
                if o.done {
                    last = Some(o);
                    break;
                }
            }
            let o = last.unwrap_or_else(|| panic!("{} {direction:?}: no end in 5000 steps", world.name));
            let what = format!("{} {direction:?}: {o:?}", world.name);
            if closed {
                assert_eq!(o.status, EpisodeStatus::LapComplete, "{what}");
                let len = env.track().length();
                // A lap can't be faster than the top speed allows, nor absurdly slow.
                let t = o.lap_time.unwrap();
                assert!(t > len / 2.0 && t < len / 0.5, "{what}");
                assert!(o.episode_reward > 0.5 * o.steps as f64, "mostly near the centre line: {what}");
            } else {
                // The open straight: driving off its far end is leaving the road.
                assert!(o.progress > 90.0, "{what}");
            }
        }
    }
}
