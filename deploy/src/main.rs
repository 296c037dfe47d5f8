//! `deploy`: the on-car agent, the Zenoh shell around [`deploy::Driver`].
//!
//! Threads: Zenoh's callbacks put the newest camera message in a one-frame mailbox (an older
//! one not yet driven is replaced and counted) and hand model publications to the loader; the
//! loader (a background thread, niceness 19) verifies each model and swaps it into the
//! [`ModelSlot`]; the drive loop answers every frame with a `ServoCtrlMsg` and runs the
//! watchdog between frames; once a second the car's status goes out beside its liveliness
//! token.

mod bench;

use anyhow::{Context, Result, bail};
use clap::Parser;
use deploy::{Driver, Follow, ModelSlot, Offer};
use policy::ModelParts;
use policy::car::{CarConfig, Layout};
use policy::signature::TrustedKeys;
use protocol::net::{self, NetCli, zenoh};
use protocol::ros::{self, CarKeys, Time};
use protocol::{CarAssign, CarControl, CarStatus, PROTOCOL_VERSION, PolicyUpdate, keys};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, Sender, channel};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use zenoh::Wait;

/// The on-car agent: drives the car with a job's published models, each verified first.
#[derive(Parser, Debug)]
#[command(version, args_conflicts_with_subcommands = true, after_help = protocol::exit::TABLE)]
struct Cli {
    #[command(subcommand)]
    command: Option<Sub>,
    /// The job whose models to drive (leave out with --model-dir to drive offline).
    #[arg(long)]
    job: Option<String>,
    #[command(flatten)]
    net: NetCli,
    /// Public keys (PEM, the learner's `.pub`) whose models the car accepts (repeatable). With
    /// `--certs DIR`, the cluster's `models.pub` there is trusted too.
    #[arg(long)]
    trust: Vec<PathBuf>,
    /// The car's configuration (default: built-in defaults, the same as deploy/car.toml).
    #[arg(long)]
    car: Option<PathBuf>,
    /// A model folder: every model taken is saved here, and without --job the car drives the
    /// model saved here (verified again), with no network. Or DeepRacer's model archive
    /// (NAME.tar.gz), driven offline if car.toml's trust_unsigned lists NAME.
    #[arg(long)]
    model_dir: Option<PathBuf>,
    /// Which models to drive: latest, best, or one version number.
    #[arg(long, default_value = "latest")]
    follow: Follow,
}

#[derive(clap::Subcommand, Debug)]
enum Sub {
    /// Per-frame latency on one core (frame preparation, inference) and a new model's way to
    /// the first frame it drives (decode, signature and checksum, load, swap).
    Bench {
        /// Seconds per measurement.
        #[arg(long, default_value_t = 5.0)]
        seconds: f64,
    },
    /// Join a Paddock cluster with a token (`coordinator token create --role car`): make
    /// this car's key, check the coordinator's CA against the token, write the credentials
    /// folder (`--certs DIR`), then drive with `deploy --certs DIR --job JOB`.
    Join(protocol::join::JoinCli),
}

fn main() {
    protocol::secure::init_process("info");
    let cli = Cli::parse();
    let result = match cli.command {
        Some(Sub::Bench { seconds }) => bench::run(seconds),
        Some(Sub::Join(j)) => protocol::join::run_cli(protocol::secure::Role::Car, j).map_err(anyhow::Error::from),
        None => run(cli),
    };
    protocol::exit::exit(result.map(|()| protocol::exit::SUCCESS))
}

/// The newest camera message not yet driven.
#[derive(Default)]
struct Mailbox {
    frame: Mutex<Option<(Vec<u8>, Instant)>>,
    ready: Condvar,
    replaced: AtomicU64,
}

impl Mailbox {
    fn put(&self, bytes: Vec<u8>) {
        let now = Instant::now();
        if let Ok(mut f) = self.frame.lock() {
            if f.replace((bytes, now)).is_some() {
                self.replaced.fetch_add(1, Ordering::Relaxed);
            }
            self.ready.notify_one();
        }
    }

    fn take(&self, timeout: Duration) -> Option<(Vec<u8>, Instant)> {
        let f = self.frame.lock().ok()?;
        let (mut f, _) = self.ready.wait_timeout_while(f, timeout, |f| f.is_none()).ok()?;
        f.take()
    }
}

fn run(cli: Cli) -> Result<()> {
    let archive = cli.model_dir.as_deref().filter(|d| d.is_file());
    let mut trusted = cli.trust.clone();
    trusted.extend(cli.net.certs.as_ref().map(|d| d.join(protocol::secure::MODEL_PUB_FILE)).filter(|p| p.exists()));
    if trusted.is_empty() && archive.is_none() {
        bail!(
            "give --trust FILE (the learner's public key) or --certs DIR holding models.pub: the car drives only models signed by a key it trusts"
        );
    }
    let car = match &cli.car {
        Some(p) => CarConfig::load(p)?,
        None => CarConfig::default(),
    };
    let trust = TrustedKeys::load(&trusted)?;
    let slot = Arc::new(ModelSlot::default());
    if let Some(a) = archive {
        if cli.job.is_some() {
            bail!(
                "{}: an archive is driven offline; leave out --job (a job's models are kept in a folder)",
                a.display()
            );
        }
        // DeepRacer's archive, imported here as `coordinator import` would.
        let origin = a.display().to_string();
        let f = policy::carpkg::read(a)?.to_folder(&origin, 0)?;
        let parts = ModelParts::new(&f.metadata, &f.model, &f.manifest, None);
        let name = policy::carpkg::car_model_name(a);
        match slot.offer_import(parts, &name, &car, &format!("archive {origin}")) {
            Offer::Taken(_) => tracing::info!(archive = %origin, model = %name, "driving DeepRacer's model"),
            Offer::Refused(why) => bail!("{origin}: {why}"),
            Offer::Skipped(_) => {}
        }
    } else if let Some(dir) = &cli.model_dir
        && dir.join("manifest.json").exists()
    {
        let parts = ModelParts::read(dir).with_context(|| format!("reading the saved model in {}", dir.display()))?;
        match slot.offer(parts, &trust, &car, &format!("folder {}", dir.display()), &Follow::Latest) {
            Offer::Taken(v) => tracing::info!(version = v, folder = %dir.display(), "driving the saved model"),
            Offer::Refused(why) if cli.job.is_none() => bail!("{}: {why}", dir.display()),
            _ => {}
        }
    }
    // With --connect alone the car waits for an organiser's assignment (the console's cars page).
    let waits = cli.job.is_none() && cli.model_dir.is_none() && !cli.net.connect.is_empty();
    if cli.job.is_none() && cli.model_dir.is_none() && !waits {
        bail!(
            "give --job (and --connect) to follow a job's models, --connect alone to wait for an assignment, or --model-dir to drive a saved model offline"
        );
    }
    if cli.job.is_none() && !waits && slot.current().is_none() {
        bail!("{}: no model saved there", cli.model_dir.as_ref().expect("checked").display());
    }
    let session =
        net::open_retrying(&cli.net.args(cli.job.is_some()).as_machine(protocol::secure::Role::Car, &car.id))?;
    let car_keys = CarKeys::new(&car.namespace);
    let layout = match car.layout {
        Layout::Community => ros::Layout::Community,
        Layout::Aws => ros::Layout::Aws,
    };
    let _token =
        session.liveliness().declare_token(keys::car_alive(&car.id)).wait().map_err(|e| anyhow::anyhow!("{e}"))?;

    // Frames in.
    let mailbox = Arc::new(Mailbox::default());
    let mb = mailbox.clone();
    let _frames = session
        .declare_subscriber(&car_keys.sensor)
        .callback(move |s| mb.put(s.payload().to_bytes().into_owned()))
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;

    // Models in, verified on the loader thread; the job followed changes with an assignment.
    let (model_tx, model_rx) = channel::<(Vec<u8>, &'static str)>();
    let following = Arc::new(Mutex::new(cli.job.clone().unwrap_or_default()));
    // One more at each assignment: a model of the job before it, checked while the car was
    // reassigned, does not drive.
    let generation = Arc::new(AtomicU64::new(0));
    let model_subs = Arc::new(Mutex::new(Vec::new()));
    if let Some(job) = &cli.job {
        *model_subs.lock().expect("subscriptions") = follow_job(&session, &car.id, job, &cli.follow, &model_tx)?;
    } else if waits {
        tracing::info!(car = %car.id, "waiting for an organiser to assign a model");
    }
    let (assign_tx, assign_rx) = channel::<CarAssign>();
    let id2 = car.id.clone();
    let _assign = session
        .declare_subscriber(keys::car_assign(&car.id))
        .callback(move |s| match protocol::decode::<CarAssign>(&s.payload().to_bytes()) {
            Ok(a) if a.car_id == id2 && keys::is_valid_name(&a.job_id) => {
                let _ = assign_tx.send(a);
            }
            Ok(a) => tracing::warn!(car = %id2, "dropped an assignment for car '{}', job '{}'", a.car_id, a.job_id),
            Err(e) => tracing::warn!(car = %id2, "dropped an assignment: {e}"),
        })
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    {
        let (session, car_id, following, subs, slot, tx, follow, generation) = (
            session.clone(),
            car.id.clone(),
            following.clone(),
            model_subs.clone(),
            slot.clone(),
            model_tx.clone(),
            cli.follow.clone(),
            generation.clone(),
        );
        std::thread::spawn(move || {
            while let Ok(a) = assign_rx.recv() {
                tracing::info!(car = %car_id, job = %a.job_id, "assigned a job's models: the current model stops driving until the new one is checked");
                *following.lock().expect("the job followed") = a.job_id.clone();
                generation.fetch_add(1, Ordering::SeqCst);
                slot.clear();
                match follow_job(&session, &car_id, &a.job_id, &follow, &tx) {
                    Ok(s) => *subs.lock().expect("subscriptions") = s,
                    Err(e) => tracing::error!(car = %car_id, "cannot follow job '{}': {e:#}", a.job_id),
                }
                if !a.model.is_empty() {
                    let _ = tx.send((a.model, "assigned"));
                }
            }
        });
    }
    drop(model_tx);
    let loader = {
        let (slot, car, dir, job, follow, generation) = (
            slot.clone(),
            car.clone(),
            cli.model_dir.clone(),
            following.clone(),
            cli.follow.clone(),
            generation.clone(),
        );
        std::thread::spawn(move || {
            if let Err(e) = deploy::driver::background_thread() {
                tracing::warn!("{e}; models load at the drive loop's priority");
            }
            load_models(model_rx, &slot, &trust, &car, dir.as_deref(), (&job, &generation), &follow)
        })
    };

    // The e-stop.
    let estop = Arc::new(AtomicBool::new(false));
    let (e2, id2) = (estop.clone(), car.id.clone());
    let _control = session
        .declare_subscriber(keys::car_control(&car.id))
        .callback(move |s| match protocol::decode::<CarControl>(&s.payload().to_bytes()) {
            Ok(c) if c.car_id == id2 => e2.store(c.estop, Ordering::Relaxed),
            Ok(c) => tracing::warn!(car = %id2, "dropped a control message for car '{}'", c.car_id),
            Err(e) => tracing::warn!(car = %id2, "dropped a control message: {e}"),
        })
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;

    let stop = Arc::new(AtomicBool::new(false));
    let s2 = stop.clone();
    ctrlc::set_handler(move || s2.store(true, Ordering::Relaxed)).context("installing the Ctrl-C handler")?;

    let servo_pub = session
        .declare_publisher(car_keys.servo.clone())
        .congestion_control(zenoh::qos::CongestionControl::Drop)
        .priority(zenoh::qos::Priority::RealTime)
        .express(true)
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let publish = |c: &deploy::Command, seq: u64| {
        let bytes = ros::encode_servo(c.servo, layout, now_stamp(), seq, &c.correlation);
        if let Err(e) = servo_pub.put(bytes).wait() {
            tracing::warn!("command not sent: {e}");
        }
    };
    tracing::info!(car = %car.id, frames = %car_keys.sensor, commands = %car_keys.servo, "car agent up");
    let mut driver = Driver::new(car.clone(), slot.clone());
    let mut seq = 0u64;
    let mut last_status = Instant::now();
    let mut bad_logged: Option<Instant> = None;
    while !stop.load(Ordering::Relaxed) {
        driver.set_estop(estop.load(Ordering::Relaxed));
        if let Some((bytes, arrived)) = mailbox.take(Duration::from_millis(5)) {
            match driver.frame(&bytes, arrived) {
                Ok(c) => {
                    seq += 1;
                    publish(&c, seq);
                    driver.record_frame_to_command(arrived.elapsed());
                }
                Err(e) => {
                    // At most one line a second for a stream of bad frames.
                    if bad_logged.is_none_or(|t| t.elapsed() >= Duration::from_secs(1)) {
                        tracing::warn!(car = %car.id, "frame dropped: {e}");
                        bad_logged = Some(Instant::now());
                    }
                }
            }
        }
        if let Some(c) = driver.tick(Instant::now()) {
            seq += 1;
            publish(&c, seq);
        }
        if last_status.elapsed() >= Duration::from_secs(1) {
            last_status = Instant::now();
            let job = following.lock().expect("the job followed").clone();
            let status = status(&car, &cli, &job, &driver, &slot, mailbox.replaced.load(Ordering::Relaxed));
            let _ = net::put(&session, &keys::car_status(&car.id), &status);
        }
    }
    // Leave the car stopped.
    publish(&deploy::Command { servo: ros::Servo::default(), correlation: Default::default(), version: None }, seq + 1);
    tracing::info!(car = %car.id, "stopped; throttle 0 sent");
    drop(model_subs);
    drop(loader);
    Ok(())
}

fn now_stamp() -> Time {
    Time::from_secs_f64(SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_secs_f64()).unwrap_or(0.0))
}

/// Subscribe to `job`'s models (latest or best, as `follow` says) and ask for the current one.
fn follow_job(
    session: &zenoh::Session,
    car: &str,
    job: &str,
    follow: &Follow,
    model_tx: &Sender<(Vec<u8>, &'static str)>,
) -> Result<Vec<zenoh::pubsub::Subscriber<()>>> {
    let (key, source) = match follow {
        Follow::Best => (keys::best(job), "best"),
        _ => (keys::policy(job), "latest"),
    };
    let tx = model_tx.clone();
    let sub = session
        .declare_subscriber(&key)
        .callback(move |s| {
            let _ = tx.send((s.payload().to_bytes().into_owned(), source));
        })
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    // A car that starts late gets the current model at once.
    let (tx, session2, key2) = (model_tx.clone(), session.clone(), key.clone());
    std::thread::spawn(move || ask_current(&session2, &key2, source, &tx));
    tracing::info!(car, job, %follow, key, "following the job's models");
    Ok(vec![sub])
}

/// Ask the learner's queryable for its current model, a few times until it answers.
fn ask_current(session: &zenoh::Session, key: &str, source: &'static str, tx: &Sender<(Vec<u8>, &'static str)>) {
    for _ in 0..10 {
        let Ok(replies) = session.get(key).timeout(Duration::from_secs(3)).wait() else { return };
        let mut got = false;
        while let Ok(r) = replies.recv() {
            if let Ok(s) = r.result() {
                got = tx.send((s.payload().to_bytes().into_owned(), source)).is_ok();
            }
        }
        if got {
            return;
        }
        std::thread::sleep(Duration::from_secs(1));
    }
}

fn load_models(
    rx: Receiver<(Vec<u8>, &'static str)>,
    slot: &ModelSlot,
    trust: &TrustedKeys,
    car: &CarConfig,
    dir: Option<&Path>,
    (job, generation): (&Mutex<String>, &AtomicU64),
    follow: &Follow,
) {
    while let Ok((bytes, source)) = rx.recv() {
        let seen = generation.load(Ordering::SeqCst);
        let job = job.lock().map(|j| j.clone()).unwrap_or_default();
        let u = match protocol::decode::<PolicyUpdate>(&bytes) {
            Ok(u) if u.job_id == job => u,
            Ok(u) => {
                tracing::warn!("dropped a model for job '{}' (following '{job}')", u.job_id);
                continue;
            }
            Err(e) => {
                tracing::warn!("dropped a model message: {e}");
                continue;
            }
        };
        // Already driving this version: nothing to check.
        if slot.current().is_some_and(|m| m.version == u.policy_version && m.source == source) {
            continue;
        }
        let parts = match protocol::exchange::policy_parts(&u) {
            Ok(p) => p,
            Err(e) => {
                tracing::warn!("dropped a model message: {e}");
                continue;
            }
        };
        // An assigned model drives whatever its version; the job's own follow as asked.
        let follow = if source == "assigned" { &Follow::Best } else { follow };
        let offered = slot.offer(parts, trust, car, source, follow);
        if matches!(offered, Offer::Taken(_)) && generation.load(Ordering::SeqCst) != seen {
            tracing::info!(job, "dropped a model of the job followed before the assignment");
            slot.clear();
            continue;
        }
        if let Offer::Taken(v) = offered
            && let Some(dir) = dir
            && let Some(m) = slot.current()
        {
            match m.parts.write(dir) {
                Ok(()) => tracing::info!(version = v, folder = %dir.display(), "saved for offline driving"),
                Err(e) => tracing::warn!("could not save the model: {e}"),
            }
        }
    }
}

fn status(car: &CarConfig, cli: &Cli, job: &str, d: &Driver, slot: &ModelSlot, replaced: u64) -> CarStatus {
    let f = d.figures();
    let m = slot.current();
    let (refused, last_refusal) = slot.refusals();
    CarStatus {
        protocol_version: PROTOCOL_VERSION,
        car_id: car.id.clone(),
        job_id: job.to_string(),
        follow: cli.follow.to_string(),
        has_model: m.is_some(),
        policy_version: m.as_ref().map(|m| m.version).unwrap_or(0),
        model_source: m.as_ref().map(|m| m.source.clone()).unwrap_or_default(),
        model_key: m.as_ref().map(|m| m.key.clone()).unwrap_or_default(),
        frames_per_s: f.frames_per_s,
        inference_ms_p50: f.inference_ms.0,
        inference_ms_p99: f.inference_ms.1,
        frame_to_command_ms_p50: f.frame_to_command_ms.0,
        frame_to_command_ms_p99: f.frame_to_command_ms.1,
        refused,
        last_refusal,
        watchdog: d.state().name().into(),
        frames: f.frames,
        commands: f.commands,
        swaps: slot.swaps(),
        bad_frames: f.bad_frames,
        skipped_frames: replaced,
    }
}
