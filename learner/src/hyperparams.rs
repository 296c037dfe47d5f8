//! DeepRacer's `hyperparameters.json`, read unchanged (the keys of simapp's
//! `HyperParameterKeys`, as `sagemaker_graph_manager.py::get_updated_hyper_parameters`
//! reads them).
//!
//! Every key simapp knows is accepted with its type; a key Paddock does not use is accepted
//! and reported (`ignored`), an unknown key is reported as a warning, and a key of the wrong
//! type is refused naming the key. Defaults are the DeepRacer console's PPO defaults.

use policy::TrainingAlgorithm;
use policy::nn::Precision;
use serde_json::Value;
use std::path::Path;

/// PPO loss for the value head.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LossType {
    /// Huber (δ = 1).
    Huber,
    /// Mean squared error.
    MeanSquaredError,
}

/// Paddock's default `target_kl`. Without it the default job's policy, though it laps in
/// training, is now and then moved by one update by a KL of 0.5–2.5 (against a median of
/// 0.014), which knocks mean progress down to 20–50 % for a few iterations: a 3-minute `up`
/// job's final model can miss laps.
pub const DEFAULT_TARGET_KL: f64 = 0.05;

/// `num_epochs` when the file does not set it (DeepRacer's is 10, and a file that sets it is
/// followed). From pixels on three surfaces, over six seeds in two runs each beside DeepRacer's
/// 10, 3 epochs brought the verified model's checkpoint at a median of 47 s instead of 86 s in
/// `train` and 57 s instead of 70 s in `up`, and the models lapped the tracks they never
/// trained on as well (docs/benchmarks.md). The KL stop already ended most updates before
/// their fourth epoch; those it let run all 10 took a run's longest updates.
pub const DEFAULT_NUM_EPOCHS: usize = 3;

/// `value_epochs` when the file does not set it (see [`Hyperparameters::value_epochs`]).
/// The value tower is Paddock's own business (the car's archive holds the policy alone), and
/// its later epochs bought nothing measurable: from pixels on three surfaces, a third of the
/// gradient steps came after the third epoch, and with the value tower left out of them the
/// verified model came no later (docs/benchmarks.md).
pub const DEFAULT_VALUE_EPOCHS: Option<usize> = Some(3);

/// `dual_clip` when the file does not set it (see [`Hyperparameters::dual_clip`]): the
/// dual-clip PPO of Ye et al. (2020), whose c is 3. Paddock's updates train on episodes acted
/// a few versions back; once the policy is nearly sure of its actions, such an episode can
/// hold actions it now all but rules out, and without the bound a gradient step on their
/// ratios wrecked an object-avoidance policy for good (docs/benchmarks.md).
pub const DEFAULT_DUAL_CLIP: Option<f64> = Some(3.0);

/// How the learning rate moves over a job (Paddock's addition, key `lr_schedule`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LrSchedule {
    /// `lr` throughout, as in DeepRacer.
    Constant,
    /// `lr` until half of the job's budget is spent (its time, episodes or env steps,
    /// whichever is nearest its limit), then linearly down to zero at the budget's end; a
    /// job that stops at a target (progress, reward, laps) keeps `lr`. Without it a solved
    /// task's policy keeps drifting at full step size to the end of the job, and now and then
    /// the last model sits in a dip.
    #[default]
    Cooldown,
}

impl LrSchedule {
    /// The factor on `lr` once `spent` (0–1) of the job's budget is used.
    pub fn factor(self, spent: f64) -> f64 {
        match self {
            LrSchedule::Constant => 1.0,
            // `min` returns 1 for a NaN.
            LrSchedule::Cooldown => (2.0 * (1.0 - spent.clamp(0.0, 1.0))).min(1.0),
        }
    }
}

/// The hyperparameters, documented.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Hyperparameters {
    /// Minibatch size for gradient steps.
    pub batch_size: usize,
    /// Entropy bonus coefficient.
    pub beta_entropy: f64,
    /// γ.
    pub discount_factor: f64,
    /// Value loss: huber or mean squared error.
    pub loss_type: LossType,
    /// Adam learning rate.
    pub lr: f64,
    /// Episodes collected per training iteration.
    pub num_episodes_between_training: usize,
    /// Passes over each iteration's experience (a file without the key gets Paddock's
    /// [`DEFAULT_NUM_EPOCHS`]).
    pub num_epochs: usize,
    /// Stop after this many episodes (`term_cond_max_episodes`).
    pub term_cond_max_episodes: u64,
    /// Stop when the mean reward per episode over an iteration reaches this (`term_cond_avg_score`).
    pub term_cond_avg_score: f64,
    /// Paddock's addition (DeepRacer has no such key, and a file without it gets this
    /// default): an update stops taking gradient steps after the first minibatch whose
    /// approximate KL divergence from the policy the update began with exceeds 1.5 × this
    /// (Stable-Baselines3's `target_kl`). `null`: every epoch runs, as in DeepRacer.
    pub target_kl: Option<f64>,
    /// Paddock's addition (DeepRacer has no such key, and a file without it gets this
    /// default): `"cooldown"` keeps `lr` for the first half of the job's budget and brings
    /// it down linearly to zero at the end (not in a job that stops at a target);
    /// `"constant"` keeps `lr` throughout, as in DeepRacer.
    pub lr_schedule: LrSchedule,
    /// Paddock's addition (DeepRacer has no such key; default 0): the updates from policy
    /// version 0 up to this one train the value tower alone, the policy held as it is. A
    /// model imported from DeepRacer's graph starts at version 0 with a new value tower, and
    /// `clone` sets this for it, so that the advantages are worth following before the
    /// policy moves.
    pub value_warmup_updates: u64,
    /// Paddock's addition (DeepRacer has no such key, and a file without it gets this
    /// default): the value tower takes gradient steps in the first this-many epochs of each
    /// update and the policy tower in all of them; `null`: both in every epoch, as in
    /// DeepRacer. The updates of the value warm-up train it in every epoch.
    pub value_epochs: Option<usize>,
    /// Paddock's addition (DeepRacer has no such key, and a file without it gets this
    /// default): PPO's surrogate for a sample whose advantage is negative is bounded below by
    /// this many times its advantage, so a ratio above it carries no gradient (dual-clip
    /// PPO); `null`: the clipped surrogate alone, as in DeepRacer.
    pub dual_clip: Option<f64>,
    /// SAC's temperature α (`sac_alpha`): fixed, as in DeepRacer, unless `sac_target_entropy`
    /// is set, when it is where the tuning starts.
    pub sac_alpha: f64,
    /// Paddock's addition for SAC (default `null`: α fixed, as in DeepRacer): tune α so
    /// that the policy's entropy approaches this many nats; `"auto"` is −2 (minus the
    /// actions' dimension, SAC's usual target).
    pub sac_target_entropy: Option<f64>,
    /// Paddock's addition for SAC (default 1: DeepRacer's copy): how far V's target moves
    /// towards V once per iteration (τ).
    pub sac_tau: f64,
    /// SAC's replay memory, in transitions (DeepRacer's 1,000,000 by default).
    pub sac_replay_size: usize,
    /// Paddock's addition for SAC (default 1: DeepRacer's one gradient step per transition
    /// collected): gradient steps per new transition, the bound flow control keeps on the
    /// replay's intake.
    pub sac_gradient_steps_per_transition: f64,
    /// Paddock's addition for PPO (default `"f32"`): `"bf16"` makes the update's matrix
    /// products with operands rounded to bf16 and f32 sums, twice the multiply-adds a cycle
    /// on a CPU with AVX-512 BF16 (AMD Zen 4 and later, Intel Sapphire Rapids and later); a
    /// learner on a CPU without it refuses the run. The weights, Adam's moments and every sum
    /// stay f32.
    pub precision: Precision,
}

impl Default for Hyperparameters {
    fn default() -> Self {
        Hyperparameters {
            batch_size: 64,
            beta_entropy: 0.01,
            discount_factor: 0.99,
            loss_type: LossType::Huber,
            lr: 0.0003,
            num_episodes_between_training: 20,
            num_epochs: DEFAULT_NUM_EPOCHS,
            term_cond_max_episodes: 100_000,
            term_cond_avg_score: 100_000.0,
            target_kl: Some(DEFAULT_TARGET_KL),
            lr_schedule: LrSchedule::Cooldown,
            value_warmup_updates: 0,
            value_epochs: DEFAULT_VALUE_EPOCHS,
            dual_clip: DEFAULT_DUAL_CLIP,
            sac_alpha: 0.2,
            sac_target_entropy: None,
            sac_tau: 1.0,
            sac_replay_size: 1_000_000,
            sac_gradient_steps_per_transition: 1.0,
            precision: Precision::F32,
        }
    }
}

/// A parsed file and what it said that Paddock does not act on.
#[derive(Clone, Debug, PartialEq)]
pub struct Parsed {
    /// The values.
    pub hyperparameters: Hyperparameters,
    /// The keys the file sets.
    pub keys: Vec<String>,
    /// Keys nobody knows.
    pub unknown: Vec<String>,
}

impl Parsed {
    /// The keys the file sets that `algorithm` does not use, each with why.
    pub fn ignored_for(&self, algorithm: TrainingAlgorithm) -> Vec<String> {
        let ppo_only = "clipped PPO's, not used by SAC";
        let why = |k: &str| -> Option<&str> {
            match (algorithm, k) {
                (_, "stack_size") => Some("DeepRacer reads it but always stacks 1 frame"),
                (TrainingAlgorithm::ClippedPpo, "e_greedy_value" | "epsilon_steps") => {
                    Some("not used by clipped PPO with categorical exploration")
                }
                (TrainingAlgorithm::ClippedPpo, k) if k.starts_with("sac_") => Some("SAC's, not used by clipped PPO"),
                (
                    TrainingAlgorithm::Sac,
                    "beta_entropy"
                    | "num_epochs"
                    | "target_kl"
                    | "value_warmup_updates"
                    | "value_epochs"
                    | "dual_clip"
                    | "precision"
                    | "exploration_type"
                    | "e_greedy_value"
                    | "epsilon_steps",
                ) => Some(ppo_only),
                _ => None,
            }
        };
        self.keys.iter().filter_map(|k| why(k).map(|w| format!("{k} ({w})"))).collect()
    }
}

/// Why a file was refused.
#[derive(Debug, thiserror::Error)]
#[error("{origin}: {msg}")]
pub struct HyperparameterError {
    /// The file.
    pub origin: String,
    /// What is wrong, naming the key.
    pub msg: String,
}

impl Hyperparameters {
    /// Read a file.
    pub fn load(path: &Path) -> Result<Parsed, HyperparameterError> {
        let origin = path.display().to_string();
        let text = std::fs::read_to_string(path)
            .map_err(|e| HyperparameterError { origin: origin.clone(), msg: e.to_string() })?;
        Hyperparameters::parse(&text, &origin)
    }

    /// Parse JSON text.
    pub fn parse(text: &str, origin: &str) -> Result<Parsed, HyperparameterError> {
        let err = |msg: String| HyperparameterError { origin: origin.into(), msg };
        let v: Value = serde_json::from_str(text).map_err(|e| err(format!("not valid JSON: {e}")))?;
        let Value::Object(map) = v else { return Err(err("expected a JSON object".into())) };
        let mut h = Hyperparameters::default();
        let keys: Vec<String> = map.keys().cloned().collect();
        let mut unknown = Vec::new();
        let int = |k: &str, v: &Value| -> Result<u64, HyperparameterError> {
            match v {
                Value::Number(n) if n.as_u64().is_some() => Ok(n.as_u64().expect("checked")),
                Value::Number(n) if n.as_f64().is_some_and(|f| f >= 0.0 && f.fract() == 0.0) => {
                    Ok(n.as_f64().expect("checked") as u64)
                }
                Value::String(s) if s.trim().parse::<u64>().is_ok() => Ok(s.trim().parse().expect("checked")),
                other => Err(err(format!("key '{k}' is {other}, expected a whole number"))),
            }
        };
        let float = |k: &str, v: &Value| -> Result<f64, HyperparameterError> {
            match v {
                Value::Number(n) => Ok(n.as_f64().expect("JSON numbers are f64")),
                Value::String(s) if s.trim().parse::<f64>().is_ok() => Ok(s.trim().parse().expect("checked")),
                other => Err(err(format!("key '{k}' is {other}, expected a number"))),
            }
        };
        let positive =
            |k: &str, x: u64| if x == 0 { Err(err(format!("key '{k}' must be at least 1"))) } else { Ok(x as usize) };
        for (k, v) in &map {
            match k.as_str() {
                "batch_size" => h.batch_size = positive(k, int(k, v)?)?,
                "beta_entropy" => h.beta_entropy = float(k, v)?,
                "discount_factor" => {
                    h.discount_factor = float(k, v)?;
                    if !(0.0..=1.0).contains(&h.discount_factor) {
                        return Err(err(format!(
                            "key 'discount_factor' is {}, expected a value in [0, 1]",
                            h.discount_factor
                        )));
                    }
                }
                "loss_type" => {
                    h.loss_type = match v.as_str().map(|s| s.trim().to_lowercase()) {
                        Some(s) if s == "huber" => LossType::Huber,
                        Some(s) if s == "mean squared error" || s == "mse" => LossType::MeanSquaredError,
                        _ => {
                            return Err(err(format!(
                                "key 'loss_type' is {v}, expected \"huber\" or \"mean squared error\""
                            )));
                        }
                    }
                }
                "lr" => {
                    h.lr = float(k, v)?;
                    if !(h.lr > 0.0 && h.lr.is_finite()) {
                        return Err(err(format!("key 'lr' is {}, expected a positive number", h.lr)));
                    }
                }
                "num_episodes_between_training" => h.num_episodes_between_training = positive(k, int(k, v)?)?,
                "num_epochs" => h.num_epochs = positive(k, int(k, v)?)?,
                "term_cond_max_episodes" => h.term_cond_max_episodes = int(k, v)?,
                "term_cond_avg_score" => h.term_cond_avg_score = float(k, v)?,
                "target_kl" => {
                    h.target_kl = if v.is_null() { None } else { Some(float(k, v)?) };
                    if h.target_kl.is_some_and(|t| !(t > 0.0 && t.is_finite())) {
                        return Err(err(format!("key 'target_kl' is {v}, expected a positive number or null")));
                    }
                }
                "lr_schedule" => {
                    h.lr_schedule = match v.as_str() {
                        Some("cooldown") => LrSchedule::Cooldown,
                        Some("constant") => LrSchedule::Constant,
                        _ => {
                            return Err(err(format!(
                                "key 'lr_schedule' is {v}, expected \"cooldown\" or \"constant\""
                            )));
                        }
                    }
                }
                "value_warmup_updates" => h.value_warmup_updates = int(k, v)?,
                "value_epochs" => {
                    h.value_epochs = if v.is_null() {
                        None
                    } else {
                        match int(k, v) {
                            Ok(n) if n >= 1 => Some(n as usize),
                            _ => {
                                return Err(err(format!(
                                    "key 'value_epochs' is {v}, expected a whole number of at least 1 or null"
                                )));
                            }
                        }
                    };
                }
                "dual_clip" => {
                    h.dual_clip = match v.as_f64() {
                        _ if v.is_null() => None,
                        Some(c) if c > 1.0 && c.is_finite() => Some(c),
                        _ => return Err(err(format!("key 'dual_clip' is {v}, expected a number above 1 or null"))),
                    };
                }
                "precision" => {
                    h.precision = match v.as_str() {
                        Some("f32") => Precision::F32,
                        Some("bf16") => Precision::Bf16,
                        _ => return Err(err(format!("key 'precision' is {v}, expected \"f32\" or \"bf16\""))),
                    };
                }
                "stack_size" => {
                    int(k, v)?;
                }
                "e_greedy_value" => {
                    float(k, v)?;
                }
                "epsilon_steps" => {
                    int(k, v)?;
                }
                "sac_alpha" => {
                    h.sac_alpha = float(k, v)?;
                    if !(h.sac_alpha > 0.0 && h.sac_alpha.is_finite()) {
                        return Err(err(format!("key 'sac_alpha' is {v}, expected a positive number")));
                    }
                }
                "sac_target_entropy" => {
                    h.sac_target_entropy = match v {
                        Value::Null => None,
                        Value::String(s) if s == "auto" => Some(-2.0),
                        _ => Some(float(k, v).map_err(|_| {
                            err(format!("key 'sac_target_entropy' is {v}, expected a number of nats, \"auto\" or null"))
                        })?),
                    };
                }
                "sac_tau" => {
                    h.sac_tau = float(k, v)?;
                    if !(h.sac_tau > 0.0 && h.sac_tau <= 1.0) {
                        return Err(err(format!("key 'sac_tau' is {v}, expected a value in (0, 1]")));
                    }
                }
                "sac_replay_size" => h.sac_replay_size = positive(k, int(k, v)?)?,
                "sac_gradient_steps_per_transition" => {
                    h.sac_gradient_steps_per_transition = float(k, v)?;
                    let r = h.sac_gradient_steps_per_transition;
                    if !(r > 0.0 && r <= 1000.0) {
                        return Err(err(format!(
                            "key 'sac_gradient_steps_per_transition' is {v}, expected a number above 0 (at most 1000)"
                        )));
                    }
                }
                "exploration_type" => match v.as_str() {
                    Some("categorical") | Some("Categorical") => {}
                    Some(other) => {
                        return Err(err(format!(
                            "key 'exploration_type' is \"{other}\": Paddock's PPO explores by sampling (\"categorical\") only"
                        )));
                    }
                    None => return Err(err(format!("key 'exploration_type' is {v}, expected a string"))),
                },
                _ => unknown.push(k.clone()),
            }
        }
        Ok(Parsed { hyperparameters: h, keys, unknown })
    }

    /// The file as DeepRacer writes it.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(&serde_json::json!({
            "batch_size": self.batch_size,
            "beta_entropy": self.beta_entropy,
            "discount_factor": self.discount_factor,
            "e_greedy_value": 0.05,
            "epsilon_steps": 10000,
            "exploration_type": "categorical",
            "loss_type": match self.loss_type { LossType::Huber => "huber", LossType::MeanSquaredError => "mean squared error" },
            "lr": self.lr,
            "lr_schedule": self.lr_schedule,
            "num_episodes_between_training": self.num_episodes_between_training,
            "num_epochs": self.num_epochs,
            "stack_size": 1,
            "target_kl": self.target_kl,
            "term_cond_avg_score": self.term_cond_avg_score,
            "term_cond_max_episodes": self.term_cond_max_episodes,
            "value_warmup_updates": self.value_warmup_updates,
            "value_epochs": self.value_epochs,
            "dual_clip": self.dual_clip,
            "sac_alpha": self.sac_alpha,
            "sac_target_entropy": self.sac_target_entropy,
            "sac_tau": self.sac_tau,
            "sac_replay_size": self.sac_replay_size,
            "sac_gradient_steps_per_transition": self.sac_gradient_steps_per_transition,
            "precision": match self.precision { Precision::F32 => "f32", Precision::Bf16 => "bf16" },
        }))
        .expect("JSON")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn drfc_template_parses_unchanged() {
        let text = r#"{"batch_size": 64, "beta_entropy": 0.01, "discount_factor": 0.99, "e_greedy_value": 0.05,
            "epsilon_steps": 10000, "exploration_type": "categorical", "loss_type": "huber", "lr": 0.0003,
            "num_episodes_between_training": 20, "num_epochs": 5, "stack_size": 1, "term_cond_avg_score": 350.0,
            "term_cond_max_episodes": 1000, "sac_alpha": 0.2}"#;
        let p = Hyperparameters::parse(text, "h.json").unwrap();
        assert_eq!(p.hyperparameters.num_epochs, 5);
        assert_eq!(p.hyperparameters.term_cond_max_episodes, 1000);
        assert!(p.unknown.is_empty());
        let ignored = p.ignored_for(TrainingAlgorithm::ClippedPpo);
        assert_eq!(ignored.len(), 4, "{ignored:?}");
        let back = Hyperparameters::parse(&p.hyperparameters.to_json(), "back.json").unwrap();
        assert_eq!(back.hyperparameters, p.hyperparameters);
        // DeepRacer's file has no `target_kl`: Paddock's default applies.
        assert_eq!(p.hyperparameters.target_kl, Some(DEFAULT_TARGET_KL));
    }

    /// Issue 55: `num_epochs` is Paddock's 3 in a file without the key, and whatever a file
    /// sets (DRoA's 10, deepracer-for-cloud's 5) otherwise; the model's file says which.
    #[test]
    fn num_epochs_is_paddocks_default_only_when_the_file_does_not_set_it() {
        for (text, want) in [
            ("{}", DEFAULT_NUM_EPOCHS),
            (r#"{"lr": 0.0003}"#, 3),
            (r#"{"num_epochs": 10}"#, 10),
            (r#"{"num_epochs": 5}"#, 5),
            (r#"{"num_epochs": 1}"#, 1),
        ] {
            let h = Hyperparameters::parse(text, "h.json").unwrap().hyperparameters;
            assert_eq!(h.num_epochs, want, "{text}");
            let written: serde_json::Value = serde_json::from_str(&h.to_json()).unwrap();
            assert_eq!(written["num_epochs"], want, "{text}");
        }
    }

    /// Issue 8: `target_kl` is a number or null, and survives the round trip.
    #[test]
    fn target_kl_is_a_number_or_null_and_survives_the_round_trip() {
        for (text, want) in
            [(r#"{"target_kl": 0.02}"#, Some(0.02)), (r#"{"target_kl": null}"#, None), ("{}", Some(DEFAULT_TARGET_KL))]
        {
            let h = Hyperparameters::parse(text, "h.json").unwrap().hyperparameters;
            assert_eq!(h.target_kl, want, "{text}");
            let back = Hyperparameters::parse(&h.to_json(), "back.json").unwrap().hyperparameters;
            assert_eq!(back, h, "{text}");
        }
    }

    /// Issue 55: `value_epochs` is a whole number of at least 1 or null, Paddock's default
    /// without it, and survives the round trip; SAC says it does not use it.
    #[test]
    fn value_epochs_is_a_whole_number_or_null_and_survives_the_round_trip() {
        for (text, want) in
            [(r#"{"value_epochs": 3}"#, Some(3)), (r#"{"value_epochs": null}"#, None), ("{}", DEFAULT_VALUE_EPOCHS)]
        {
            let p = Hyperparameters::parse(text, "h.json").unwrap();
            assert_eq!(p.hyperparameters.value_epochs, want, "{text}");
            let back = Hyperparameters::parse(&p.hyperparameters.to_json(), "back.json").unwrap().hyperparameters;
            assert_eq!(back, p.hyperparameters, "{text}");
        }
        for bad in [
            r#"{"value_epochs": 0}"#,
            r#"{"value_epochs": -2}"#,
            r#"{"value_epochs": 2.5}"#,
            r#"{"value_epochs": "x"}"#,
        ] {
            let e = Hyperparameters::parse(bad, "h.json").unwrap_err().to_string();
            assert!(e.starts_with("h.json: key 'value_epochs'") && e.contains("at least 1 or null"), "{bad}: {e}");
        }
        let p = Hyperparameters::parse(r#"{"value_epochs": 3}"#, "h.json").unwrap();
        assert!(p.ignored_for(TrainingAlgorithm::Sac).iter().any(|k| k.starts_with("value_epochs")));
        assert!(p.ignored_for(TrainingAlgorithm::ClippedPpo).is_empty());
    }

    /// Issue 55: `dual_clip` is a number above 1 or null, Paddock's default without it, and
    /// survives the round trip; SAC does not use it.
    #[test]
    fn dual_clip_is_a_number_above_one_or_null_and_survives_the_round_trip() {
        for (text, want) in [
            (r#"{"dual_clip": 3}"#, Some(3.0)),
            (r#"{"dual_clip": 1.5}"#, Some(1.5)),
            (r#"{"dual_clip": null}"#, None),
            ("{}", DEFAULT_DUAL_CLIP),
        ] {
            let p = Hyperparameters::parse(text, "h.json").unwrap();
            assert_eq!(p.hyperparameters.dual_clip, want, "{text}");
            let back = Hyperparameters::parse(&p.hyperparameters.to_json(), "back.json").unwrap().hyperparameters;
            assert_eq!(back, p.hyperparameters, "{text}");
        }
        for bad in [r#"{"dual_clip": 1}"#, r#"{"dual_clip": 0.5}"#, r#"{"dual_clip": -3}"#, r#"{"dual_clip": "3"}"#] {
            let e = Hyperparameters::parse(bad, "h.json").unwrap_err().to_string();
            assert!(e.starts_with("h.json: key 'dual_clip'") && e.contains("above 1 or null"), "{bad}: {e}");
        }
        let p = Hyperparameters::parse(r#"{"dual_clip": 3}"#, "h.json").unwrap();
        assert!(p.ignored_for(TrainingAlgorithm::Sac).iter().any(|k| k.starts_with("dual_clip")));
        assert!(p.ignored_for(TrainingAlgorithm::ClippedPpo).is_empty());
    }

    /// Issue 55: `precision` is "f32" (without it) or "bf16", survives the round trip, and
    /// is PPO's alone.
    #[test]
    fn precision_is_f32_or_bf16_and_survives_the_round_trip() {
        for (text, want) in [
            (r#"{"precision": "bf16"}"#, Precision::Bf16),
            (r#"{"precision": "f32"}"#, Precision::F32),
            ("{}", Precision::F32),
        ] {
            let p = Hyperparameters::parse(text, "h.json").unwrap();
            assert_eq!(p.hyperparameters.precision, want, "{text}");
            let back = Hyperparameters::parse(&p.hyperparameters.to_json(), "back.json").unwrap().hyperparameters;
            assert_eq!(back, p.hyperparameters, "{text}");
        }
        for bad in [r#"{"precision": "fp16"}"#, r#"{"precision": 16}"#, r#"{"precision": null}"#] {
            let e = Hyperparameters::parse(bad, "h.json").unwrap_err().to_string();
            assert!(
                e.starts_with("h.json: key 'precision'") && e.contains(r#"expected "f32" or "bf16""#),
                "{bad}: {e}"
            );
        }
        let p = Hyperparameters::parse(r#"{"precision": "bf16"}"#, "h.json").unwrap();
        assert!(p.ignored_for(TrainingAlgorithm::Sac).iter().any(|k| k.starts_with("precision")));
        assert!(p.ignored_for(TrainingAlgorithm::ClippedPpo).is_empty());
    }

    /// Issue 30: `value_warmup_updates` is read and written, and zero without it.
    #[test]
    fn value_warmup_updates_is_read_written_and_zero_without_it() {
        assert_eq!(Hyperparameters::parse("{}", "h").unwrap().hyperparameters.value_warmup_updates, 0);
        let h = Hyperparameters::parse(r#"{"value_warmup_updates": 5}"#, "h").unwrap().hyperparameters;
        assert_eq!(h.value_warmup_updates, 5);
        assert_eq!(Hyperparameters::parse(&h.to_json(), "h").unwrap().hyperparameters, h);
        let e = Hyperparameters::parse(r#"{"value_warmup_updates": -1}"#, "h").unwrap_err().to_string();
        assert!(e.contains("value_warmup_updates"), "{e}");
    }

    /// Issue 8: the learning-rate schedule is the cool-down unless the file says constant.
    #[test]
    fn lr_schedule_is_cooldown_unless_the_file_says_constant() {
        for (text, want) in [
            ("{}", LrSchedule::Cooldown),
            (r#"{"lr_schedule": "constant"}"#, LrSchedule::Constant),
            (r#"{"lr_schedule": "cooldown"}"#, LrSchedule::Cooldown),
        ] {
            let h = Hyperparameters::parse(text, "h.json").unwrap().hyperparameters;
            assert_eq!(h.lr_schedule, want, "{text}");
            let back = Hyperparameters::parse(&h.to_json(), "back.json").unwrap().hyperparameters;
            assert_eq!(back, h, "{text}");
        }
        // Full rate for the first half of the budget, then down in a straight line to zero.
        for (spent, constant, cooldown) in [
            (0.0, 1.0, 1.0),
            (0.3, 1.0, 1.0),
            (0.5, 1.0, 1.0),
            (0.6, 1.0, 0.8),
            (0.9, 1.0, 0.2),
            (1.0, 1.0, 0.0),
            (1.7, 1.0, 0.0),
        ] {
            assert_eq!(LrSchedule::Constant.factor(spent), constant, "{spent}");
            assert!((LrSchedule::Cooldown.factor(spent) - cooldown).abs() < 1e-12, "{spent}");
        }
    }

    #[test]
    fn unknown_keys_are_reported_and_wrong_types_refused() {
        let p = Hyperparameters::parse(r#"{"lr": 0.001, "learning_rate": 1}"#, "h.json").unwrap();
        assert_eq!(p.unknown, vec!["learning_rate".to_string()]);
        assert_eq!(p.hyperparameters.lr, 0.001);
        for (text, want) in [
            (r#"{"batch_size": "big"}"#, "key 'batch_size'"),
            (r#"{"batch_size": 0}"#, "at least 1"),
            (r#"{"lr": [1]}"#, "key 'lr'"),
            (r#"{"lr": -1}"#, "positive"),
            (r#"{"loss_type": "l1"}"#, "key 'loss_type'"),
            (r#"{"discount_factor": 1.5}"#, "[0, 1]"),
            (r#"{"num_epochs": 2.5}"#, "whole number"),
            (r#"{"exploration_type": "e-greedy"}"#, "categorical"),
            (r#"{"target_kl": 0}"#, "key 'target_kl' is 0, expected a positive number or null"),
            (r#"{"target_kl": "far"}"#, "key 'target_kl'"),
            (r#"{"lr_schedule": "cosine"}"#, "key 'lr_schedule' is \"cosine\", expected \"cooldown\" or \"constant\""),
            ("[]", "expected a JSON object"),
        ] {
            let e = Hyperparameters::parse(text, "h.json").unwrap_err().to_string();
            assert!(e.starts_with("h.json: ") && e.contains(want), "{text}: {e}");
        }
    }
}
