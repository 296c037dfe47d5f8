//! Learners on several machines: synchronous PPO over Zenoh, each tower trained by its own
//! members, and each tower's members splitting every minibatch as DD-PPO does; SAC's
//! gradient steps split between all the members, every member holding a copy of the replay
//! memory.
//!
//! The learner that runs the job (the lowest live id) leads; every other learner that serves
//! the job follows. Per update the leader publishes a plan (the trajectories, the shuffle
//! seed, the members in rank order, and, for a member that does not hold the leader's state,
//! the weights and optimiser moments). Even ranks train the policy tower and odd ranks the
//! value tower; the members of a tower train on their shares of each minibatch, publish the
//! shares' weighted gradients and add them in rank order ([`learner::Reducer`]), so they
//! apply the same Adam step to the same weights, bit for bit. Every step ends with the loss
//! figures summed over the team, and the update with the two towers' states swapped, so
//! every member ends it with the same state. A member that dies (its liveliness token goes)
//! or stops answering makes the attempt fail: the leader makes that update again with
//! whoever is left, and the lost member gets the state again when it comes back. A follower
//! whose leader goes becomes the leader (the serve loop's lowest-id rule).
//!
//! SAC ([`learner::algorithm::Shared`] says what differs): a plan's episodes go into every
//! member's replay memory, in the plan's order, and its seed draws every member's batches and
//! noise, so each gradient step is shared as one learner's ([`learner::sac::Sac::step_in`]:
//! every member its share of the batch, the big dense layers' gradients as factors).
//! A joiner's state includes the leader's replay memory, sent in parts of at most 32 MB
//! ([`wire::MEMORY_PART`]) on the team's memory key just before the plan that carries the
//! state.

use learner::algorithm::{Shared, Team};
use learner::update::LearnerState;
use learner::{GroupError, Reducer, Refused, UpdateStats};
use policy::Trajectory;
use protocol::exchange::{self as wire, JobView, MemoryParts, TeamPlan, TeamState};
use protocol::net::{self, DropCounters, Sub, try_next, zenoh};
use protocol::{DecodeError, GradShare, PROTOCOL_VERSION, TeamJoin, TeamMemory, keys};
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use zenoh::Wait;

/// A member not heard from for this long is dropped from the team.
pub const MEMBER_TIMEOUT: Duration = Duration::from_secs(3);
/// How long a member waits for another's first share of an update (the plan, and maybe the
/// state, must reach it first) and for each later one.
const FIRST_SHARE_TIMEOUT: Duration = Duration::from_secs(60);
const SHARE_TIMEOUT: Duration = Duration::from_secs(15);

/// The learners whose liveliness tokens are up, kept current by a liveliness subscriber.
pub struct Roster {
    alive: Arc<Mutex<BTreeSet<String>>>,
    _sub: zenoh::pubsub::Subscriber<()>,
}

impl Roster {
    /// Follow the learners' tokens.
    pub fn new(session: &zenoh::Session) -> anyhow::Result<Roster> {
        let alive: Arc<Mutex<BTreeSet<String>>> = Arc::default();
        let a = alive.clone();
        let sub = session
            .liveliness()
            .declare_subscriber(keys::LEARNERS_ALIVE)
            .history(true)
            .callback(move |s| {
                let id = keys::last(s.key_expr().as_str()).to_string();
                if let Ok(mut set) = a.lock() {
                    match s.kind() {
                        zenoh::sample::SampleKind::Put => set.insert(id),
                        zenoh::sample::SampleKind::Delete => set.remove(&id),
                    };
                }
            })
            .wait()
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        Ok(Roster { alive, _sub: sub })
    }

    /// Whether `id`'s token is up.
    pub fn contains(&self, id: &str) -> bool {
        self.alive.lock().map(|s| s.contains(id)).unwrap_or(false)
    }

    /// The live learners, by id.
    pub fn ids(&self) -> Vec<String> {
        self.alive.lock().map(|s| s.iter().cloned().collect()).unwrap_or_default()
    }
}

/// One member's shares by (plan, step): the summed values and the factors.
type Queue = BTreeMap<(u64, u64), (Vec<f32>, Vec<f32>)>;

/// Gradient shares received and not yet added.
pub struct Shares {
    sub: Sub,
    job: String,
    waiting: HashMap<String, Queue>,
    drops: Arc<DropCounters>,
}

impl Shares {
    /// Subscribe to the job's shares.
    pub fn new(session: &zenoh::Session, job: &str, drops: Arc<DropCounters>) -> anyhow::Result<Shares> {
        Ok(Shares {
            sub: net::subscribe(session, &keys::team_shares(job))?,
            job: job.into(),
            waiting: HashMap::new(),
            drops,
        })
    }

    /// Take what arrived; shares of plans before `plan` are thrown away. (A share's size is
    /// checked when it is taken: the two exchanges of a step differ.)
    fn pump(&mut self, plan: u64) {
        while let Some((key, w)) = try_next::<GradShare>(&self.sub, &self.drops) {
            let from = keys::last(&key).to_string();
            match wire::share_from_wire(w, &self.job, &from) {
                Ok((p, step, values, factors)) if p >= plan => {
                    self.waiting.entry(from).or_default().insert((p, step), (values, factors));
                }
                Ok(_) => {}
                Err(e) => {
                    self.drops.refuse(&format!("a gradient share from {from}"), &e);
                }
            }
        }
        for q in self.waiting.values_mut() {
            q.retain(|(p, _), _| *p >= plan);
        }
    }
}

/// One update's view of the team: this member's rank, and the Zenoh all-reduce.
struct Group<'a> {
    session: &'a zenoh::Session,
    job: &'a str,
    me: &'a str,
    members: &'a [String],
    plan: u64,
    shares: &'a mut Shares,
    roster: &'a Roster,
    /// The member whose share did not come, when the attempt failed.
    lost: Option<String>,
}

impl Reducer for Group<'_> {
    fn shard(&self) -> (usize, usize) {
        (self.members.iter().position(|m| m == self.me).unwrap_or(0), self.members.len())
    }

    fn all_reduce(
        &mut self,
        step: u64,
        ranks: &[usize],
        values: &mut [f32],
        factors: Vec<f32>,
    ) -> Result<Vec<Vec<f32>>, GroupError> {
        let t0 = Instant::now();
        let rank = self.shard().0;
        let giving = ranks.contains(&rank);
        if giving {
            let share = wire::share_to_wire(self.job, self.me, self.plan, step, values, &factors);
            tracing::trace!(
                member = self.me,
                values = values.len(),
                factors = factors.len(),
                factor_bytes = share.factors.len() + share.factors_mask.len(),
                "sending share {step}"
            );
            net::put(self.session, &keys::team_share(self.job, self.me), &share)
                .map_err(|e| GroupError(e.to_string()))?;
        }
        let t2 = Instant::now();
        let timeout = if step == 0 { FIRST_SHARE_TIMEOUT } else { SHARE_TIMEOUT };
        let since = Instant::now();
        let mut theirs: Vec<Option<(Vec<f32>, Vec<f32>)>> = vec![None; self.members.len()];
        loop {
            self.shares.pump(self.plan);
            let mut missing = None;
            for &r in ranks {
                let Some(m) = self.members.get(r) else {
                    return Err(GroupError(format!(
                        "exchange {step} names member {r} of a team of {}",
                        self.members.len()
                    )));
                };
                if r == rank || theirs[r].is_some() {
                    continue;
                }
                match self.shares.waiting.get_mut(m).and_then(|q| q.remove(&(self.plan, step))) {
                    Some(v) if v.0.len() == values.len() => theirs[r] = Some(v),
                    Some(v) => {
                        let e = DecodeError::Invalid(format!(
                            "gradient share of {} values where {} were expected",
                            v.0.len(),
                            values.len()
                        ));
                        self.shares.drops.refuse(&format!("a gradient share from {m}"), &e);
                        missing = missing.or(Some(m.clone()));
                    }
                    None => missing = missing.or(Some(m.clone())),
                }
            }
            let Some(m) = missing else { break };
            if !self.roster.contains(&m) || since.elapsed() > timeout {
                let why = if self.roster.contains(&m) { "did not answer" } else { "left" };
                self.lost = Some(m.clone());
                return Err(GroupError(format!("learner {m} {why} (plan {}, step {step})", self.plan)));
            }
            std::thread::sleep(Duration::from_micros(200));
        }
        let t3 = Instant::now();
        // Every member adds the same numbers in the same (rank) order, in one pass: element
        // by element, ((s0 + s1) + s2) + …, with this member's own share read in place. One
        // share is copied as it is, bit for bit.
        let shares: Vec<&[f32]> = theirs.iter().map(|s| s.as_ref().map_or(&[][..], |(v, _)| &v[..])).collect();
        if let Some((&first, rest)) = ranks.split_first() {
            for (i, v) in values.iter_mut().enumerate() {
                let at = |r: usize| if r == rank { *v } else { shares[r][i] };
                let mut acc = at(first);
                for &r in rest {
                    acc += at(r);
                }
                *v = acc;
            }
        }
        tracing::trace!(
            member = self.me,
            giving,
            put_ms = (t2 - t0).as_secs_f64() * 1e3,
            wait_ms = (t3 - t2).as_secs_f64() * 1e3,
            sum_ms = t3.elapsed().as_secs_f64() * 1e3,
            "all-reduce step {step}"
        );
        let mut mine = Some(factors);
        Ok(ranks
            .iter()
            .map(|&r| match theirs[r].take() {
                Some((_, f)) => f,
                None => mine.take().unwrap_or_default(),
            })
            .collect())
    }
}

fn to_wire_state(s: LearnerState, memory: Option<&[u8]>) -> TeamState {
    TeamState { policy_version: s.version, tensors: s.tensors, memory_bytes: memory.map_or(0, |m| m.len() as u64) }
}

struct Member {
    heard: Instant,
    /// The last plan it says it made.
    made: u64,
    in_sync: bool,
    /// The base of the last plan that carried the state to it (older wishes for the state
    /// were sent before it arrived).
    state_base: u64,
}

/// The leader's side: who is in the team, and the plans.
pub struct TeamLead<'a> {
    session: &'a zenoh::Session,
    job: String,
    me: String,
    obs_size: usize,
    joins: Sub,
    shares: Shares,
    roster: Roster,
    drops: Arc<DropCounters>,
    members: BTreeMap<String, Member>,
    plan: u64,
    good: u64,
    /// Updates made by two or more learners.
    pub team_updates: u64,
    /// Team updates that failed and were made again.
    pub failures: u64,
}

impl<'a> TeamLead<'a> {
    /// Lead `job`'s team as `me`.
    pub fn new(
        session: &'a zenoh::Session,
        job: &str,
        me: &str,
        obs_size: usize,
        drops: Arc<DropCounters>,
    ) -> anyhow::Result<TeamLead<'a>> {
        // Plan numbers grow across restarts of the leader (a follower's last plan from an
        // earlier leader is never mistaken for this one's).
        let start = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
        let plan = start.as_millis() as u64 * 1000;
        Ok(TeamLead {
            session,
            job: job.into(),
            me: me.into(),
            obs_size,
            joins: net::subscribe(session, &keys::team_joins(job))?,
            shares: Shares::new(session, job, drops.clone())?,
            roster: Roster::new(session)?,
            drops,
            members: BTreeMap::new(),
            plan,
            good: plan,
            team_updates: 0,
            failures: 0,
        })
    }

    /// The team now, the leader first.
    pub fn members(&mut self) -> Vec<String> {
        self.hear();
        std::iter::once(self.me.clone()).chain(self.members.keys().cloned()).collect()
    }

    /// Whether every member says it made the last update the team made (a member tells
    /// every half second).
    pub fn caught_up(&mut self) -> bool {
        self.hear();
        let good = self.good;
        self.members.values().all(|m| m.made == good)
    }

    /// Take the followers' wishes, drop the members gone quiet.
    fn hear(&mut self) {
        while let Some((key, j)) = try_next::<TeamJoin>(&self.joins, &self.drops) {
            let from = keys::last(&key).to_string();
            if j.job_id != self.job || j.learner != from || from == self.me || !keys::is_valid_name(&from) {
                let e = protocol::DecodeError::Invalid(format!(
                    "team join for job {:?} from {:?} on {from:?}'s key",
                    j.job_id, j.learner
                ));
                self.drops.refuse("a team join", &e);
                continue;
            }
            let good = self.good;
            let m = self.members.entry(from.clone()).or_insert_with(|| {
                tracing::info!(job = %self.job, learner = %from, "a learner joins the team");
                Member { heard: Instant::now(), made: j.plan, in_sync: j.plan == good && !j.needs_state, state_base: 0 }
            });
            m.heard = Instant::now();
            m.made = j.plan;
            if j.needs_state && j.plan < m.state_base.max(1) {
                // Asked before the state reached it.
            } else if j.needs_state {
                m.in_sync = false;
            }
        }
        let roster = &self.roster;
        self.members.retain(|id, m| {
            let keep = m.heard.elapsed() < MEMBER_TIMEOUT && roster.contains(id);
            if !keep {
                tracing::warn!(learner = %id, "a learner left the team");
            }
            keep
        });
    }
}

impl Team for TeamLead<'_> {
    fn members(&mut self) -> usize {
        self.hear();
        self.members.len()
    }

    fn update(&mut self, algo: &mut dyn Shared, trajs: &[Trajectory]) -> Result<UpdateStats, Refused> {
        self.hear();
        self.plan += 1;
        if self.members.is_empty() {
            let result = algo.update_alone(trajs);
            if result.is_ok() {
                self.good = self.plan;
            }
            return result;
        }
        let members: Vec<String> = std::iter::once(self.me.clone()).chain(self.members.keys().cloned()).collect();
        let joiners = self.members.values().any(|m| !m.in_sync);
        let memory = if joiners { algo.memory() } else { None };
        let state = joiners.then(|| to_wire_state(algo.state(), memory.as_deref()));
        if state.is_some() {
            for m in self.members.values_mut().filter(|m| !m.in_sync) {
                m.state_base = self.good;
            }
        }
        let seed = algo.draw_seed();
        let plan = TeamPlan {
            leader: self.me.clone(),
            plan: self.plan,
            base: self.good,
            policy_version: algo.version(),
            members: members.clone(),
            seed,
            lr: algo.lr(),
            trajectories: trajs.to_vec(),
            state,
        };
        // The memory first: a joiner holds the plan until the memory it completes has come.
        let mut sent = Ok(());
        if let Some(m) = &memory {
            let t = Instant::now();
            for part in wire::memory_to_wire(&self.job, &self.me, self.good, m) {
                sent = sent.and_then(|_| net::put(self.session, &keys::team_memory(&self.job), &part));
            }
            tracing::info!(job = %self.job, bytes = m.len(), seconds = t.elapsed().as_secs_f64(), "sent the replay memory to the team's joiners");
        }
        drop(memory);
        let sent = sent.and_then(|_| {
            net::put(
                self.session,
                &keys::team_plan(&self.job),
                &wire::team_plan_to_wire(&self.job, &plan, self.obs_size),
            )
        });
        let (result, lost) = match sent {
            Ok(()) => {
                let mut group = Group {
                    session: self.session,
                    job: &self.job,
                    me: &self.me,
                    members: &members,
                    plan: self.plan,
                    shares: &mut self.shares,
                    roster: &self.roster,
                    lost: None,
                };
                let result = algo.update_planned(trajs, seed, &mut group);
                (result, group.lost)
            }
            Err(e) => {
                tracing::warn!(job = %self.job, "could not send the team's plan: {e}");
                // Nothing of the update was made: the leader makes it alone.
                (Err(Refused::Group { error: GroupError(e.to_string()), version: algo.version() }), None)
            }
        };
        let failed = match &result {
            Err(why) if why.is_group() => why.to_string(),
            _ => {
                self.team_updates += 1;
                if result.is_ok() {
                    self.good = self.plan;
                }
                for m in self.members.values_mut() {
                    m.in_sync = true;
                }
                return result;
            }
        };
        // A member was lost mid-update: drop it, and make the update again without it (alone;
        // the others get the state with the next plan).
        self.failures += 1;
        tracing::warn!(job = %self.job, "{failed}; making the update again");
        if let Some(l) = lost {
            self.members.remove(&l);
        }
        for m in self.members.values_mut() {
            m.in_sync = false;
            m.state_base = 0;
        }
        self.plan += 1;
        let result = algo.update_again(trajs);
        if result.is_ok() {
            self.good = self.plan;
        }
        result
    }
}

/// How following ended.
#[derive(Debug, PartialEq)]
pub enum FollowEnd {
    /// No live learner with a lower id is left: this one should lead.
    LeaderGone,
    /// `keep_going` said so.
    Stopped,
}

/// What a follower hears about each update it made.
pub type OnUpdate<'a> = dyn FnMut(&dyn Shared, &Result<UpdateStats, Refused>) + 'a;

/// A learner that follows a job's leader in its updates: its session and name, and what it
/// accepts.
pub struct Follower<'a> {
    /// The learner's session.
    pub session: &'a zenoh::Session,
    /// The learner's id.
    pub me: &'a str,
    /// A replay memory larger than this many bytes is refused.
    pub memory_limit: u64,
    /// Where refused messages are counted.
    pub drops: Arc<DropCounters>,
}

/// Take part in `view`'s job's updates as `member` until the leader goes or `keep_going`
/// says stop. `algo` is this learner's (its state, and memory, are replaced by the leader's
/// before the first update); `on_update` hears about every update made.
pub fn follow(
    follower: Follower<'_>,
    view: &JobView<'_>,
    algo: &mut dyn Shared,
    keep_going: &mut dyn FnMut() -> bool,
    on_update: &mut OnUpdate<'_>,
) -> anyhow::Result<FollowEnd> {
    let Follower { session, me, memory_limit, drops } = follower;
    let plans = net::subscribe(session, &keys::team_plan(view.job_id))?;
    let memories = net::subscribe(session, &keys::team_memory(view.job_id))?;
    let mut parts = MemoryParts::new(memory_limit);
    let mut shares = Shares::new(session, view.job_id, drops.clone())?;
    let roster = Roster::new(session)?;
    // The wish to take part, every half second from a thread of its own (an update of
    // several seconds must not look like a dead member).
    let wish = Arc::new(Mutex::new((0u64, true)));
    let stop = Arc::new(AtomicBool::new(false));
    let beat = {
        let (wish, stop, session) = (wish.clone(), stop.clone(), session.clone());
        let (job, me) = (view.job_id.to_string(), me.to_string());
        std::thread::spawn(move || {
            while !stop.load(Ordering::Relaxed) {
                let (plan, needs_state) = *wish.lock().expect("wish");
                let j = TeamJoin {
                    protocol_version: PROTOCOL_VERSION,
                    job_id: job.clone(),
                    learner: me.clone(),
                    plan,
                    needs_state,
                };
                let _ = net::put(&session, &keys::team_join(&job, &me), &j);
                std::thread::sleep(Duration::from_millis(500));
            }
        })
    };
    let set = |plan: u64, needs: bool| *wish.lock().expect("wish") = (plan, needs);
    let mut last = 0u64;
    tracing::info!(job = %view.job_id, learner = %me, "following the job's leader: asking to join its team");
    // The job's rate: its schedule never goes above it.
    let job_lr = algo.lr();
    let started = Instant::now();
    let end = loop {
        if !keep_going() {
            break FollowEnd::Stopped;
        }
        // Grace for the roster's first replies; then a leader must be there.
        if started.elapsed() > Duration::from_secs(2) && !roster.ids().iter().any(|id| id.as_str() < me) {
            break FollowEnd::LeaderGone;
        }
        pump_memory(&memories, &mut parts, view.job_id, &drops);
        let Some((_, w)) = try_next::<protocol::TeamPlan>(&plans, &drops) else {
            std::thread::sleep(Duration::from_millis(2));
            continue;
        };
        let plan = match wire::team_plan_from_wire(w, view) {
            Ok(p) => p,
            Err(e) => {
                drops.refuse("a team plan", &e);
                continue;
            }
        };
        if let Err(e) = rate_fits(plan.lr, job_lr) {
            drops.refuse("a team plan", &e);
            continue;
        }
        if !plan.members.iter().any(|m| m == me) {
            continue;
        }
        if last != plan.base
            && let Some(state) = plan.state.clone()
        {
            // The replay memory that completes the state, sent just before the plan.
            let memory = if state.memory_bytes > 0 {
                let waited = Instant::now();
                loop {
                    pump_memory(&memories, &mut parts, view.job_id, &drops);
                    if let Some(m) = parts.take(&plan.leader, plan.base, state.memory_bytes) {
                        break Some(m);
                    }
                    if waited.elapsed() > FIRST_SHARE_TIMEOUT || !roster.contains(&plan.leader) {
                        tracing::warn!(job = %view.job_id, "the replay memory of the leader's state did not all come");
                        break None;
                    }
                    std::thread::sleep(Duration::from_millis(2));
                }
            } else {
                None
            };
            let state_of = LearnerState { version: state.policy_version, tensors: state.tensors };
            match (state.memory_bytes > 0, memory) {
                (true, None) => {}
                (_, memory) => match algo.restore(state_of, memory.as_deref()) {
                    Ok(()) => {
                        last = plan.base;
                        let with =
                            memory.map_or(String::new(), |m| format!(" and its replay memory ({} bytes)", m.len()));
                        tracing::info!(job = %view.job_id, version = algo.version(), "took over the leader's weights and optimiser state{with}");
                    }
                    Err(e) => tracing::warn!(job = %view.job_id, "the leader's state does not fit this learner: {e}"),
                },
            }
        }
        if last != plan.base || algo.version() != plan.policy_version {
            set(last, true);
            continue;
        }
        set(last, false);
        // The leader's learning rate (the job's schedule), so every member steps alike.
        algo.set_lr(plan.lr);
        let mut group = Group {
            session,
            job: view.job_id,
            me,
            members: &plan.members,
            plan: plan.plan,
            shares: &mut shares,
            roster: &roster,
            lost: None,
        };
        let result = algo.update_planned(&plan.trajectories, plan.seed, &mut group);
        match &result {
            Err(why) if why.is_group() => {
                tracing::warn!(job = %view.job_id, "{why}");
                set(last, true);
            }
            _ => {
                if result.is_ok() {
                    last = plan.plan;
                }
                set(last, false);
                on_update(&*algo, &result);
            }
        }
    };
    stop.store(true, Ordering::Relaxed);
    let _ = beat.join();
    Ok(end)
}

/// Take the replay memory parts that arrived (between plans too: a memory's parts must not
/// wait in Zenoh's queue behind the plan they complete).
fn pump_memory(sub: &Sub, parts: &mut MemoryParts, job: &str, drops: &DropCounters) {
    while let Some((_, m)) = try_next::<TeamMemory>(sub, drops) {
        if let Err(e) = parts.insert(m, job) {
            drops.refuse("a replay memory part", &e);
        }
    }
}

/// A plan's learning rate must be one the job can give: its schedule never goes above the
/// hyperparameters' `lr`.
fn rate_fits(plan_lr: f64, job_lr: f64) -> Result<(), DecodeError> {
    if plan_lr > job_lr {
        return Err(DecodeError::Invalid(format!("a learning rate of {plan_lr}, above the job's lr {job_lr}")));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 8: a plan cannot raise the learning rate above the job's.
    #[test]
    fn a_plan_cannot_raise_the_rate_above_the_jobs() {
        for (plan, ok) in [(3e-4, true), (1.5e-4, true), (0.0, true), (3.0001e-4, false), (1.0, false)] {
            let r = rate_fits(plan, 3e-4);
            assert_eq!(r.is_ok(), ok, "{plan}");
            if let Err(e) = r {
                assert!(e.to_string().contains("above the job's lr 0.0003"), "{e}");
            }
        }
    }
}
