//! The race a run drives: time trial, object avoidance or head-to-bot, with DeepRacer's keys
//! (the simapp's YAML keys, lower-cased, as the `[race]` table; deepracer-for-cloud's
//! `run.env` read as it is). Defaults are deepracer-for-cloud's, where its users come from.
//!
//! This module reads and checks the configuration and turns it into obstacle placements
//! ([`RaceConfig::placement`]); [`crate::objects`] drives them in an environment.

use serde::{Deserialize, Serialize};
use tracks::objects::{Lane, Placement};

/// DeepRacer's race types (`RACE_TYPE`, `DR_RACE_TYPE`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RaceType {
    /// Laps against the clock, alone.
    #[default]
    TimeTrial,
    /// Boxes on the lanes.
    ObjectAvoidance,
    /// Bot cars driving the lanes.
    HeadToBot,
}

impl RaceType {
    /// The name in the `[race]` table (`time_trial`, …).
    pub fn parse(s: &str) -> Option<RaceType> {
        RaceType::parse_deepracer(&s.to_ascii_uppercase())
    }

    /// The name in `run.env` (`TIME_TRIAL`, …).
    pub fn parse_deepracer(s: &str) -> Option<RaceType> {
        Some(match s {
            "TIME_TRIAL" => RaceType::TimeTrial,
            "OBJECT_AVOIDANCE" => RaceType::ObjectAvoidance,
            "HEAD_TO_BOT" => RaceType::HeadToBot,
            _ => return None,
        })
    }
}

/// The obstacle models DeepRacer has (`OBSTACLE_TYPE_LIST`); all share one footprint.
pub const OBSTACLE_TYPES: [&str; 3] = ["box_obstacle", "deepracer_box_obstacle", "amazon_box_obstacle"];

/// The `[race]` table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RaceConfig {
    /// The race type.
    pub race_type: RaceType,
    /// Obstacles on the track (`NUMBER_OF_OBSTACLES`); ignored when `object_positions` is set.
    pub number_of_obstacles: usize,
    /// The smallest gap between obstacles, in percent of the track's length
    /// (`MIN_DISTANCE_BETWEEN_OBSTACLES`).
    pub min_distance_between_obstacles: f64,
    /// Obstacles placed at random every episode (`RANDOMIZE_OBSTACLE_LOCATIONS`).
    pub randomize_obstacle_locations: bool,
    /// The obstacles are bot cars standing still (`IS_OBSTACLE_BOT_CAR`).
    pub is_obstacle_bot_car: bool,
    /// The obstacle model (`OBSTACLE_TYPE`).
    pub obstacle_type: String,
    /// Fixed obstacles, `"fraction,lane"` each (`OBJECT_POSITIONS`; lane `-1` outer, else
    /// inner); they set the count.
    pub object_positions: Vec<String>,
    /// Bot cars (`NUMBER_OF_BOT_CARS`).
    pub number_of_bot_cars: usize,
    /// The smallest gap between bots (m, `MIN_DISTANCE_BETWEEN_BOT_CARS`).
    pub min_distance_between_bot_cars: f64,
    /// Bots placed at random every episode (`RANDOMIZE_BOT_CAR_LOCATIONS`).
    pub randomize_bot_car_locations: bool,
    /// The bots' speed along the centre line (m/s, `BOT_CAR_SPEED`).
    pub bot_car_speed: f64,
    /// Bots change lanes (`IS_LANE_CHANGE`).
    pub is_lane_change: bool,
    /// Seconds between a bot's lane changes: at least (`LOWER_LANE_CHANGE_TIME`)…
    pub lower_lane_change_time: f64,
    /// …and at most (`UPPER_LANE_CHANGE_TIME`).
    pub upper_lane_change_time: f64,
    /// Centre-line metres a lane change takes (`LANE_CHANGE_DISTANCE`).
    pub lane_change_distance: f64,
    /// Seconds the bots stop after a car hits one from behind (`PENALTY_SECONDS`).
    pub bot_car_penalty: f64,
}

impl Default for RaceConfig {
    fn default() -> Self {
        RaceConfig {
            race_type: RaceType::TimeTrial,
            number_of_obstacles: 6,
            min_distance_between_obstacles: 2.0,
            randomize_obstacle_locations: true,
            is_obstacle_bot_car: false,
            obstacle_type: "box_obstacle".into(),
            object_positions: vec![],
            number_of_bot_cars: 3,
            min_distance_between_bot_cars: 2.0,
            randomize_bot_car_locations: false,
            bot_car_speed: 0.2,
            is_lane_change: false,
            lower_lane_change_time: 3.0,
            upper_lane_change_time: 5.0,
            lane_change_distance: 1.0,
            bot_car_penalty: 2.0,
        }
    }
}

/// Why a race configuration was refused; the message names the file and the key.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("{0}")]
pub struct RaceError(pub String);

/// deepracer-for-cloud's `run.env` key for each `[race]` key.
const RUN_ENV_KEYS: [(&str, &str); 16] = [
    ("DR_RACE_TYPE", "race_type"),
    ("DR_OA_NUMBER_OF_OBSTACLES", "number_of_obstacles"),
    ("DR_OA_MIN_DISTANCE_BETWEEN_OBSTACLES", "min_distance_between_obstacles"),
    ("DR_OA_RANDOMIZE_OBSTACLE_LOCATIONS", "randomize_obstacle_locations"),
    ("DR_OA_IS_OBSTACLE_BOT_CAR", "is_obstacle_bot_car"),
    ("DR_OA_OBSTACLE_TYPE", "obstacle_type"),
    ("DR_OA_OBJECT_POSITIONS", "object_positions"),
    ("DR_H2B_NUMBER_OF_BOT_CARS", "number_of_bot_cars"),
    ("DR_H2B_MIN_DISTANCE_BETWEEN_BOT_CARS", "min_distance_between_bot_cars"),
    ("DR_H2B_RANDOMIZE_BOT_CAR_LOCATIONS", "randomize_bot_car_locations"),
    ("DR_H2B_BOT_CAR_SPEED", "bot_car_speed"),
    ("DR_H2B_IS_LANE_CHANGE", "is_lane_change"),
    ("DR_H2B_LOWER_LANE_CHANGE_TIME", "lower_lane_change_time"),
    ("DR_H2B_UPPER_LANE_CHANGE_TIME", "upper_lane_change_time"),
    ("DR_H2B_LANE_CHANGE_DISTANCE", "lane_change_distance"),
    ("DR_H2B_BOT_CAR_PENALTY", "bot_car_penalty"),
];

/// A `run.env`'s assignments: `KEY=VALUE` lines (an `export ` before the key, quotes around
/// the value and a `# comment` after it are taken off; blank and comment lines skipped).
pub fn parse_env(text: &str, origin: &str) -> Result<Vec<(String, String)>, RaceError> {
    let mut out = vec![];
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let line = line.strip_prefix("export ").unwrap_or(line);
        let Some((k, v)) = line.split_once('=') else {
            return Err(RaceError(format!("{origin}: line {}: expected KEY=VALUE, got {line:?}", i + 1)));
        };
        let mut v = v.trim();
        if let Some(q) = v.chars().next().filter(|c| *c == '"' || *c == '\'') {
            v = v[1..].split(q).next().unwrap_or("");
        } else if let Some(j) = v.find(" #") {
            v = v[..j].trim_end();
        }
        out.push((k.trim().to_string(), v.to_string()));
    }
    Ok(out)
}

impl RaceConfig {
    /// The race a run's evaluations and verifications drive, when it differs from this one:
    /// head-to-bot with the bots placed at random and changing lanes, whatever training does.
    /// A model checked against bots that stand where they stood in training, in lanes it
    /// learnt, can lap without ever having to get past one; these it must overtake.
    pub fn for_checks(&self) -> Option<RaceConfig> {
        let bots = self.race_type == RaceType::HeadToBot && self.number_of_bot_cars > 0 && self.bot_car_speed > 0.0;
        (bots && !(self.randomize_bot_car_locations && self.is_lane_change)).then(|| RaceConfig {
            randomize_bot_car_locations: true,
            is_lane_change: true,
            ..self.clone()
        })
    }

    /// The race a deepracer-for-cloud `run.env` configures (its other keys are not read
    /// here). Every DR_OA_ and DR_H2B_ key is read, as deepracer-for-cloud passes them all.
    pub fn from_run_env(text: &str, origin: &str) -> Result<RaceConfig, RaceError> {
        let mut c = RaceConfig::default();
        for (k, v) in parse_env(text, origin)? {
            let Some((_, key)) = RUN_ENV_KEYS.iter().find(|(e, _)| *e == k) else { continue };
            let bad = |want: &str| RaceError(format!("{origin}: {k} is {v:?}; expected {want}"));
            let boolean = || match v.to_ascii_lowercase().as_str() {
                "true" => Ok(true),
                "false" => Ok(false),
                _ => Err(bad("True or False")),
            };
            let number =
                || v.parse::<f64>().ok().filter(|x| x.is_finite() && *x >= 0.0).ok_or_else(|| bad("a number ≥ 0"));
            let count = || v.parse::<usize>().map_err(|_| bad("a whole number ≥ 0"));
            match *key {
                "race_type" => {
                    c.race_type = RaceType::parse_deepracer(&v)
                        .ok_or_else(|| bad("TIME_TRIAL, OBJECT_AVOIDANCE or HEAD_TO_BOT"))?
                }
                "number_of_obstacles" => c.number_of_obstacles = count()?,
                "min_distance_between_obstacles" => c.min_distance_between_obstacles = number()?,
                "randomize_obstacle_locations" => c.randomize_obstacle_locations = boolean()?,
                "is_obstacle_bot_car" => c.is_obstacle_bot_car = boolean()?,
                "obstacle_type" => c.obstacle_type = v.clone(),
                "object_positions" => {
                    c.object_positions =
                        v.split(';').map(str::trim).filter(|s| !s.is_empty()).map(String::from).collect()
                }
                "number_of_bot_cars" => c.number_of_bot_cars = count()?,
                "min_distance_between_bot_cars" => c.min_distance_between_bot_cars = number()?,
                "randomize_bot_car_locations" => c.randomize_bot_car_locations = boolean()?,
                "bot_car_speed" => c.bot_car_speed = number()?,
                "is_lane_change" => c.is_lane_change = boolean()?,
                "lower_lane_change_time" => c.lower_lane_change_time = number()?,
                "upper_lane_change_time" => c.upper_lane_change_time = number()?,
                "lane_change_distance" => c.lane_change_distance = number()?,
                _ => c.bot_car_penalty = number()?,
            }
        }
        c.check(origin)?;
        Ok(c)
    }

    /// The checks every source of a race goes through; `origin` names it.
    pub fn check(&self, origin: &str) -> Result<(), RaceError> {
        let bad = |m: String| Err(RaceError(format!("{origin}: {m}")));
        if !OBSTACLE_TYPES.contains(&self.obstacle_type.as_str()) {
            return bad(format!(
                "race.obstacle_type (OBSTACLE_TYPE) is {:?}; DeepRacer has {OBSTACLE_TYPES:?}",
                self.obstacle_type
            ));
        }
        self.fixed_positions(origin)?;
        for (k, v) in [
            ("race.min_distance_between_obstacles", self.min_distance_between_obstacles),
            ("race.min_distance_between_bot_cars", self.min_distance_between_bot_cars),
            ("race.bot_car_speed", self.bot_car_speed),
            ("race.lane_change_distance", self.lane_change_distance),
            ("race.bot_car_penalty", self.bot_car_penalty),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(format!("{k} is {v}; expected a number ≥ 0"));
            }
        }
        if !(self.lower_lane_change_time > 0.0 && self.lower_lane_change_time <= self.upper_lane_change_time) {
            return bad(format!(
                "race.lower_lane_change_time {} and race.upper_lane_change_time {}: expected 0 < lower ≤ upper",
                self.lower_lane_change_time, self.upper_lane_change_time
            ));
        }
        Ok(())
    }

    /// `object_positions` as (fraction, lane) pairs.
    fn fixed_positions(&self, origin: &str) -> Result<Vec<(f64, Lane)>, RaceError> {
        self.object_positions
            .iter()
            .map(|p| {
                let bad = |why: &str| {
                    RaceError(format!("{origin}: race.object_positions (OBJECT_POSITIONS) entry {p:?}: {why}"))
                };
                let (f, lane) = p.split_once(',').ok_or_else(|| bad("expected \"fraction,lane\""))?;
                let f: f64 = f.trim().parse().map_err(|_| bad("the fraction is not a number"))?;
                if !(0.0..1.0).contains(&f) {
                    return Err(bad("the fraction of the track's length must be in [0, 1)"));
                }
                let lane: i64 = lane.trim().parse().map_err(|_| bad("the lane is not -1 or 1"))?;
                if !(-1..=1).contains(&lane) {
                    return Err(bad("the lane is not -1 (outer) or 1 (inner)"));
                }
                Ok((f, Lane::from_number(lane)))
            })
            .collect()
    }

    /// How the obstacles are placed (`None`: a race without obstacles); `origin` names the
    /// configuration in an error.
    pub fn placement(&self, origin: &str) -> Result<Option<Placement>, RaceError> {
        if self.race_type != RaceType::ObjectAvoidance {
            return Ok(None);
        }
        let fixed = self.fixed_positions(origin)?;
        Ok(Some(if !fixed.is_empty() {
            Placement::Fixed(fixed)
        } else {
            Placement::Spaced {
                count: self.number_of_obstacles,
                min_gap_percent: self.min_distance_between_obstacles,
                random: self.randomize_obstacle_locations,
            }
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 31: a DeepRacer-for-Cloud run.env configures the race.
    #[test]
    fn a_deepracer_for_cloud_run_env_configures_the_race() {
        let env = r#"
# run.env
DR_WORLD_NAME=reInvent2019_track
export DR_RACE_TYPE=OBJECT_AVOIDANCE
DR_OA_NUMBER_OF_OBSTACLES=3   # three boxes
DR_OA_MIN_DISTANCE_BETWEEN_OBSTACLES="4.5"
DR_OA_RANDOMIZE_OBSTACLE_LOCATIONS=False
DR_OA_OBSTACLE_TYPE=deepracer_box_obstacle
DR_OA_OBJECT_POSITIONS='0.23,-1;0.46, 1'
DR_H2B_BOT_CAR_SPEED=0.5
DR_H2B_IS_LANE_CHANGE=true
"#;
        let c = RaceConfig::from_run_env(env, "run.env").unwrap();
        assert_eq!(c.race_type, RaceType::ObjectAvoidance);
        assert_eq!((c.number_of_obstacles, c.min_distance_between_obstacles), (3, 4.5));
        assert!(!c.randomize_obstacle_locations && c.is_lane_change);
        assert_eq!(c.obstacle_type, "deepracer_box_obstacle");
        assert_eq!(c.object_positions, ["0.23,-1", "0.46, 1"]);
        assert_eq!(c.bot_car_speed, 0.5);
        // Fixed positions win over the count, with DeepRacer's lane sign.
        assert_eq!(
            c.placement("run.env").unwrap(),
            Some(Placement::Fixed(vec![(0.23, Lane::Outer), (0.46, Lane::Inner)]))
        );
        // Without them: the count, the gap, random or not.
        let spaced = RaceConfig { object_positions: vec![], ..c.clone() };
        assert_eq!(
            spaced.placement("x").unwrap(),
            Some(Placement::Spaced { count: 3, min_gap_percent: 4.5, random: false })
        );
        // Not an object-avoidance race: no obstacles.
        assert_eq!(RaceConfig::default().placement("x").unwrap(), None);
        // As the `[race]` table of a job's simulator configuration, it reads back the same.
        let sim = crate::SimConfig { race: c.clone(), ..crate::SimConfig::default() };
        let back: crate::SimConfig = crate::config::parse_toml(&toml::to_string(&sim).unwrap(), "sim.toml").unwrap();
        assert_eq!(back.race, c);
    }

    /// Issue 31: bad race keys are refused naming the key.
    #[test]
    fn bad_race_keys_are_refused_naming_the_key() {
        for (env, want) in [
            (
                "DR_RACE_TYPE=DRAG_RACE",
                "DR_RACE_TYPE is \"DRAG_RACE\"; expected TIME_TRIAL, OBJECT_AVOIDANCE or HEAD_TO_BOT",
            ),
            ("DR_OA_NUMBER_OF_OBSTACLES=-2", "DR_OA_NUMBER_OF_OBSTACLES"),
            (
                "DR_OA_RANDOMIZE_OBSTACLE_LOCATIONS=yes",
                "DR_OA_RANDOMIZE_OBSTACLE_LOCATIONS is \"yes\"; expected True or False",
            ),
            ("DR_OA_OBJECT_POSITIONS=1.2,1", "entry \"1.2,1\": the fraction of the track's length must be in [0, 1)"),
            ("DR_OA_OBJECT_POSITIONS=0.5,2", "the lane is not -1 (outer) or 1 (inner)"),
            ("DR_OA_OBJECT_POSITIONS=0.5", "expected \"fraction,lane\""),
            ("DR_OA_OBSTACLE_TYPE=pizza_box", "race.obstacle_type (OBSTACLE_TYPE) is \"pizza_box\""),
            ("DR_H2B_LOWER_LANE_CHANGE_TIME=9", "expected 0 < lower ≤ upper"),
            ("not an assignment", "line 1: expected KEY=VALUE"),
        ] {
            let e = RaceConfig::from_run_env(env, "run.env").unwrap_err().0;
            assert!(e.starts_with("run.env: ") && e.contains(want), "{env}: {e}");
        }
    }

    /// Issue 31: the race table reads DeepRacer's keys lower-cased.
    #[test]
    fn the_race_table_reads_deepracers_keys_lower_cased() {
        let t: RaceConfig =
            toml::from_str("race_type = \"head_to_bot\"\nnumber_of_bot_cars = 2\nbot_car_speed = 0.5\n").unwrap();
        assert_eq!((t.race_type, t.number_of_bot_cars, t.bot_car_speed), (RaceType::HeadToBot, 2, 0.5));
        assert_eq!(t.number_of_obstacles, RaceConfig::default().number_of_obstacles);
        let e = toml::from_str::<RaceConfig>("bots = 2").unwrap_err().to_string();
        assert!(e.contains("bots"), "{e}");
    }
}
