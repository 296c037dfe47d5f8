//! `learner bench --learners N`: whole PPO updates (batch, forward, backward, all-reduce and
//! Adam) shared by N learner processes of one thread each, a team over Zenoh on loopback,
//! against one learner of one thread making the same updates in the same run. With
//! `--check` it also replays the team's updates on one learner and fails unless the weights
//! agree to float rounding, and unless every member ends with the leader's weights bit for bit.

use crate::bench_metadata;
use crate::team::{FollowEnd, TeamLead, follow};
use anyhow::{Context, Result, bail};
use faer::Par;
use learner::run::Team;
use learner::{Hyperparameters, Ppo};
use policy::{ActorCritic, Trajectory};
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

fn model_of(network: &str, epochs: usize) -> Result<(ActorCritic, Hyperparameters)> {
    let (_, _, meta) = bench_metadata(network)?;
    let model = ActorCritic::new(&meta, 27, &mut ChaCha8Rng::seed_from_u64(1));
    if epochs == 0 {
        bail!("--epochs: expected at least 1");
    }
    // Every epoch of every update runs (no `target_kl` stop): the rate counts them all.
    let hyper = Hyperparameters { num_epochs: epochs, batch_size: 64, target_kl: None, ..Hyperparameters::default() };
    Ok((model, hyper))
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

fn digest(ppo: &Ppo) -> u64 {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    ppo.version.hash(&mut h);
    for x in ppo.model.pi.params.iter().chain(&ppo.model.v.params) {
        x.to_bits().hash(&mut h);
    }
    h.finish()
}

fn free_port() -> Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
}

/// Updates for at least `seconds` (and at least two); sample-gradients per second (every
/// sample of an update once per epoch).
fn rate(seconds: f64, epochs: usize, mut update: impl FnMut() -> Result<()>) -> Result<(f64, usize)> {
    let t = Instant::now();
    let mut k = 0;
    while t.elapsed().as_secs_f64() < seconds || k < 2 {
        update()?;
        k += 1;
    }
    Ok(((k * EPISODES * STEPS * epochs) as f64 / t.elapsed().as_secs_f64(), k))
}

/// The bench's leader: rows for 1 learner and for a team of `learners`.
pub fn run(network: &str, seconds: f64, learners: usize, epochs: usize, check: bool) -> Result<()> {
    if check && epochs > 3 {
        bail!(
            "--check compares the team with one learner after about 24 minibatch steps, where rounding has not yet grown: give --epochs 3 or fewer (this run: {epochs})"
        );
    }
    let (model, hyper) = model_of(network, epochs)?;
    let camera = !network.eq_ignore_ascii_case("MLP");
    let trajs = episodes(&model, camera, 2);
    let os = model.obs_size();

    let mut alone = Ppo::new(model.clone(), hyper.clone(), 0, 7, Par::Seq);
    alone.update(&trajs)?;
    let (one, _) = rate(seconds, epochs, || {
        alone.update(&trajs)?;
        Ok(())
    })?;

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
    let mut ppo = Ppo::new(model.clone(), hyper.clone(), 0, 7, Par::Seq);
    // As a job's `lr_schedule` does: the leader's rate is not the hyperparameters'. The
    // members start from the hyperparameters' and must step with the rate each plan carries.
    ppo.set_lr(hyper.lr * 0.5);
    let mut replay = ppo.clone();
    let start = ppo.clone();
    // The first update carries the state to the members: not timed.
    let t0 = Instant::now();
    lead.update(&mut ppo, &trajs)?;
    let first_s = t0.elapsed().as_secs_f64();
    // Rounding differences grow with every step of a chaotic optimisation: the comparison
    // with one learner is made after about 24 minibatch steps (at least one update).
    let checked = (3 / epochs).max(1);
    let mut against_one = None;
    if check {
        for _ in 1..checked {
            lead.update(&mut ppo, &trajs)?;
        }
        for _ in 0..checked {
            replay.update(&trajs)?;
        }
        // How far the team is from one learner, against how far the updates moved the
        // weights. Adam divides every gradient by its running scale, so for weights whose
        // gradients are nearly zero rounding differences become whole steps: a few per cent
        // of the movement for the camera network after 24 steps (1e-6 for the MLP); a lost
        // or doubled share changes the direction of every step, tens of per cent.
        let flat = |p: &Ppo| p.model.pi.params.iter().chain(&p.model.v.params).copied().collect::<Vec<f32>>();
        let (start, one, team) = (flat(&start), flat(&replay), flat(&ppo));
        let norm = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| ((x - y) as f64).powi(2)).sum::<f64>().sqrt();
        let (apart, moved) = (norm(&team, &one), norm(&one, &start));
        let ok = moved > 0.0 && apart <= 5e-2 * moved && replay.version == ppo.version;
        against_one = Some((apart, moved, ok));
    }
    let (team, timed) = rate(seconds, epochs, || {
        if let Err(why) = lead.update(&mut ppo, &trajs) {
            bail!("the team's update was refused during the bench: {why}");
        }
        if lead.failures > 0 {
            bail!("the team failed during the bench ({} failures)", lead.failures);
        }
        Ok(())
    })?;
    let made = timed + if check { checked } else { 1 };
    if lead.team_updates != made as u64 {
        bail!("{} of {made} updates were made by the team", lead.team_updates);
    }
    // The leader goes: the members print their weights' digest and end.
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
    println!(
        "# learner bench: whole updates ({EPISODES} × {STEPS} samples, minibatch 64, {epochs} epoch(s) an update), {network}"
    );
    println!();
    println!("| measurement | sample-gradients/s | ratio to 1 × 1 |");
    println!("|---|---|---|");
    println!("| 1 learner × 1 thread, whole updates | {one:.0} | 1.00 |");
    println!(
        "| {learners} learner processes × 1 thread, a team over Zenoh on loopback | {team:.0} | {:.2} |",
        team / one
    );
    println!("(the team's first update, which carries the weights and optimiser state to the members: {first_s:.2} s)");

    if let Some((apart, moved, ok_one)) = against_one {
        println!(
            "check: after {checked} updates the team's weights are {apart:.3e} from one learner's, which moved {moved:.3e} from the start ({:.2e} of it)",
            apart / moved.max(f64::MIN_POSITIVE)
        );
        let want = format!("digest {:016x} version {}", digest(&ppo), ppo.version);
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

/// A bench team member: follows the bench's leader, then prints its weights' digest.
pub fn member(network: &str, epochs: usize, net_args: NetArgs, id: &str) -> Result<()> {
    let session = net::open_retrying(&net_args)?;
    let _token =
        session.liveliness().declare_token(keys::learner_alive(id)).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    let (model, hyper) = model_of(network, epochs)?;
    let os = model.obs_size();
    let mut ppo = Ppo::new(model, hyper, 0, 0, Par::Seq);
    let worlds = [WORLD.to_string()];
    let actions = protocol::Actions::of(&bench_metadata(network)?.2.action_space);
    let view = JobView { job_id: JOB, obs_size: os, worlds: &worlds, actions };
    let mut updates = 0u64;
    let end = follow(&session, id, &view, &mut ppo, Arc::new(DropCounters::default()), &mut || true, &mut |_, _| {
        updates += 1
    })?;
    if end != FollowEnd::LeaderGone {
        bail!("the member stopped: {end:?}");
    }
    println!("member {id}: {updates} updates, digest {:016x} version {}", digest(&ppo), ppo.version);
    Ok(())
}
