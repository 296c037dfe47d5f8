//! `learner bench --learners N`: whole PPO updates (batch, forward, backward, all-reduce and
//! Adam), or SAC's with `--sac`, shared by N learner processes of one thread each, a team over
//! Zenoh on loopback, against one learner of one thread making the same updates in the same
//! run. The leader makes one update alone before the team's first, so the members join a
//! learner with a history (SAC's: a replay memory, which travels with the state). With
//! `--check` it also replays the team's updates on one learner and fails unless the weights
//! agree to float rounding, and unless every member ends with the leader's state (weights,
//! optimisers) bit for bit.

use crate::bench_metadata;
use crate::team::{FollowEnd, Follower, TeamLead, follow};
use anyhow::{Context, Result, bail};
use faer::Par;
use learner::algorithm::{Shared, Team};
use learner::sac::SacTrainer;
use learner::{Hyperparameters, Ppo};
use policy::{ActorCritic, ModelMetadata, Trajectory};
use protocol::exchange::JobView;
use protocol::keys;
use protocol::net::zenoh::Wait;
use protocol::net::{self, DropCounters, NetArgs};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::hash::{Hash, Hasher};
use std::io::Read;
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The bench's job name and world.
const JOB: &str = "bench";
const WORLD: &str = "bench";
/// Episodes × steps of one update: 8 minibatches of 64 an epoch.
const EPISODES: usize = 8;
const STEPS: usize = 64;

/// The bench's learner: PPO's, or SAC's with `sac`, from fixed seeds (two calls give two
/// learners in the same state), its learning rate half the hyperparameters' as a job's
/// `lr_schedule` makes it (the members start from the hyperparameters' and must step with
/// the rate each plan carries); and its model.
fn learner_of(network: &str, epochs: usize, sac: bool) -> Result<(Box<dyn Shared>, ActorCritic)> {
    let meta = metadata(network, sac)?;
    let model = ActorCritic::new(&meta, 27, &mut ChaCha8Rng::seed_from_u64(1));
    if epochs == 0 {
        bail!("--epochs: expected at least 1");
    }
    // Every epoch of every update runs (no `target_kl` stop): the rate counts them all. SAC:
    // 8 gradient steps an update (one per 64 of its 512 new transitions).
    let hyper = Hyperparameters {
        num_epochs: epochs,
        batch_size: 64,
        target_kl: None,
        value_epochs: None,
        sac_gradient_steps_per_transition: 1.0 / 64.0,
        ..Hyperparameters::default()
    };
    let mut algo: Box<dyn Shared> = if sac {
        Box::new(SacTrainer::new(model.clone(), &meta, 27, &hyper, 0, 7, Par::Seq).map_err(anyhow::Error::msg)?)
    } else {
        Box::new(Ppo::new(model.clone(), hyper.clone(), 0, 7, Par::Seq))
    };
    algo.set_lr(hyper.lr * 0.5);
    Ok((algo, model))
}

/// The bench's model description: [`bench_metadata`]'s, or with `sac` DeepRacer's
/// continuous SAC on the same network.
fn metadata(network: &str, sac: bool) -> Result<ModelMetadata> {
    let (name, sensor, meta) = bench_metadata(network)?;
    if !sac {
        return Ok(meta);
    }
    Ok(ModelMetadata::parse(
        &format!(
            r#"{{"action_space":{{"speed":{{"high":2,"low":1}},"steering_angle":{{"high":30,"low":-30}}}},"sensor":["{sensor}"],"neural_network":"{name}","training_algorithm":"sac","action_space_type":"continuous","version":"5"}}"#
        ),
        "bench",
    )?)
}

fn episodes(model: &ActorCritic, camera: bool, seed: u64) -> Vec<Trajectory> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let os = model.obs_size();
    (0..EPISODES)
        .map(|_| {
            let obs: Vec<f32> = (0..STEPS * os)
                .map(|_| if camera { rng.random_range(0..=255u8) as f32 } else { rng.random_range(-1.0..1.0) })
                .collect();
            let acts = model.act(&obs, STEPS, false, &mut rng, Par::Seq);
            Trajectory {
                world: WORLD.into(),
                obs,
                choices: acts.iter().map(|a| a.choice).collect(),
                logp: acts.iter().map(|a| a.logp).collect(),
                values: acts.iter().map(|a| a.value).collect(),
                rewards: (0..STEPS).map(|_| rng.random_range(0.0..1.0)).collect(),
                done: true,
                ..Default::default()
            }
        })
        .collect()
}

/// A learner's whole state (every weight and moment, bit for bit) and its memory, hashed.
fn digest(algo: &dyn Shared) -> u64 {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    let state = algo.state();
    state.version.hash(&mut h);
    for (name, values) in &state.tensors {
        name.hash(&mut h);
        for x in values {
            x.to_bits().hash(&mut h);
        }
    }
    // The memory's tensors and header, in name order (the header's own order is not fixed).
    if let Some(bytes) = algo.memory() {
        let st = safetensors::SafeTensors::deserialize(&bytes).expect("a memory's bytes");
        let mut names = st.names();
        names.sort();
        for n in names {
            n.hash(&mut h);
            st.tensor(n).expect("named").data().hash(&mut h);
        }
        let (_, meta) = safetensors::SafeTensors::read_metadata(&bytes).expect("a memory's bytes");
        let info: std::collections::BTreeMap<_, _> = meta.metadata().clone().unwrap_or_default().into_iter().collect();
        info.hash(&mut h);
    }
    h.finish()
}

/// A learner's weights, flat (its state but the optimisers).
fn weights(algo: &dyn Shared) -> Vec<f32> {
    let state = algo.state();
    state.tensors.into_iter().filter(|(n, _)| !n.starts_with("adam.") && n != "carry").flat_map(|(_, v)| v).collect()
}

fn free_port() -> Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
}

/// Updates for at least `seconds` (and at least two); sample-gradients per second (each
/// update says how many it made).
fn rate(seconds: f64, mut update: impl FnMut() -> Result<usize>) -> Result<(f64, usize)> {
    let t = Instant::now();
    let (mut k, mut samples) = (0, 0);
    while t.elapsed().as_secs_f64() < seconds || k < 2 {
        samples += update()?;
        k += 1;
    }
    Ok((samples as f64 / t.elapsed().as_secs_f64(), k))
}

/// The sample-gradients an update made: PPO's every sample once an epoch, SAC's its batches.
fn sample_gradients(stats: &learner::UpdateStats, epochs: usize) -> usize {
    match stats {
        learner::UpdateStats::Sac(s) => s.samples,
        learner::UpdateStats::Ppo(s) => s.samples * epochs,
    }
}

/// The bench's leader: rows for 1 learner and for a team of `learners`.
pub fn run(network: &str, seconds: f64, learners: usize, epochs: usize, check: bool, sac: bool) -> Result<()> {
    if check && epochs > 3 && !sac {
        bail!(
            "--check compares the team with one learner after about 24 minibatch steps, where rounding has not yet grown: give --epochs 3 or fewer (this run: {epochs})"
        );
    }
    let (mut alone, model) = learner_of(network, epochs, sac)?;
    let camera = !network.eq_ignore_ascii_case("MLP");
    let trajs = episodes(&model, camera, 2);
    let os = model.obs_size();

    alone.update_alone(&trajs)?;
    let (one, _) = rate(seconds, || Ok(sample_gradients(&alone.update_alone(&trajs)?, epochs)))?;
    let port = free_port()?;
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let session = net::open(&NetArgs { listen: vec![endpoint.clone()], ..Default::default() })?;
    let me = "bench-learner-0";
    let token =
        session.liveliness().declare_token(keys::learner_alive(me)).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    let exe = std::env::current_exe()?;
    let mut children = Vec::new();
    for i in 1..learners {
        children.push(
            Command::new(&exe)
                .args([
                    "bench-member",
                    "--network",
                    network,
                    "--connect",
                    &endpoint,
                    "--id",
                    &format!("bench-learner-{i}"),
                    "--epochs",
                    &epochs.to_string(),
                ])
                .args(sac.then_some("--sac"))
                .env("RUST_LOG", std::env::var("RUST_LOG").unwrap_or_else(|_| "warn".into()))
                .stdout(Stdio::piped())
                .spawn()
                .context("starting a team member")?,
        );
    }
    let drops = Arc::new(DropCounters::default());
    let mut lead = TeamLead::new(&session, JOB, me, os, drops.clone())?;
    let waited = Instant::now();
    while lead.members().len() < learners {
        if waited.elapsed() > Duration::from_secs(60) {
            bail!("only {:?} of {learners} learners joined within 60 s", lead.members());
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    // The leader and the one learner the team is checked against start alike, and each makes
    // one update alone first: the members join a learner with a history.
    let (mut algo, _) = learner_of(network, epochs, sac)?;
    let (mut replay, _) = learner_of(network, epochs, sac)?;
    let start = weights(algo.as_ref());
    algo.update_alone(&trajs)?;
    replay.update_alone(&trajs)?;
    // The first update carries the state to the members: not timed.
    let t0 = Instant::now();
    lead.update(algo.as_mut(), &trajs)?;
    let first_s = t0.elapsed().as_secs_f64();
    // Rounding differences grow with every step of a chaotic optimisation: the comparison
    // with one learner is made after about 24 gradient steps (at least one update).
    let checked = if sac { 3 } else { (3 / epochs).max(1) };
    let mut against_one = None;
    if check {
        for _ in 1..checked {
            lead.update(algo.as_mut(), &trajs)?;
        }
        for _ in 0..checked {
            replay.update_alone(&trajs)?;
        }
        // How far the team is from one learner, against how far the updates moved the
        // weights. Adam divides every gradient by its running scale, so for weights whose
        // gradients are nearly zero rounding differences become whole steps: a few per cent
        // of the movement for the camera network after 24 steps (1e-6 for the MLP); a lost
        // or doubled share changes the direction of every step, tens of per cent.
        let (one, team) = (weights(replay.as_ref()), weights(algo.as_ref()));
        let norm = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| ((x - y) as f64).powi(2)).sum::<f64>().sqrt();
        let (apart, moved) = (norm(&team, &one), norm(&one, &start));
        let ok = moved > 0.0 && apart <= 5e-2 * moved && replay.version() == algo.version();
        against_one = Some((apart, moved, ok));
    }
    let (team, timed) = rate(seconds, || {
        let stats = match lead.update(algo.as_mut(), &trajs) {
            Ok(stats) => stats,
            Err(why) => bail!("the team's update was refused during the bench: {why}"),
        };
        if lead.failures > 0 {
            bail!("the team failed during the bench ({} failures)", lead.failures);
        }
        Ok(sample_gradients(&stats, epochs))
    })?;
    let made = timed + if check { checked } else { 1 };
    if lead.team_updates != made as u64 {
        bail!("{} of {made} updates were made by the team", lead.team_updates);
    }
    // The leader goes once every member has made the last update (a member still applying it
    // when the leader goes would print the state before it): the members print their
    // weights' digest and end.
    let waited = Instant::now();
    while !lead.caught_up() && waited.elapsed() < Duration::from_secs(10) {
        std::thread::sleep(Duration::from_millis(50));
    }
    drop(lead);
    drop(token);
    session.close().wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut member_digests = Vec::new();
    for mut c in children {
        let mut out = String::new();
        c.stdout.take().expect("piped").read_to_string(&mut out)?;
        let status = c.wait()?;
        if !status.success() {
            bail!("a team member failed ({status}): {out}");
        }
        member_digests.push(out.trim().to_string());
    }

    println!();
    if sac {
        println!(
            "# learner bench: whole SAC updates ({EPISODES} × {STEPS} new transitions, 8 gradient steps of 64 an update), {network}"
        );
    } else {
        println!(
            "# learner bench: whole updates ({EPISODES} × {STEPS} samples, minibatch 64, {epochs} epoch(s) an update), {network}"
        );
    }
    println!();
    println!("| measurement | sample-gradients/s | ratio to 1 × 1 |");
    println!("|---|---|---|");
    println!("| 1 learner × 1 thread, whole updates | {one:.0} | 1.00 |");
    println!(
        "| {learners} learner processes × 1 thread, a team over Zenoh on loopback | {team:.0} | {:.2} |",
        team / one
    );
    let what = if sac { "the weights, optimiser state and replay memory" } else { "the weights and optimiser state" };
    println!("(the team's first update, which carries {what} to the members: {first_s:.2} s)");

    if let Some((apart, moved, ok_one)) = against_one {
        println!(
            "check: after {checked} updates the team's weights are {apart:.3e} from one learner's, which moved {moved:.3e} from the start ({:.2e} of it)",
            apart / moved.max(f64::MIN_POSITIVE)
        );
        let want = format!("digest {:016x} version {}", digest(algo.as_ref()), algo.version());
        let ok_members = member_digests.iter().all(|d| d.ends_with(&want));
        for d in &member_digests {
            println!("check: {d} (leader: {want})");
        }
        if !ok_one || !ok_members {
            bail!(
                "check failed: the team's update is not one learner's, or a member's weights differ from the leader's"
            );
        }
        println!("check passed");
    }
    Ok(())
}

/// A bench team member: follows the bench's leader, then prints its state's digest.
pub fn member(network: &str, epochs: usize, sac: bool, net_args: NetArgs, id: &str) -> Result<()> {
    let session = net::open_retrying(&net_args)?;
    let _token =
        session.liveliness().declare_token(keys::learner_alive(id)).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    let (mut algo, model) = learner_of(network, epochs, sac)?;
    // A member starts at the hyperparameters' rate and version 0: it must take the leader's
    // state over, and step at the rate each plan carries.
    algo.set_lr(Hyperparameters::default().lr);
    let os = model.obs_size();
    let worlds = [WORLD.to_string()];
    let actions = protocol::Actions::of(&metadata(network, sac)?.action_space);
    let view = JobView { job_id: JOB, obs_size: os, worlds: &worlds, actions };
    let mut updates = 0u64;
    let drops = Arc::new(DropCounters::default());
    let follower = Follower { session: &session, me: id, memory_limit: u64::MAX, drops };
    let end = follow(follower, &view, algo.as_mut(), &mut || true, &mut |_, _| updates += 1)?;
    if end != FollowEnd::LeaderGone {
        bail!("the member stopped: {end:?}");
    }
    println!("member {id}: {updates} updates, digest {:016x} version {}", digest(algo.as_ref()), algo.version());
    Ok(())
}
