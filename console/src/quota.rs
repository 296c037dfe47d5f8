//! Quotas, checked on every path that spends them: a user's (`coordinator users quota`) and
//! the instance's (every user together, and models made on the console's token), in models
//! kept and minutes of training and evaluation. A model's minutes are its job's time so far,
//! or while it trains its stop's time limit when that is longer (DeepRacer on AWS reserves the
//! requested minutes the same way), plus its evaluations' time. A refusal is 403 and names the
//! quota, what is used and what is left.

use crate::api::App;
use crate::auth::{Forbidden, Principal};
use crate::store::ModelRecord;
use crate::users::Quota;
use protocol::JobState;

/// What models use: how many, and their minutes.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Usage {
    /// Models kept.
    pub models: u32,
    /// Minutes of training (or reserved for it) and evaluation.
    pub minutes: f64,
}

/// What an action asks for.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Ask {
    /// New models.
    pub models: u32,
    /// Minutes it may run (its stop's time limit); `Some(0.0)`: it needs minutes left, however
    /// few; none: it spends no minutes.
    pub minutes: Option<f64>,
}

impl Ask {
    /// An evaluation: no model, some minutes left.
    pub const EVALUATION: Ask = Ask { models: 0, minutes: Some(0.0) };
    /// An import: a model, no minutes.
    pub const IMPORT: Ask = Ask { models: 1, minutes: None };
}

/// A model's stop's time limit (minutes).
pub fn stop_minutes(stop: &toml::Table) -> f64 {
    stop.get("minutes").and_then(|v| v.as_float().or_else(|| v.as_integer().map(|i| i as f64))).unwrap_or(0.0)
}

/// A model's minutes: its training's (see the module), its evaluations' and its race entries'
/// (`entries`: every model's, from [`crate::races::Races::minutes_by_model`]).
pub fn model_minutes(app: &App, rec: &ModelRecord, entries: &std::collections::HashMap<String, f64>) -> f64 {
    let training = if rec.job_id.is_empty() {
        0.0
    } else {
        let reserved = stop_minutes(&rec.stop);
        match app.hub.job(&rec.job_id) {
            Some(j) if matches!(j.state(), JobState::Running | JobState::Stopping) => j.minutes.max(reserved),
            Some(j) => j.minutes,
            // The coordinator does not know the job (not listed yet): its reservation.
            None => reserved,
        }
    };
    let now = protocol::job::now_unix();
    let evaluations: f64 = crate::evaluations::dir(&app.store, &rec.name)
        .map(|d| crate::evaluations::list(&d, &Default::default()))
        .unwrap_or_default()
        .iter()
        .map(|e| {
            let start = e["created"].as_f64().unwrap_or(now);
            (e["finished"].as_f64().unwrap_or(now) - start).max(0.0) / 60.0
        })
        .sum();
    training + evaluations + entries.get(&rec.name).copied().unwrap_or(0.0)
}

/// What the models of `owner` use (every model: `None`).
pub fn usage(app: &App, owner: Option<&str>) -> Usage {
    let entries = app.races.minutes_by_model(protocol::job::now_unix());
    app.store.list().iter().filter(|r| owner.is_none() || r.owner.as_deref() == owner).fold(Usage::default(), |u, r| {
        Usage { models: u.models + 1, minutes: u.minutes + model_minutes(app, r, &entries) }
    })
}

/// Why `ask` does not fit `quota` given `used`, naming whose quota (`whose`: "your", "the
/// instance's").
pub fn refusal(quota: &Quota, used: Usage, ask: Ask, whose: &str) -> Option<String> {
    if let Some(limit) = quota.models
        && used.models + ask.models > limit
    {
        return Some(format!(
            "{whose} quota of models: {} of {limit} kept, {} left; delete one first",
            used.models,
            limit.saturating_sub(used.models)
        ));
    }
    if let (Some(limit), Some(asked)) = (quota.minutes, ask.minutes) {
        let left = (limit - used.minutes).max(0.0);
        if asked > 0.0 && used.minutes + asked > limit {
            return Some(format!(
                "{whose} quota of minutes: {:.1} of {limit} used or reserved, {left:.1} left; this asks for up to {asked:.1} \
                 (its stop's time limit): set a shorter one",
                used.minutes
            ));
        }
        if asked <= 0.0 && left <= 0.0 {
            return Some(format!("{whose} quota of minutes: {:.1} of {limit} used, none left", used.minutes));
        }
    }
    None
}

/// Check `ask` against the user's quota and the instance's: 403 naming the first that it
/// does not fit.
pub fn check(app: &App, p: &Principal, ask: Ask) -> Result<(), Forbidden> {
    if let Some(user) = &p.user {
        let quota = app.gate.users.get(user).map(|u| u.quota).unwrap_or_default();
        if quota != Quota::default()
            && let Some(why) = refusal(&quota, usage(app, Some(user)), ask, "your")
        {
            crate::counters::refused("a quota");
            return Err(Forbidden(why));
        }
    }
    let instance = app.gate.users.instance_quota();
    if instance != Quota::default()
        && let Some(why) = refusal(&instance, usage(app, None), ask, "the instance's")
    {
        crate::counters::refused("a quota");
        return Err(Forbidden(why));
    }
    Ok(())
}

/// [`check`] from a request's handler: on a blocking thread (it reads every model's
/// evaluations).
pub async fn check_off_thread(app: &App, p: &Principal, ask: Ask) -> Result<(), Forbidden> {
    let (app, p) = (app.clone(), p.clone());
    tokio::task::spawn_blocking(move || check(&app, &p, ask)).await.unwrap_or(Ok(()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 52: each quota refuses what does not fit, and says what is used and left.
    #[test]
    fn a_quota_refuses_what_does_not_fit_and_says_what_is_left() {
        let q = |models, minutes| Quota { models, minutes };
        let u = |models, minutes| Usage { models, minutes };
        let a = |models, minutes: f64| Ask { models, minutes: Some(minutes) };
        // (quota, used, ask, refused with)
        for (quota, used, ask, want) in [
            (q(None, None), u(100, 1e6), a(1, 60.0), None),
            (q(Some(2), None), u(1, 0.0), a(1, 10.0), None),
            (q(Some(2), None), u(2, 0.0), a(1, 10.0), Some("quota of models: 2 of 2 kept, 0 left")),
            (q(Some(2), None), u(2, 0.0), a(0, 0.0), None),
            (
                q(None, Some(30.0)),
                u(0, 25.0),
                a(1, 10.0),
                Some("quota of minutes: 25.0 of 30 used or reserved, 5.0 left"),
            ),
            (q(None, Some(30.0)), u(0, 20.0), a(1, 10.0), None),
            (q(None, Some(30.0)), u(0, 29.0), a(0, 0.0), None),
            (q(None, Some(30.0)), u(0, 30.0), a(0, 0.0), Some("30.0 of 30 used, none left")),
            (q(Some(5), Some(30.0)), u(0, 30.0), Ask::IMPORT, None),
        ] {
            let got = refusal(&quota, used, ask, "your");
            match want {
                None => assert_eq!(got, None, "{quota:?} {used:?} {ask:?}"),
                Some(w) => {
                    assert!(got.as_deref().is_some_and(|g| g.contains(w)), "{quota:?} {used:?} {ask:?}: {got:?}")
                }
            }
        }
    }
}
