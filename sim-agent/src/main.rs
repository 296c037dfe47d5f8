//! The `sim-agent` binary: `serve` (the network role: takes world assignments from a
//! coordinator and streams experience to a learner over Zenoh), `bench` (the simulator's
//! speed), `car` (the simulated physical car) and `handling` (the car's figures per surface).

/// mimalloc hands freed pages back to the system soon after they are freed (glibc's malloc
/// keeps them in its arenas): a long run's resident memory follows what it holds, not its
/// highest peak. `main` turns transparent huge pages off, which would make them resident again.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

mod gate;
mod hil;
mod serve;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use policy::Action;
use sim_agent::config::{ObservationKind, load_config};
use sim_agent::driver::PurePursuit;
use sim_agent::{EnvSpec, RewardFn, SimConfig, VecEnv};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tracks::{Direction, P2};

#[derive(Parser)]
#[command(name = "sim-agent", version, about = "Paddock's simulator agent", after_help = protocol::exit::TABLE)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Serve a coordinator: run the assigned world with the latest policy, stream experience.
    Serve(ServeCli),
    /// Join a Paddock cluster with a token (`coordinator token create --role agent`): make
    /// this machine's key, check the coordinator's CA against the token, write the
    /// credentials folder (`--certs DIR`); then `serve --certs DIR` (or `--service`).
    Join(protocol::join::JoinCli),
    /// Measure env steps/s (1 and 2 threads, built-in and Python reward) and query cost.
    Bench(BenchArgs),
    /// Play the physical car for `deploy`: camera frames out in the car's layout at 15 Hz,
    /// servo commands in, DeepRacer's evaluation rules (hardware in the loop, no car).
    Car(hil::CarArgs),
    /// Measure the car on every surface (top speed, acceleration, stopping distance, turning
    /// radius at full lock, roll and pitch) beside the simple models; prints Markdown.
    Handling {
        /// Simulator configuration file (its `[car]` section is measured).
        #[arg(long)]
        config: Option<PathBuf>,
    },
}

#[derive(clap::Args)]
struct ServeCli {
    #[command(flatten)]
    net: protocol::net::NetCli,
    /// Environments to run.
    #[arg(long, default_value_t = 16)]
    envs: usize,
    /// Threads for the environments (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Agent id (default: HOST-PID).
    #[arg(long)]
    id: Option<String>,
    /// Where the policy acts over the environments: auto (today the CPU: on the GPU
    /// measured, acting there was slower), cpu or gpu (the GPU, a software one included, or an
    /// error).
    #[arg(long, default_value = "auto")]
    device: gpu::DeviceChoice,
    /// A public key whose policies this agent runs (the learner's `.pub`, from `coordinator
    /// keys new` or the run folder's `signing.pub`); repeatable. With `--certs DIR` its
    /// `models.pub` is trusted too. With neither, each job's first signer is pinned.
    #[arg(long, value_name = "FILE")]
    trust: Vec<PathBuf>,
}

#[derive(clap::Args)]
struct BenchArgs {
    /// World to drive.
    #[arg(long, default_value = "reinvent_base")]
    world: String,
    /// Environments in the vector.
    #[arg(long, default_value_t = 64)]
    envs: usize,
    /// Seconds to measure each configuration.
    #[arg(long, default_value_t = 5.0)]
    seconds: f64,
    /// Python reward file for the Python rows.
    #[arg(long, default_value = "examples/rewards/follow_center_line.py")]
    python_reward: PathBuf,
    /// Thread counts to measure.
    #[arg(long, value_delimiter = ',', default_value = "1,2")]
    threads: Vec<usize>,
    /// Simulator configuration file (TOML).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Override a configuration key (`key=value`, repeatable).
    #[arg(long = "set")]
    sets: Vec<String>,
}

fn handling(config: Option<PathBuf>) -> Result<()> {
    let cfg: SimConfig = load_config(config.as_deref(), &[]).context("loading the simulator configuration")?;
    print!("{}", sim_agent::handling::markdown(&cfg.car));
    Ok(())
}

fn main() {
    let cli = Cli::parse();
    if matches!(cli.command, Command::Serve(_)) {
        // Acting frees and takes again the same buffers every few milliseconds (handed back at
        // once, inference over 8 environments took 1.65x as long); what an idle agent freed goes back.
        protocol::secure::purge_freed_memory_after(100);
    }
    protocol::secure::init_process("info");
    // The camera on a headless NVIDIA server (sim_agent::icd), before any thread starts.
    sim_agent::icd::headless_nvidia();
    let result = match cli.command {
        Command::Bench(args) => bench(args),
        Command::Join(j) => protocol::join::run_cli(protocol::secure::Role::Agent, j).map_err(anyhow::Error::from),
        Command::Car(args) => hil::run(args),
        Command::Handling { config } => handling(config),
        Command::Serve(a) => gate::trust(&a.trust, a.net.certs.as_deref()).and_then(|trust| {
            serve::serve(serve::ServeArgs {
                net: protocol::net::NetArgs::from(a.net).as_role(protocol::secure::Role::Agent),
                envs: a.envs,
                id: a.id,
                threads: a
                    .threads
                    .unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)),
                device: a.device,
                trust,
            })
        }),
    };
    protocol::exit::exit(result.map(|()| protocol::exit::SUCCESS))
}

fn bench(args: BenchArgs) -> Result<()> {
    let cfg: SimConfig = load_config(args.config.as_deref(), &args.sets)?;
    let world = tracks::world(&args.world)?;
    let spec = EnvSpec::from_world(&world, Direction::Forward);
    println!(
        "# sim-agent bench: world {}, {} envs, {:.0} s per row, observation {:?}",
        args.world, args.envs, args.seconds, cfg.observation.kind
    );
    println!();
    println!("| reward | threads | env steps/s | vs 1 thread | episodes | mean progress at episode end |");
    println!("|---|---|---|---|---|---|");
    type MakeReward = Box<dyn Fn() -> Result<RewardFn>>;
    let rewards: Vec<(String, MakeReward)> = vec![
        ("built-in center_line".into(), Box::new(|| Ok(RewardFn::Builtin(sim_agent::BuiltinReward::CenterLine)))),
        (format!("python {}", args.python_reward.display()), {
            let p = args.python_reward.clone();
            Box::new(move || RewardFn::from_spec(&p.display().to_string()).context("loading the Python reward"))
        }),
    ];
    let cfg = Arc::new(cfg);
    for (name, make) in &rewards {
        let mut base = None;
        for &threads in &args.threads {
            let r = run_vec(&spec, &cfg, args.envs, threads, make()?, args.seconds)?;
            let ratio = base.map(|b: f64| format!("{:.2}×", r.steps_per_s / b)).unwrap_or_else(|| "1.00×".into());
            base.get_or_insert(r.steps_per_s);
            println!(
                "| {name} | {threads} | {:.0} | {ratio} | {} | {:.1} |",
                r.steps_per_s, r.episodes, r.mean_progress
            );
        }
    }
    println!();
    breakdown(&spec, &cfg, &args.python_reward, args.seconds.min(2.0))?;
    println!();
    query_bench(&world.track(Direction::Forward), args.seconds.min(2.0));
    println!();
    if let Err(e) = camera_bench(&world, &spec, &cfg, args.envs, args.seconds.min(3.0)) {
        println!("camera: not measured: {e:#}");
    }
    if cfg.observation.kind != ObservationKind::Lidar {
        let mut lidar_cfg = (*cfg).clone();
        lidar_cfg.observation.kind = ObservationKind::StateLidar;
        let r = run_vec(
            &spec,
            &Arc::new(lidar_cfg),
            args.envs,
            *args.threads.last().unwrap_or(&1),
            RewardFn::Builtin(sim_agent::BuiltinReward::CenterLine),
            args.seconds.min(2.0),
        )?;
        println!();
        println!(
            "state + {}-ray lidar, built-in reward, {} threads: {:.0} env steps/s",
            cfg.observation.lidar_rays,
            args.threads.last().unwrap_or(&1),
            r.steps_per_s
        );
    }
    Ok(())
}

struct RunResult {
    steps_per_s: f64,
    episodes: usize,
    mean_progress: f64,
}

fn run_vec(
    spec: &EnvSpec,
    cfg: &Arc<SimConfig>,
    n: usize,
    threads: usize,
    reward: RewardFn,
    seconds: f64,
) -> Result<RunResult> {
    let mut vec = VecEnv::new(vec![spec.clone(); n], cfg.clone(), 7, reward, threads)?;
    let driver = PurePursuit::default();
    let mut actions: Vec<Action> = vec.envs().iter().map(|e| driver.act(e)).collect();
    let bar = ProgressBar::new((seconds * 1000.0) as u64)
        .with_style(ProgressStyle::with_template("{msg} [{bar:30}] {elapsed}").expect("template"))
        .with_message(format!("{threads} thread(s)"));
    let (mut stepped, mut episodes, mut progress_sum) = (0u64, 0usize, 0.0);
    let mut in_env = Duration::ZERO;
    let wall = Instant::now();
    while wall.elapsed().as_secs_f64() < seconds {
        let t = Instant::now();
        let outcomes = vec.step(&actions)?;
        in_env += t.elapsed();
        for o in outcomes {
            if o.done {
                episodes += 1;
                progress_sum += o.progress;
            }
        }
        stepped += n as u64;
        for (a, e) in actions.iter_mut().zip(vec.envs()) {
            *a = driver.act(e);
        }
        bar.set_position(wall.elapsed().as_millis() as u64);
    }
    bar.finish_and_clear();
    Ok(RunResult {
        steps_per_s: stepped as f64 / in_env.as_secs_f64(),
        episodes,
        mean_progress: if episodes > 0 { progress_sum / episodes as f64 } else { f64::NAN },
    })
}

/// Rendered frames/s (batched) and camera env steps/s (physics + render + reward).
fn camera_bench(world: &tracks::World, spec: &EnvSpec, cfg: &Arc<SimConfig>, n: usize, seconds: f64) -> Result<()> {
    use sim_agent::camera::{Renderer, View};
    let mut r = Renderer::new()?;
    let track = world.track(Direction::Forward);
    let views: Vec<View<'_>> = (0..n)
        .map(|i| {
            let (p, h) = track.pose_at(track.length() * i as f64 / n as f64);
            View {
                track: &track,
                surface: world.surface,
                lighting: world.lighting,
                pose: [p.x, p.y, h],
                jitter: [0.0, 0.0],
                texture_seed: 0,
                objects: &[],
            }
        })
        .collect();
    r.render(&views, false);
    let t = Instant::now();
    let mut frames = 0usize;
    while t.elapsed().as_secs_f64() < seconds {
        std::hint::black_box(r.render(&views, false));
        frames += n;
    }
    let fps = frames as f64 / t.elapsed().as_secs_f64();
    let threads = std::thread::available_parallelism().map(|x| x.get()).unwrap_or(1);
    println!(
        "camera on {}: {fps:.0} frames/s rendering {n} views of 160x120 per batch (render + readback + luma)",
        r.adapter()
    );
    drop(r);
    // Camera env steps/s (physics + render + reward) for each race and the stereo pair, against
    // the time trial, in the same run.
    use sim_agent::race::{RaceConfig, RaceType};
    let oa = RaceConfig { race_type: RaceType::ObjectAvoidance, number_of_obstacles: 3, ..RaceConfig::default() };
    let h2b = RaceConfig {
        race_type: RaceType::HeadToBot,
        number_of_bot_cars: 2,
        bot_car_speed: 0.5,
        ..RaceConfig::default()
    };
    let sector = sim_agent::config::CameraLidar {
        sensor: sim_agent::config::LidarSensor::SectorLidar,
        sectors: 8,
        values: 1,
        clip: 0.5,
        first: false,
    };
    let mut base = 0.0;
    for (name, kind, race, lidar) in [
        ("time trial", ObservationKind::Camera, RaceConfig::default(), None),
        ("object avoidance, 3 boxes", ObservationKind::Camera, oa.clone(), None),
        ("head-to-bot, 2 bots", ObservationKind::Camera, h2b, None),
        ("stereo pair, time trial", ObservationKind::Stereo, RaceConfig::default(), None),
        ("camera + SECTOR_LIDAR, object avoidance, 3 boxes", ObservationKind::Camera, oa, Some(sector)),
    ] {
        let mut cam = (**cfg).clone();
        cam.observation.kind = kind;
        cam.observation.camera_lidar = lidar;
        cam.race = race;
        let reward = RewardFn::Builtin(sim_agent::BuiltinReward::CenterLine);
        let res = run_vec(spec, &Arc::new(cam), n, threads, reward, seconds)?;
        if base == 0.0 {
            base = res.steps_per_s;
        }
        println!(
            "camera env steps/s, {name}: {:.0} ({:.2}× the time trial; {threads} threads)",
            res.steps_per_s,
            res.steps_per_s / base
        );
    }
    Ok(())
}

/// Time `f` repeatedly for about `seconds`; nanoseconds per call.
fn per_call(seconds: f64, mut f: impl FnMut()) -> f64 {
    let t = Instant::now();
    let mut n = 0u64;
    while t.elapsed().as_secs_f64() < seconds {
        for _ in 0..256 {
            f();
        }
        n += 256;
    }
    t.elapsed().as_secs_f64() * 1e9 / n as f64
}

/// Where one env step's time goes, on one core.
fn breakdown(spec: &EnvSpec, cfg: &Arc<SimConfig>, python: &std::path::Path, seconds: f64) -> Result<()> {
    use sim_agent::car::Car;
    use sim_agent::params::{EpisodeClock, compute_params};
    let dt = 1.0 / cfg.control_hz / cfg.physics_substeps as f64;
    let mut car = Car::new(&cfg.car, spec.friction, dt);
    let (p, h) = spec.track.pose_at(0.0);
    car.reset(p.x, p.y, h);
    let mut k = 0u64;
    let physics = per_call(seconds, || {
        k += 1;
        let steer = if k % 200 < 100 { 0.2 } else { -0.2 };
        for _ in 0..cfg.physics_substeps {
            car.step(steer, 1.5);
        }
    });
    let mut env = sim_agent::Env::new(spec.clone(), cfg.clone(), sim_agent::Mode::Training, 1, 0.0)?;
    let driver = PurePursuit::default();
    for _ in 0..40 {
        env.step(driver.act(&env), sim_agent::BuiltinReward::CenterLine)?;
    }
    let pose = env.pose();
    let wheels = sim_agent::car::wheel_points_at(&cfg.car, pose.x, pose.y, pose.yaw);
    let clock = EpisodeClock { start_ndist: 0.0, prev_progress: 10.0, steps: 40, sim_time: 2.0 };
    let action = Action { steering_angle: 5.0, speed: 2.0 };
    let params_ns = per_call(seconds, || {
        std::hint::black_box(compute_params(env.track(), &pose, &wheels, action, &clock));
    });
    let mut obs = vec![0.0f32; sim_agent::obs::obs_dim(&cfg.observation)];
    let obs_ns = per_call(seconds, || sim_agent::obs::observe(&env, &mut obs));
    let params = compute_params(env.track(), &pose, &wheels, action, &clock);
    let builtin_ns = per_call(seconds, || {
        std::hint::black_box(sim_agent::BuiltinReward::CenterLine.reward(&params, env.line()).expect("reward"));
    });
    let mut py = sim_agent::python::PythonReward::load(python)?;
    let track = env.track().clone();
    let python_ns = per_call(seconds, || {
        std::hint::black_box(py.call(0, 1, &track, &params).expect("reward"));
    });
    let driver_ns = per_call(seconds, || {
        std::hint::black_box(driver.act(&env));
    });
    println!("where one env step's time goes (one core, ns per step):");
    println!();
    println!("| part | ns |");
    println!("|---|---|");
    println!("| physics ({} rapier substeps) | {physics:.0} |", cfg.physics_substeps);
    println!("| params + rules (track queries, 4 wheel tests) | {params_ns:.0} |");
    println!("| observation ({:?}) | {obs_ns:.0} |", cfg.observation.kind);
    println!("| built-in reward | {builtin_ns:.0} |");
    println!("| Python reward call (GIL taken per call here; batched in the vector env) | {python_ns:.0} |");
    println!("| pure-pursuit driver (not counted in env steps/s) | {driver_ns:.0} |");
    Ok(())
}

fn query_bench(track: &tracks::Track, seconds: f64) {
    // Points along a lap, jittered across the road: what a driving car asks for.
    let pts: Vec<P2> = (0..4096)
        .map(|i| {
            let (p, h) = track.pose_at(track.length() * i as f64 / 4096.0);
            let off = ((i * 7919) % 101) as f64 / 100.0 - 0.5;
            P2::new(p.x - off * 0.6 * h.sin(), p.y + off * 0.6 * h.cos())
        })
        .collect();
    let time = |f: &dyn Fn(P2) -> f64| {
        let t = Instant::now();
        let mut n = 0u64;
        let mut sink = 0.0;
        while t.elapsed().as_secs_f64() < seconds {
            for &p in &pts {
                sink += f(p);
            }
            n += pts.len() as u64;
        }
        std::hint::black_box(sink);
        t.elapsed().as_secs_f64() * 1e9 / n as f64
    };
    const WHEELS: [(f64, f64); 4] = [(-0.08, 0.08), (0.08, 0.08), (-0.08, -0.08), (0.08, -0.08)];
    let fast = time(&|p| {
        let on = WHEELS.iter().filter(|(dx, dy)| track.on_road(P2::new(p.x + dx, p.y + dy))).count();
        track.query(p).ndist + on as f64
    });
    let scan = time(&|p| {
        let on = WHEELS.iter().filter(|(dx, dy)| track.on_road_scan(P2::new(p.x + dx, p.y + dy))).count();
        track.query_scan(p).ndist + on as f64
    });
    println!(
        "track queries per step (projection, closest waypoints, width, left/right, 4 wheel road tests), one core:"
    );
    println!("grid {fast:.0} ns; full scan (reference) {scan:.0} ns; grid is {:.1}× faster", scan / fast);
}
