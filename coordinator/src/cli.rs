//! The command line, as clap types. Subcommand and flag names are part of the interface.

use clap::{Args, Parser, Subcommand};
use sim_agent::SimConfig;
use sim_agent::race::{RaceConfig, RaceType};
use std::path::{Path, PathBuf};

/// Paddock: train DeepRacer-style cars on your own machines.
#[derive(Parser)]
#[command(name = "coordinator", version, about, after_help = protocol::exit::TABLE)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand)]
pub enum Command {
    /// The built-in worlds and your own track files.
    Tracks {
        #[command(subcommand)]
        command: TracksCommand,
    },
    /// Reward functions.
    Reward {
        #[command(subcommand)]
        command: RewardCommand,
    },
    /// Drive laps with the scripted pure-pursuit driver and print each lap.
    Drive(DriveArgs),
    /// Train a model with PPO in this process.
    Train(TrainArgs),
    /// Run evaluation trials with a model's most likely actions.
    Evaluate(EvaluateArgs),
    /// Start a new run from a model's weights (transfer learning).
    Clone(CloneArgs),
    /// Race models on a world under DeepRacer's race rules: a leaderboard (best lap, mean,
    /// off-tracks, crashes) and a page with each model's fastest lap drawn on the track,
    /// coloured by speed, and its camera frames.
    Race(RaceCmdArgs),
    /// Keep jobs, watch agents, assign worlds, enforce stop conditions (the coordinator role).
    Serve(ServeCli),
    /// The web console: DeepRacer's racer workflow in a browser. On one machine it starts a
    /// coordinator, a learner and sim agents and serves on http://127.0.0.1:8100 (the address
    /// it prints carries its token). Runs the `console` binary: `console --help` lists its flags.
    #[command(disable_help_flag = true)]
    Console {
        /// The console's flags (`--agents N`, `--listen ADDR`, `--data DIR`, …).
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// The console's users (admin, facilitator, racer): `users add NAME --role ROLE
    /// [--password-file F] --data DIR`, `invite`, `role`, `quota`, `remove`, `list`. Runs
    /// `console users`: `console users --help` lists its flags.
    #[command(disable_help_flag = true)]
    Users {
        /// The subcommand and its flags.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Job control: start, list, status, stop, logs.
    Job {
        #[command(subcommand)]
        command: JobCommand,
    },
    /// Alive sim agents, their hosts and worlds.
    Agents {
        #[command(flatten)]
        net: NetCli,
    },
    /// One machine, one command: coordinator, learner and sim agents on loopback, one job.
    Up(UpArgs),
    /// Charts (SVG and PNG) and an HTML page of a run folder: training graph, evaluations,
    /// racing line, reward along the track, actions, hyperparameters.
    Report {
        /// The run folder (`train --out`, or `up`'s `<out>/run`).
        run: PathBuf,
        /// Where the report goes (default: RUN/report).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Render the car's camera view (160x120) to a PNG; --grid for several worlds side by side.
    Render(RenderArgs),
    /// Write a model for a car, another runtime or DeepRacer: `export MODEL_DIR --car
    /// NAME.tar.gz` (DeepRacer's archive, for a car's console or USB stick), `--onnx FILE`,
    /// `--virtual virtualmodel-NAME.tar.gz` or `--virtual-dir DIR` (the whole model, both
    /// networks, for DeepRacer on AWS's import page and deepracer-for-cloud).
    #[command(group(clap::ArgGroup::new("format").required(true).multiple(true).args(["car", "onnx", "virtual", "virtual_dir"])))]
    Export {
        /// The model folder.
        model: PathBuf,
        /// Write DeepRacer's model archive here: `agent/model.pb` (a frozen TensorFlow graph
        /// with DeepRacer's node names) and `model_metadata.json`. A car names the model after
        /// the file, up to its first dot.
        #[arg(long)]
        car: Option<PathBuf>,
        /// Write ONNX here (input `observation` [N,120,160,1] NHWC 0–255; outputs `logits`
        /// and, for discrete actions, `probabilities`).
        #[arg(long)]
        onnx: Option<PathBuf>,
        /// Write DeepRacer on AWS's model archive here (what its export gives and, unpacked,
        /// its import page takes): rl_coach's checkpoint of every network, the frozen policy,
        /// the metadata, reward function, hyperparameters, training parameters and metrics.
        #[arg(long)]
        r#virtual: Option<PathBuf>,
        /// Write the same as a folder (DRoA's import page; deepracer-for-cloud's model prefix).
        #[arg(long)]
        virtual_dir: Option<PathBuf>,
        #[command(flatten)]
        deepracer: VirtualArgs,
    },
    /// Bring a DeepRacer model into Paddock: its archive (`.tar.gz`, as a car or DeepRacer on
    /// AWS takes it) or a bare `model.pb`, into a model folder that evaluate, drive, deploy,
    /// export and clone take.
    Import(ImportArgs),
    /// Signing keys: `keys new NAME` writes NAME.key (secret, for `--signing-key`) and NAME.pub
    /// (for a car's `--trust`).
    Keys {
        #[command(subcommand)]
        command: KeysCommand,
    },
    /// The cluster's TLS credentials: `certs new DIR` writes a CA and one certificate per role
    /// (coordinator, learner, agent, car, operator) for every role's `--certs DIR`; `issue`
    /// gives a machine its own, `revoke` withdraws any, `list` shows them.
    Certs {
        #[command(subcommand)]
        command: CertsCommand,
    },
    /// Join tokens: `token create --role agent` prints a token a machine joins the cluster
    /// with in one command (`sim-agent join TOKEN --certs DIR`); `list`, `revoke`.
    Token {
        #[command(subcommand)]
        command: TokenCommand,
    },
    /// Service units: `service print agent` writes a hardened systemd unit for a role.
    Service {
        #[command(subcommand)]
        command: ServiceCommand,
    },
    /// The cars (`deploy`) on the network: model, frames/s, latencies, refusals, watchdog;
    /// `--estop CAR` holds a car at throttle 0 until `--release CAR`.
    Cars(CarsArgs),
    /// Benchmarks of the cluster: `cluster` (env steps/s vs one process), `publish` (model latency).
    Bench {
        #[command(subcommand)]
        command: BenchCommand,
    },
}

#[derive(Subcommand)]
pub enum CertsCommand {
    /// Write ca.pem, ca.key and <role>.pem/<role>.key for every role into DIR. Copy ca.pem and
    /// a role's two files to each machine that runs it; keep ca.key off the cluster.
    New {
        /// The folder (created if missing).
        dir: PathBuf,
        /// Replace credentials already there.
        #[arg(long)]
        force: bool,
        #[command(flatten)]
        slots: SlotArgs,
    },
    /// How many machines of each role may join with a token (DIR/ids.toml's slots). Every
    /// node's access rules cover the slots from its start; after growing them give every node
    /// the new ids.toml and restart it.
    Slots {
        /// The credentials folder.
        dir: PathBuf,
        #[command(flatten)]
        slots: SlotCounts,
    },
    /// Give machines certificates of their own: DIR/<role>-<id>.pem and .key, common name
    /// paddock-<role>.<id>, bound by the access rules to that id (agent lab-1's certificate
    /// cannot send as lab-2), and the ids added to DIR/ids.toml. Copy ca.pem, ids.toml and the
    /// machine's two files to it; give every node the new ids.toml and restart those that
    /// should hear the new machine (access rules are read when a node joins). Role-wide
    /// certificates keep working, each able to speak for any id of its role: enough for a
    /// small cluster on a network you trust. `certs issue DIR console NAME` instead writes the
    /// console's web certificate for the host name or address NAME (DIR/console-NAME.pem and
    /// .key, for the console's --tls-cert and --tls-key).
    Issue {
        /// The credentials folder (with ca.pem and ca.key).
        dir: PathBuf,
        /// agent, learner, car, operator or coordinator; or console (its web certificate).
        role: String,
        /// The machines' ids (an agent's or learner's --id, a car's id; the console's host names
        /// or addresses).
        #[arg(required = true)]
        ids: Vec<String>,
        /// Days the certificates are valid.
        #[arg(long, default_value_t = 3650)]
        days: u32,
    },
    /// Revoke certificates: add them to the CA's revocation list DIR/crl.pem. A running
    /// coordinator given DIR hands the list to every node within seconds; each then refuses
    /// those certificates and closes the links it holds to them.
    Revoke {
        /// The credentials folder (with ca.pem and ca.key).
        dir: PathBuf,
        /// A certificate's name (agent-lab-1, or agent for the role-wide one) or a machine's id.
        #[arg(required = true)]
        names: Vec<String>,
    },
    /// Every certificate in DIR: its common name, expiry, and whether it is revoked.
    List {
        /// The credentials folder.
        dir: PathBuf,
    },
}

/// The slots `certs new` makes.
#[derive(Args, Clone, Debug)]
pub struct SlotArgs {
    /// Agents that may join with a token.
    #[arg(long = "agent-slots", default_value_t = 64)]
    pub agent: u32,
    /// Learners that may join with a token.
    #[arg(long = "learner-slots", default_value_t = 8)]
    pub learner: u32,
    /// Cars that may join with a token.
    #[arg(long = "car-slots", default_value_t = 8)]
    pub car: u32,
}

impl SlotArgs {
    /// As the roster takes them.
    pub fn list(&self) -> Vec<(protocol::secure::Role, u32)> {
        use protocol::secure::Role;
        vec![(Role::Agent, self.agent), (Role::Learner, self.learner), (Role::Car, self.car)]
    }
}

/// New slot counts (`certs slots`): only the roles given change.
#[derive(Args, Clone, Debug)]
#[group(required = true, multiple = true)]
pub struct SlotCounts {
    /// Agent slots.
    #[arg(long)]
    pub agent: Option<u32>,
    /// Learner slots.
    #[arg(long)]
    pub learner: Option<u32>,
    /// Car slots.
    #[arg(long)]
    pub car: Option<u32>,
}

impl SlotCounts {
    /// The roles given, with their counts.
    pub fn list(&self) -> Vec<(protocol::secure::Role, u32)> {
        use protocol::secure::Role;
        [(Role::Agent, self.agent), (Role::Learner, self.learner), (Role::Car, self.car)]
            .into_iter()
            .filter_map(|(r, n)| n.map(|n| (r, n)))
            .collect()
    }
}

/// `coordinator token …`: join tokens, asked of a running coordinator as an operator.
#[derive(Subcommand)]
pub enum TokenCommand {
    /// Make a token a machine joins with (`sim-agent join TOKEN`, `learner join`, `deploy
    /// join`): single-use and short-lived by default; it carries the CA's hash and the
    /// coordinator's join door. Only a hash of its secret is kept.
    Create {
        /// The role the machine joins as: agent, learner or car.
        #[arg(long)]
        role: String,
        /// How long the token may be used (1h, 30m, 2d; at most 7 days).
        #[arg(long, default_value = "1h", value_parser = humantime::parse_duration)]
        ttl: std::time::Duration,
        /// How many machines may join with it.
        #[arg(long, default_value_t = 1)]
        uses: u32,
        /// The id to join as (a slot, slot-N, or an id in ids.toml); by default the next free slot.
        #[arg(long)]
        name: Option<String>,
        /// How long the certificates it gets are valid (365d, 12h, …).
        #[arg(long, default_value = "365d", value_parser = humantime::parse_duration)]
        cert_valid: std::time::Duration,
        /// The join door's HOST:PORT to write in the token (by default the door's own address
        /// when it listens on one; none when it listens on every interface: the machine then
        /// finds it by scouting).
        #[arg(long)]
        address: Option<String>,
        #[command(flatten)]
        net: NetCli,
    },
    /// Every token: role, uses, expiry, state, the machines that joined with it; and the joins
    /// granted and refused since the coordinator started, by reason.
    List {
        #[command(flatten)]
        net: NetCli,
    },
    /// Make a token unusable.
    Revoke {
        /// The token's id (8 hex digits, the second part of its text).
        id: String,
        #[command(flatten)]
        net: NetCli,
    },
}

#[derive(Subcommand)]
pub enum ServiceCommand {
    /// Print a systemd unit that runs ROLE (agent, learner, coordinator or car) as a service:
    /// restarted on failure (not on a usage error), a dynamic user, a state folder, the file
    /// system read-only elsewhere, no new privileges, a memory ceiling.
    Print {
        /// agent, learner, coordinator or car.
        role: String,
        /// The binary's path (by default where this one's sibling is installed).
        #[arg(long)]
        bin: Option<PathBuf>,
        /// The memory ceiling (systemd's MemoryMax).
        #[arg(long, default_value = "8G")]
        memory_max: String,
        /// Arguments after `serve` (e.g. --connect tls/10.0.0.1:7447).
        #[arg(last = true)]
        args: Vec<String>,
    },
}

#[derive(Subcommand)]
pub enum KeysCommand {
    /// Write a new ed25519 key pair: NAME.key (PKCS#8 PEM, owner-only) and NAME.pub.
    New {
        /// The pair's name (a path without extension: `keys/learner`).
        name: PathBuf,
    },
}

#[derive(Args)]
pub struct CarsArgs {
    /// Hold this car at throttle 0 (its e-stop) until released.
    #[arg(long, conflicts_with = "release")]
    pub estop: Option<String>,
    /// Release this car's e-stop.
    #[arg(long)]
    pub release: Option<String>,
    /// Print JSON lines.
    #[arg(long)]
    pub json: bool,
    /// Seconds to listen for the cars' status.
    #[arg(long, default_value_t = 2.0)]
    pub seconds: f64,
    #[command(flatten)]
    pub net: NetCli,
}

#[derive(Subcommand)]
pub enum BenchCommand {
    /// DeepRacer's model archive per network: export (graph and archive) and import (unpack,
    /// read, check), against writing and reading the same model's folder (safetensors).
    ModelFiles {
        /// Measurements per figure (the median is printed).
        #[arg(long, default_value_t = 5)]
        repeats: usize,
    },
    /// Samples trained on per second end to end: single process vs `up` with 1, 2, 4 agents.
    Cluster {
        /// Seconds per row.
        #[arg(long, default_value_t = 30.0)]
        seconds: f64,
        /// Environments in total.
        #[arg(long, default_value_t = 32)]
        envs: usize,
        /// World.
        #[arg(long, default_value = "reinvent_base")]
        world: String,
    },
    /// Experience throughput agent -> learner: plain TCP against mutual TLS with the access
    /// rules, interleaved rounds in one run.
    Wire {
        /// Seconds per round.
        #[arg(long, default_value_t = 3.0)]
        seconds: f64,
        /// Rounds per link (the median is reported).
        #[arg(long, default_value_t = 5)]
        rounds: usize,
        /// Seconds of each `up` job in the end-to-end comparison (0: skip it).
        #[arg(long, default_value_t = 30.0)]
        up_seconds: f64,
    },
    /// Every parser and decoder under libFuzzer (`fuzz/`, through cargo-fuzz), a bounded time
    /// each, from the repository's root: new inputs are kept in `fuzz/corpus`, crashes in
    /// `fuzz/artifacts` (the suite replays both). Prints a table and a verdict (exit 1 when a
    /// target found a failing input).
    Fuzz {
        /// Seconds per target.
        #[arg(long, default_value_t = 60)]
        seconds: u64,
        /// Only these targets (comma-separated; default: all).
        #[arg(long, value_delimiter = ',')]
        targets: Vec<String>,
        /// cargo-fuzz's sanitizer: none or address (slower; catches what safe Rust cannot do).
        #[arg(long, default_value = "none")]
        sanitizer: String,
    },
    /// What recording the run's logs (sim-trace, metrics JSON, MCAP) costs: steps/s with
    /// `record_trace` on and off, `train` and `up`, interleaved rounds in one run.
    Record {
        /// Seconds per training.
        #[arg(long, default_value_t = 30.0)]
        seconds: f64,
        /// Rounds per setting (the median is reported).
        #[arg(long, default_value_t = 3)]
        rounds: usize,
    },
    /// A cluster run for a long time under churn (issue 54): two worlds from pixels, two
    /// agents joined with tokens, one killed every --kill-every minutes, one revoked and
    /// joined again every --rejoin-every, agent 1's certificates living --cert-minutes.
    /// Samples each role's memory, threads, files and sockets, the agents' CPU per step and
    /// the steps/s, the stale and refused counts into soak.csv and soak.svg; prints a verdict
    /// (exit 1 unless it passes), each slope weighed with its error: memory growth ≤ 1 %/h,
    /// steps/s drift ≤ 2 %/h, no episode lost, every kill recovered.
    Soak(crate::soak::SoakArgs),
    /// Machines joining and a model reaching them, against their number (issue 54): N
    /// machines, each in a network namespace of its own (as root), join with one token; a
    /// signed model is broadcast to all, over Zenoh's peer mesh and through a router. Prints
    /// the time until all joined and until all hold the model, per N, and a verdict (every copy
    /// held and checked, no transport closed).
    Scale {
        /// Machine counts (comma-separated).
        #[arg(long, value_delimiter = ',', default_value = "1,2,4,8,16")]
        machines: Vec<usize>,
        /// Models broadcast per run.
        #[arg(long, default_value_t = 10)]
        rounds: usize,
        /// Where the runs go (logs, credentials).
        #[arg(long, default_value = "runs/bench-scale")]
        out: PathBuf,
    },
    /// One machine of `bench scale`: holds every model broadcast, each checked.
    #[command(hide = true)]
    ScaleReceive {
        #[command(flatten)]
        net: NetCli,
        /// Where each model's arrival is written.
        #[arg(long)]
        record: PathBuf,
    },
    /// The publisher of `bench scale`: signed models, as the learner.
    #[command(hide = true)]
    ScaleSend {
        #[command(flatten)]
        net: NetCli,
        /// Models to publish.
        #[arg(long)]
        rounds: usize,
        /// Where each publication is written.
        #[arg(long)]
        record: PathBuf,
    },
    /// A quality check of minutes: the README's kind of job (`up`, two worlds, two agents) run
    /// long, then the model of its last update evaluated on both worlds. Prints a verdict
    /// (exit 1 when it fails): the last model still laps every trial, updates went on past
    /// 120 iterations, and at most 5 % of the episodes were dropped as stale.
    LongJob {
        /// Minutes of the job.
        #[arg(long, default_value_t = 3.0)]
        minutes: f64,
        /// Evaluation trials per world.
        #[arg(long, default_value_t = 3)]
        trials: u32,
        /// Where the run goes (kept).
        #[arg(long, default_value = "runs/bench-long-job")]
        out: PathBuf,
    },
    /// Every DeepRacer race from pixels (issue 31): the time trial, object avoidance (3 random
    /// boxes), head-to-bot (2 bots at 0.5 m/s), the stereo pair, and the camera with the
    /// console's LiDAR (SECTOR_LIDAR) among 3 boxes, each trained by `train` and by `up` with 2
    /// agents, then evaluated under the race's rules. Prints a table and a
    /// verdict (exit 1 when a model fails: fewer laps than trials, or a crash).
    Races(RacesArgs),
    /// Generalisation (issue 34): a model trained only on generated tracks (`generated:N`, a
    /// new track every few episodes, either way round), its last checkpoint evaluated on
    /// catalog tracks it never saw. Prints a table and a verdict (exit 1 unless it laps 3/3 on
    /// each).
    Generated {
        /// The generated family (`generated:N`).
        #[arg(long, default_value_t = 1)]
        family: u64,
        /// Catalog tracks to evaluate on (repeatable; default reinvent_base, Oval_track,
        /// Bowtie_track).
        #[arg(long)]
        unseen: Vec<String>,
        /// Observations: state or camera.
        #[arg(long, default_value = "camera")]
        sensor: String,
        /// Minutes of training.
        #[arg(long, default_value_t = 20.0)]
        minutes: f64,
        /// Random seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Where the run goes (kept).
        #[arg(long, default_value = "runs/bench-generated")]
        out: PathBuf,
    },
    /// The adaptive schedule against an even one (issue 34): the same `up` job over several
    /// worlds (2 agents), adaptive and even, for each seed; the wall-clock until an evaluation
    /// laps 3/3 on every world. Prints a table and a verdict (exit 1 unless adaptive's median
    /// is shorter).
    Schedule {
        /// Worlds (repeatable; default five of different difficulty).
        #[arg(long = "world")]
        worlds: Vec<String>,
        /// Observations: state or camera.
        #[arg(long, default_value = "camera")]
        sensor: String,
        /// Budget of each job (minutes); a job that does not get there counts as this.
        #[arg(long, default_value_t = 30.0)]
        minutes: f64,
        /// Seeds (repeatable; default 1, 2, 3).
        #[arg(long = "seed")]
        seeds: Vec<u64>,
        /// Where the jobs go (kept).
        #[arg(long, default_value = "runs/bench-schedule")]
        out: PathBuf,
    },
    /// The racing line's reward against the centre line's (issue 34): per sensor, the same
    /// training (`--action-space-from-line`, same seed and minutes) with `builtin:race_line`
    /// and with `builtin:center_line`, the two models raced (`coordinator race`). Prints a
    /// table and a verdict (exit 1 unless the racing line's model laps 3/3 within 1.15× the
    /// line's theoretical time, faster than the centre line's).
    RaceLine {
        /// The track.
        #[arg(long, default_value = "reinvent_base")]
        world: String,
        /// Minutes a training.
        #[arg(long, default_value_t = 5.0)]
        minutes: f64,
        /// Observations: `state`, `camera` (repeatable; default both).
        #[arg(long = "sensor")]
        sensors: Vec<String>,
        /// Random seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Where the runs and the races go (kept).
        #[arg(long, default_value = "runs/bench-race-line")]
        out: PathBuf,
    },
    /// SAC against PPO from the same files (issue 32): deepracer-for-cloud's continuous
    /// `model_metadata.json` with `"training_algorithm": "sac"`, and the same with
    /// `"clipped_ppo"`, trained by `train` to 3/3 laps on the state vector and from the camera;
    /// then SAC under `up` with 1, 2 and 4 agents. Wall-clock to the model, each model
    /// evaluated again; a table and a verdict (exit 1 when a SAC model does not lap 3/3, or 2
    /// agents are not 1.6× faster than 1).
    Sac {
        /// The track.
        #[arg(long, default_value = "reinvent_base")]
        world: String,
        /// Budget per training (minutes).
        #[arg(long, default_value_t = 5.0)]
        minutes: f64,
        /// Observations: `state`, `camera` (repeatable; default both).
        #[arg(long = "sensor")]
        sensors: Vec<String>,
        /// Agents for the `up` rows (repeatable; default 1, 2 and 4).
        #[arg(long = "agents")]
        agents: Vec<usize>,
        /// Random seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Where the runs go (kept).
        #[arg(long, default_value = "runs/bench-sac")]
        out: PathBuf,
    },
    /// Publish-to-4-agents latency of a SHALLOW camera model; bytes per env step.
    Publish {
        /// Publications to time.
        #[arg(long, default_value_t = 10)]
        repeats: usize,
    },
    /// Wall-clock to 3/3 laps on every world from pixels: `train` in one process, then `up`
    /// with 2 agents, same worlds, same settings, in one run; then both models on more tracks.
    Pixels(PixelsArgs),
}

#[derive(Args, Clone, Debug)]
pub struct PixelsArgs {
    /// Worlds to train on.
    #[arg(long, default_value = "reinvent_carpet,reinvent_concrete,reinvent_wood", value_delimiter = ',')]
    pub worlds: Vec<String>,
    /// Worlds never trained on, for the generalisation table.
    #[arg(long, default_value = "reinvent_base,reInvent2019_track,Oval_track", value_delimiter = ',')]
    pub unseen: Vec<String>,
    /// Trials per world when both models are driven on the training worlds and the unseen
    /// ones at the end. 3 gives the laps the issues' goals count; 20 or more tells a model
    /// that laps a track every time from one that laps it half the time.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=MAX_VERIFY_TRIALS))]
    pub trials: u32,
    /// Time limit of each training (minutes).
    #[arg(long, default_value_t = 20.0)]
    pub minutes: f64,
    /// Environments in total (split over the agents for `up`).
    #[arg(long, default_value_t = 16)]
    pub envs: usize,
    /// Consecutive 3/3 evaluations (on every world) before the checkpoint is verified.
    #[arg(long, default_value_t = protocol::job::TARGET_EVALS)]
    pub evals: u32,
    /// Trials per world of the verification that ends a training (0: none; the streak
    /// of --evals ends it).
    #[arg(long, default_value_t = learner::run::VERIFY_TRIALS as u32, value_parser = clap::value_parser!(u32).range(0..=MAX_VERIFY_TRIALS))]
    pub verify_trials: u32,
    /// Train for the whole --minutes (no lap target), to see whether a policy that lapped
    /// everywhere stays good.
    #[arg(long)]
    pub keep_training: bool,
    /// Seconds between a training's evaluations (its checkpoints) until the lap target is in
    /// sight (then every version is evaluated). 20 suits two cores, where an update takes
    /// seconds; a GPU machine's updates come far sooner.
    #[arg(long, default_value_t = 20.0)]
    pub checkpoint_seconds: f64,
    /// Seeds: both setups are run once per seed (`train --seed S`, `up --seed S`) and
    /// compared seed by seed and by their medians.
    #[arg(long, default_value = "1", value_delimiter = ',')]
    pub seeds: Vec<u64>,
    /// A variant run beside today's setup for every seed, in the same run: `NAME=ARGS`, its
    /// arguments (split at spaces) added to both `train` and `up`, e.g.
    /// `--variant 'epochs3=--hyperparameters hp3.json'` (repeatable); a flag the bench sets
    /// itself (`--checkpoint-seconds 2`, say) takes the variant's value. Each gets its tables
    /// and a line in the comparison.
    #[arg(long = "variant", value_name = "NAME=ARGS")]
    pub variants: Vec<String>,
    /// Where the runs go (kept, with their models).
    #[arg(long, default_value = "runs/bench-pixels")]
    pub out: PathBuf,
}

pub use protocol::net::NetCli;

/// The most verification trials per world a command takes (an agent refuses more).
const MAX_VERIFY_TRIALS: i64 = protocol::exchange::SANITY_LIMIT as i64;

#[derive(Args)]
pub struct ServeCli {
    #[command(flatten)]
    pub net: NetCli,
    /// The job database (redb); jobs survive restarts.
    #[arg(long, default_value = "paddock-coordinator.redb")]
    pub db: PathBuf,
    /// Serve the web console beside the coordinator on this address (host:port), its data
    /// folder beside the database (`console-data`).
    #[arg(long, value_name = "ADDR")]
    pub console: Option<String>,
    /// Where the join door listens (HOST:PORT): machines join with `coordinator token create`
    /// tokens (`sim-agent join`, `learner join`, `deploy join`). Open when --certs DIR holds
    /// the CA's key (ca.key), by default on port 7449 of every interface (if that port is
    /// free); `none` keeps it shut.
    #[arg(long, value_name = "ADDR")]
    pub join_listen: Option<String>,
}

#[derive(Subcommand)]
pub enum JobCommand {
    /// Start a job from a TOML spec (it may name DeepRacer's files as they are).
    Start {
        /// The job spec.
        spec: PathBuf,
        /// Job id (default: derived from the spec's name and the time).
        #[arg(long)]
        id: Option<String>,
        #[command(flatten)]
        net: NetCli,
    },
    /// Every job.
    List {
        #[command(flatten)]
        net: NetCli,
    },
    /// One job: state, per world figures, the learner.
    Status {
        /// Job id.
        id: String,
        /// Print JSON.
        #[arg(long)]
        json: bool,
        /// Keep showing it, refreshed every 2 s, until the job ends (exit status 0 if it
        /// finished, 1 if it failed).
        #[arg(long)]
        watch: bool,
        #[command(flatten)]
        net: NetCli,
    },
    /// Stop a job gracefully (final checkpoint and best model written).
    Stop {
        /// Job id.
        id: String,
        #[command(flatten)]
        net: NetCli,
    },
    /// Choose the version cars following `best` drive (a checkpoint of the job's run).
    Promote {
        /// Job id.
        id: String,
        /// Policy version (a checkpoint's).
        version: u64,
        #[command(flatten)]
        net: NetCli,
    },
    /// A job's report (charts and an HTML page, see `coordinator report`), from its learner's
    /// run folder on this machine.
    Report {
        /// Job id.
        id: String,
        /// Where the report goes (default: the run folder's report/).
        #[arg(long)]
        out: Option<PathBuf>,
        #[command(flatten)]
        net: NetCli,
    },
    /// A job's event log.
    Logs {
        /// Job id.
        id: String,
        /// Keep printing new lines until the job ends.
        #[arg(long)]
        follow: bool,
        #[command(flatten)]
        net: NetCli,
    },
    #[command(skip)]
    Agents { net: NetCli },
}

/// The race a command drives, as DeepRacer configures it (`race` keys of the simulator
/// configuration): set on the configuration as typed values, before the command's `--set`
/// overrides (see [`RaceArgs::sim_config`]).
#[derive(Args, Clone, Debug, Default)]
pub struct RaceArgs {
    /// Race type: time_trial, object_avoidance or head_to_bot (other keys through
    /// `--set race.KEY=VALUE`, DeepRacer's names lower-cased; see config/default.toml).
    #[arg(long, value_name = "TYPE")]
    pub race: Option<String>,
    /// Obstacles on the track (race.number_of_obstacles); implies object_avoidance.
    #[arg(long, value_name = "N")]
    pub obstacles: Option<usize>,
    /// Bot cars (race.number_of_bot_cars); implies head_to_bot.
    #[arg(long, value_name = "N")]
    pub bots: Option<usize>,
    /// The bots' speed along the centre line (m/s, race.bot_car_speed).
    #[arg(long, value_name = "M_PER_S")]
    pub bot_speed: Option<f64>,
    /// A deepracer-for-cloud run.env: its DR_RACE_TYPE, DR_OA_* and DR_H2B_* keys configure
    /// the race (the flags above and --set override them); for train and up its
    /// DR_WORLD_NAME is the world, DR_ENABLE_DOMAIN_RANDOMIZATION the camera's randomisation,
    /// and custom_files/ beside it (reward_function.py, model_metadata.json,
    /// hyperparameters.json) the files, where the command's own flags do not name them.
    #[arg(long, value_name = "run.env")]
    pub run_env: Option<PathBuf>,
}

/// What a deepracer-for-cloud `run.env` names besides the race.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RunEnvFiles {
    /// `DR_WORLD_NAME`.
    pub world: Option<String>,
    /// `custom_files/reward_function.py`, when it exists.
    pub reward: Option<PathBuf>,
    /// `custom_files/model_metadata.json`, when it exists.
    pub model_metadata: Option<PathBuf>,
    /// `custom_files/hyperparameters.json`, when it exists.
    pub hyperparameters: Option<PathBuf>,
    /// `DR_ENABLE_DOMAIN_RANDOMIZATION`.
    pub randomize: Option<bool>,
}

impl RunEnvFiles {
    /// Fill what a command's own flags left unnamed: the world, the reward, the
    /// hyperparameters and the camera's randomisation (before `sets`, so `--set` wins).
    /// Returns `model_metadata.json`, which the caller takes unless it has a sensor of its own.
    pub fn fill(
        self,
        world: &mut Vec<String>,
        reward: &mut Option<String>,
        hyperparameters: &mut Option<PathBuf>,
        sets: &mut Vec<String>,
    ) -> Option<PathBuf> {
        if world.is_empty() {
            world.extend(self.world);
        }
        if reward.is_none() {
            *reward = self.reward.map(|p| p.display().to_string());
        }
        if hyperparameters.is_none() {
            *hyperparameters = self.hyperparameters;
        }
        if let Some(r) = self.randomize {
            sets.insert(0, format!("camera.randomize={r}"));
        }
        self.model_metadata
    }
}

impl RaceArgs {
    /// The world and files `--run-env` names (none without it), as deepracer-for-cloud lays
    /// them out: `custom_files/` beside `run.env`.
    pub fn run_env_files(&self) -> anyhow::Result<Option<RunEnvFiles>> {
        use anyhow::Context;
        let Some(path) = &self.run_env else { return Ok(None) };
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let origin = path.display().to_string();
        let mut f = RunEnvFiles::default();
        for (k, v) in sim_agent::race::parse_env(&text, &origin)? {
            match k.as_str() {
                "DR_WORLD_NAME" if !v.is_empty() => f.world = Some(v),
                "DR_ENABLE_DOMAIN_RANDOMIZATION" => match v.to_ascii_lowercase().as_str() {
                    "true" => f.randomize = Some(true),
                    "false" => f.randomize = Some(false),
                    _ => anyhow::bail!("{origin}: DR_ENABLE_DOMAIN_RANDOMIZATION is {v:?}; expected True or False"),
                },
                _ => {}
            }
        }
        let custom = path.parent().unwrap_or(std::path::Path::new(".")).join("custom_files");
        let file = |name: &str| Some(custom.join(name)).filter(|p| p.is_file());
        f.reward = file("reward_function.py");
        f.model_metadata = file("model_metadata.json");
        f.hyperparameters = file("hyperparameters.json");
        Ok(Some(f))
    }

    /// Whether a flag (or `--run-env`) describes the race.
    pub fn given(&self) -> bool {
        self.race.is_some()
            || self.obstacles.is_some()
            || self.bots.is_some()
            || self.bot_speed.is_some()
            || self.run_env.is_some()
    }

    /// `race` as the flags describe it: a `--run-env`'s race replaces it whole (its keys
    /// that the file leaves out at deepracer-for-cloud's defaults), then `--race`,
    /// `--obstacles`, `--bots` and `--bot-speed` set theirs.
    pub fn apply(&self, race: &mut RaceConfig) -> anyhow::Result<()> {
        use anyhow::Context;
        if let Some(path) = &self.run_env {
            let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            *race = RaceConfig::from_run_env(&text, &path.display().to_string())?;
        }
        let implied = match (&self.race, self.obstacles, self.bots) {
            (Some(r), ..) => Some(r.as_str()),
            (None, Some(_), None) => Some("object_avoidance"),
            (None, None, Some(_)) => Some("head_to_bot"),
            (None, Some(_), Some(_)) => anyhow::bail!("--obstacles and --bots: say which race with --race"),
            (None, None, None) => None,
        };
        if let Some(r) = implied {
            race.race_type = RaceType::parse(r)
                .ok_or_else(|| anyhow::anyhow!("--race {r}: expected time_trial, object_avoidance or head_to_bot"))?;
        }
        if let Some(n) = self.obstacles {
            race.number_of_obstacles = n;
        }
        if let Some(n) = self.bots {
            race.number_of_bot_cars = n;
        }
        if let Some(v) = self.bot_speed {
            race.bot_car_speed = v;
        }
        Ok(())
    }

    /// The simulator configuration a command runs: `file`'s (or the defaults), the race these
    /// flags describe, then `sets` (`--set key=value`, `race.KEY` too), which have the last word.
    pub fn sim_config(&self, file: Option<&Path>, sets: &[String]) -> anyhow::Result<SimConfig> {
        let mut cfg: SimConfig = sim_agent::config::load_config(file, &[])?;
        self.apply(&mut cfg.race)?;
        let origin = file.map_or_else(|| "defaults".to_string(), |p| p.display().to_string());
        Ok(sim_agent::config::apply_sets(cfg, &origin, sets)?)
    }
}

#[derive(Args)]
pub struct UpArgs {
    /// Run this job spec as it is (what `job start` takes) instead of one made from the flags
    /// below that describe a job (worlds, reward, files, stop conditions, --set, --seed).
    #[arg(long, value_name = "JOB.toml", conflicts_with_all = [
        "world", "reversed", "reward", "sensor", "hyperparameters", "model_metadata", "clone_from", "minutes",
        "max_episodes", "env_steps", "target_progress", "target_reward", "window", "target_laps",
        "target_evals", "verify_trials", "stop_on_plateau", "stop_on_collapse", "sets", "seed", "race", "obstacles", "bots",
        "bot_speed", "run_env", "schedule",
    ])]
    pub job: Option<PathBuf>,
    /// World (repeatable; default: reinvent_carpet and reinvent_concrete).
    #[arg(long)]
    pub world: Vec<String>,
    /// Drive every world the other way round (DeepRacer's `is_reversed`).
    #[arg(long)]
    pub reversed: bool,
    /// How the environments spread over the worlds: `adaptive` (more where the last
    /// evaluations are weakest; the default with three worlds or more) or `even`.
    #[arg(long, value_parser = ["adaptive", "even"])]
    pub schedule: Option<String>,
    /// DeepRacer's hyperparameters.json.
    #[arg(long)]
    pub hyperparameters: Option<PathBuf>,
    /// DeepRacer's model_metadata.json (action space, sensor, network); instead of --sensor.
    #[arg(long, conflicts_with = "sensor")]
    pub model_metadata: Option<PathBuf>,
    /// Start from this model folder's weights (transfer learning).
    #[arg(long, value_name = "MODEL_DIR")]
    pub clone_from: Option<PathBuf>,
    /// Stop after this many episodes trained on.
    #[arg(long)]
    pub max_episodes: Option<u64>,
    /// Stop once this many environment steps have been simulated (a compute budget).
    #[arg(long)]
    pub env_steps: Option<u64>,
    /// Stop when the mean episode reward over the last --window episodes reaches this.
    #[arg(long)]
    pub target_reward: Option<f64>,
    /// Episodes in the window of --target-progress and --target-reward.
    #[arg(long, default_value_t = 20)]
    pub window: u64,
    /// Sim agent processes.
    #[arg(long, default_value_t = 2)]
    pub agents: usize,
    /// Environments per agent.
    #[arg(long, default_value_t = 16)]
    pub envs: usize,
    /// Time limit (minutes): the job stops here if it has not stopped at its verified model.
    #[arg(long, default_value_t = 5.0)]
    pub minutes: f64,
    /// Stop early when the mean progress over the last --window episodes reaches this (%).
    #[arg(long)]
    pub target_progress: Option<f64>,
    /// Stop early once an evaluation completes this many laps on every world... (0: train to
    /// the time limit or another stop).
    #[arg(long, default_value_t = 3)]
    pub target_laps: u32,
    /// ...in this many consecutive evaluations (two by default: the second version that
    /// laps everywhere laps unseen tracks far more often than the first)...
    #[arg(long, default_value_t = protocol::job::TARGET_EVALS)]
    pub target_evals: u32,
    /// ...and the last one's checkpoint, evaluated again with this many trials per world
    /// (fresh noise), laps as often: that checkpoint is the model (0: no verification).
    #[arg(long, default_value_t = learner::run::VERIFY_TRIALS as u32, value_parser = clap::value_parser!(u32).range(0..=MAX_VERIFY_TRIALS))]
    pub verify_trials: u32,
    /// Stop at a plateau: this many evaluations in a row without improving the best mean
    /// progress by a point (plateaus are reported after 5 either way).
    #[arg(long)]
    pub stop_on_plateau: Option<u32>,
    /// Stop when evaluation progress collapses after a peak (the best model is kept).
    #[arg(long)]
    pub stop_on_collapse: bool,
    /// Reward: a DeepRacer Python file or builtin:NAME.
    #[arg(long)]
    pub reward: Option<String>,
    /// "state" (the state vector), "camera" (FRONT_FACING_CAMERA, SHALLOW network), "stereo"
    /// (STEREO_CAMERAS, SHALLOW network), or "camera+lidar" / "stereo+lidar" (with SECTOR_LIDAR,
    /// the console's LiDAR).
    #[arg(long, default_value = "state")]
    pub sensor: String,
    /// Override a simulator configuration key for the job (`key=value`, repeatable), e.g.
    /// `camera.randomize=true` for domain randomisation.
    #[arg(long = "set")]
    pub sets: Vec<String>,
    #[command(flatten)]
    pub race: RaceArgs,
    /// Seconds between the learner's evaluations (and checkpoints); once an evaluation laps a
    /// trial on every world, while a lap target is set, every version is evaluated.
    #[arg(long, default_value_t = 2.0)]
    pub checkpoint_seconds: f64,
    /// The key that signs every model the run writes and publishes (PKCS#8 PEM, from
    /// `coordinator keys new NAME`); default: the run folder's `signing.key`, made on first use.
    #[arg(long)]
    pub signing_key: Option<PathBuf>,
    /// Where the learner's network maths run: auto (today the CPU: on the GPU
    /// measured, faer on its cores trained faster), cpu (faer) or gpu (the GPU, a software one
    /// included, or an error).
    #[arg(long, default_value = "auto")]
    pub device: learner::DeviceChoice,
    /// The cluster's credentials (`certs new DIR`): every role on mutual TLS under the access
    /// rules, as across machines. Plain TCP on loopback without.
    #[arg(long, value_name = "DIR")]
    pub certs: Option<PathBuf>,
    /// Random seed of the job (the learner's initial weights, every environment's noise).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Output folder (the run folder is OUT/run, the model OUT/run/model).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Replace OUT if it exists.
    #[arg(long)]
    pub force: bool,
}

#[derive(Args)]
pub struct TrainArgs {
    /// World to train on (built-in name or .npy path; repeatable: the environments are split
    /// over the worlds and every evaluation runs on each). Default: reinvent_base.
    #[arg(long)]
    pub world: Vec<String>,
    /// Reward: a DeepRacer Python file or builtin:NAME (default builtin:center_line).
    #[arg(long)]
    pub reward: Option<String>,
    /// DeepRacer hyperparameters.json (default: the console's PPO defaults).
    #[arg(long)]
    pub hyperparameters: Option<PathBuf>,
    /// DeepRacer model_metadata.json (default: see --sensor).
    #[arg(long)]
    pub model_metadata: Option<PathBuf>,
    /// Without a model_metadata.json: "state" (the state vector, PADDOCK_MLP), "camera"
    /// (FRONT_FACING_CAMERA, DEEP_CONVOLUTIONAL_NETWORK_SHALLOW), "stereo" (STEREO_CAMERAS,
    /// the same network on two channels), or "camera+lidar" / "stereo+lidar" (with
    /// SECTOR_LIDAR, the console's LiDAR); 5 steering angles x 2 speeds.
    #[arg(long, default_value = "state")]
    pub sensor: String,
    /// Drive every world the other way round (DeepRacer's `is_reversed`), in training and in
    /// its evaluations.
    #[arg(long)]
    pub reversed: bool,
    /// Wall-clock budget in minutes.
    #[arg(long, default_value_t = 5.0)]
    pub minutes: f64,
    /// Run folder (default: a new folder under runs/).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Continue the run in --out from its last checkpoint.
    #[arg(long)]
    pub resume: bool,
    /// Delete --out if it exists and start again.
    #[arg(long)]
    pub force: bool,
    /// Override the learning rate.
    #[arg(long)]
    pub lr: Option<f64>,
    /// Drive with the action space the first world's racing line proposes, of N actions
    /// (default 7; see `tracks raceline`) in place of --sensor's.
    #[arg(long, value_name = "N", num_args = 0..=1, default_missing_value = "7")]
    pub action_space_from_line: Option<usize>,
    /// Stop early once an evaluation completes this many of its laps (0: train the full time).
    #[arg(long, default_value_t = 3)]
    pub target_laps: usize,
    /// Evaluation trials per checkpoint.
    #[arg(long, default_value_t = 3)]
    pub trials: usize,
    /// Consecutive evaluations that must reach --target-laps (two by default: the second
    /// version that laps everywhere laps unseen tracks far more often than the first)...
    #[arg(long, default_value_t = protocol::job::TARGET_EVALS as usize)]
    pub target_evals: usize,
    /// ...before the last one's checkpoint is evaluated again with this many trials per world
    /// (fresh noise); training stops if it laps as often, with that checkpoint as the model
    /// (0: no verification; training stops at the streak of --target-evals).
    #[arg(long, default_value_t = learner::run::VERIFY_TRIALS, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(0..=MAX_VERIFY_TRIALS as u64))]
    pub verify_trials: usize,
    /// Stop at a plateau: this many evaluations in a row without improving the best mean
    /// progress by a point (plateaus are reported after 5 either way).
    #[arg(long)]
    pub stop_on_plateau: Option<usize>,
    /// Stop when evaluation progress collapses after a peak (the best model is kept).
    #[arg(long)]
    pub stop_on_collapse: bool,
    /// Stop after this many episodes trained on.
    #[arg(long)]
    pub max_episodes: Option<u64>,
    /// Stop when the mean progress (%) over the last --window episodes reaches this.
    #[arg(long)]
    pub target_progress: Option<f64>,
    /// Stop when the mean episode reward over the last --window episodes reaches this.
    #[arg(long)]
    pub target_reward: Option<f64>,
    /// Episodes in the window of --target-progress and --target-reward.
    #[arg(long, default_value_t = 20)]
    pub window: u64,
    /// Stop once this many environment steps have been simulated (a compute budget).
    #[arg(long)]
    pub env_steps: Option<u64>,
    /// Seconds between evaluations and checkpoints; once an evaluation laps a trial on every
    /// world, while a lap target is set, every version is evaluated.
    #[arg(long, default_value_t = 2.0)]
    pub checkpoint_seconds: f64,
    /// The key that signs every model the run writes and publishes (PKCS#8 PEM, from
    /// `coordinator keys new NAME`); default: the run folder's `signing.key`, made on first use.
    #[arg(long)]
    pub signing_key: Option<PathBuf>,
    /// Parallel environments.
    #[arg(long, default_value_t = 32)]
    pub envs: usize,
    /// Where the learner's network maths run: auto (today the CPU: on the GPU
    /// measured, faer on its cores trained faster), cpu (faer) or gpu (the GPU, a software one
    /// included, or an error).
    #[arg(long, default_value = "auto")]
    pub device: learner::DeviceChoice,
    /// Threads for the environments and for the update (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Random seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Simulator configuration file (TOML).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Override a simulator configuration key (`key=value`, repeatable).
    #[arg(long = "set")]
    pub sets: Vec<String>,
    #[command(flatten)]
    pub race: RaceArgs,
}

/// `bench races`: every race from pixels, per seed, to a verified model, then each model
/// evaluated again with seeds its run never drew. Prints a table and a verdict (exit 1 unless
/// every run stopped at a verified model that then lapped every trial with no crash and, in
/// head-to-bot, overtook in each).
#[derive(Args)]
pub struct RacesArgs {
    /// The track.
    #[arg(long, default_value = "reinvent_base")]
    pub world: String,
    /// Budget per training (minutes).
    #[arg(long, default_value_t = 15.0)]
    pub minutes: f64,
    /// Which races (time_trial, object_avoidance, head_to_bot, stereo, camera_sector_lidar;
    /// default all).
    #[arg(long = "race")]
    pub races: Vec<String>,
    /// Skip `up` (train in one process only).
    #[arg(long)]
    pub no_up: bool,
    /// Seeds, comma-separated: each race is trained once a seed.
    #[arg(long, value_delimiter = ',', default_value = "1")]
    pub seeds: Vec<u64>,
    /// The reward every race trains with instead of its own (a built-in or a .py file).
    #[arg(long)]
    pub reward: Option<String>,
    /// A simulator configuration key for training (`key=value`, repeatable), e.g.
    /// race.min_distance_between_obstacles=8; the `race.` ones for the evaluation after too.
    #[arg(long = "set")]
    pub sets: Vec<String>,
    /// Trials of each model's evaluation after its run.
    #[arg(long, default_value_t = 5)]
    pub eval_trials: usize,
    /// Where the runs go (kept).
    #[arg(long, default_value = "runs/bench-races")]
    pub out: PathBuf,
}

#[derive(Args)]
pub struct EvaluateArgs {
    /// A model folder (e.g. RUN/model).
    pub model_dir: PathBuf,
    /// World to evaluate on (repeatable: one table over the worlds). Default: reinvent_base.
    #[arg(long)]
    pub world: Vec<String>,
    /// Trials (laps from the start line).
    #[arg(long, default_value_t = 3)]
    pub trials: usize,
    /// Put an off-track car back with a 2 s penalty (a crashed one with 5 s), up to 100 times,
    /// instead of ending the trial.
    #[arg(long)]
    pub reset_rules: bool,
    /// Drive the track in reverse.
    #[arg(long)]
    pub reversed: bool,
    /// Random seed (actuator noise, and the race's boxes and bots where they are placed at
    /// random).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[command(flatten)]
    pub race: RaceArgs,
    /// A simulator configuration (TOML) whose `[race]` table the evaluation drives (the race
    /// flags override it).
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Override a key of the race (`race.KEY=VALUE`, repeatable), e.g.
    /// `race.randomize_bot_car_locations=true`.
    #[arg(long = "set")]
    pub sets: Vec<String>,
}

#[derive(Args)]
pub struct RaceCmdArgs {
    /// Model folders (RUN/model) or DeepRacer model archives (.tar.gz, .tar).
    #[arg(required = true)]
    pub models: Vec<PathBuf>,
    /// The world (built-in name or .npy path).
    #[arg(long, default_value = "reinvent_base")]
    pub world: String,
    /// Drive the track in reverse.
    #[arg(long)]
    pub reversed: bool,
    /// Trials (laps from the start line) a model.
    #[arg(long, default_value_t = 3)]
    pub trials: usize,
    /// Off-tracks and crashes a trial survives, each put back on the track with its penalty
    /// (DeepRacer's races do not end a lap at the first; `drive`'s default, 10); 0 ends a
    /// trial at the first, as `evaluate` does.
    #[arg(long, default_value_t = 10)]
    pub resets: u32,
    /// Seconds added for each time off the track (DeepRacer's OFF_TRACK_PENALTY).
    #[arg(long, default_value_t = 2.0)]
    pub penalty: f64,
    /// Seconds added for each crash (DeepRacer's COLLISION_PENALTY).
    #[arg(long, default_value_t = 5.0)]
    pub collision_penalty: f64,
    /// Seed of the first trial's actuator noise (each trial the next).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Where race.html and its pictures go.
    #[arg(long, default_value = "race")]
    pub out: PathBuf,
    #[command(flatten)]
    pub race: RaceArgs,
}

#[derive(Args)]
pub struct CloneArgs {
    /// The model folder to start from.
    pub model_dir: PathBuf,
    /// The new run folder.
    #[arg(long)]
    pub out: PathBuf,
    /// Learning rate for the new run.
    #[arg(long)]
    pub lr: Option<f64>,
    /// model_metadata.json for the new run (its sensors and action space must match).
    #[arg(long)]
    pub model_metadata: Option<PathBuf>,
    /// hyperparameters.json for the new run.
    #[arg(long)]
    pub hyperparameters: Option<PathBuf>,
}

/// What `export --virtual` needs besides the model folder.
#[derive(Args, Clone, Debug, Default)]
pub struct VirtualArgs {
    /// The reward function (default: the one the model was imported with, or its run's).
    #[arg(long)]
    pub reward_function: Option<PathBuf>,
    /// DRoA's track id (default: the one the model was imported with or trained on).
    #[arg(long)]
    pub track: Option<String>,
    /// Trained clockwise (default: as imported, else DeepRacer's waypoints' direction).
    #[arg(long, conflicts_with = "counter_clockwise")]
    pub clockwise: bool,
    /// Trained counter-clockwise.
    #[arg(long)]
    pub counter_clockwise: bool,
    /// Trained on the track reversed (`train --reversed`).
    #[arg(long)]
    pub reversed: bool,
    /// For deepracer-for-cloud only: DRoA's own rules (its tracks and their directions, its
    /// races, LEFT_CAMERA, SAC's one episode between trainings) are not applied.
    #[arg(long)]
    pub deepracer_for_cloud: bool,
    /// Replace `--virtual-dir` if it exists.
    #[arg(long)]
    pub force: bool,
}

/// `coordinator import`.
#[derive(Args)]
pub struct ImportArgs {
    /// DeepRacer's model archive for a car (`.tar.gz` or `.tar`), a frozen graph (`.pb`),
    /// DRoA's `virtualmodel-NAME.tar.gz` or its folder, or a deepracer-for-cloud model folder
    /// (its prefix copied from the bucket).
    pub source: PathBuf,
    /// For a DRoA or deepracer-for-cloud model: which checkpoint (`best` or `last` of
    /// `deepracer_checkpoints.json`, or a name such as `12_Step-3456.ckpt` or a number).
    #[arg(long, default_value = "last")]
    pub checkpoint: String,
    /// The model folder to write.
    #[arg(long)]
    pub out: PathBuf,
    /// The model's model_metadata.json, for a bare `.pb` (default: the one beside it).
    #[arg(long)]
    pub model_metadata: Option<PathBuf>,
    /// Seed of the fresh value tower (the graph holds the policy tower only).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Replace `--out` if it exists.
    #[arg(long)]
    pub force: bool,
}

#[derive(Subcommand)]
pub enum TracksCommand {
    /// Every built-in world: name, length, width, direction, surface.
    List {
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Figures for one track (a built-in name or a .npy file).
    Show {
        /// World name or path to a DeepRacer .npy file.
        name: String,
        /// Draw the track top-down into this PNG file.
        #[arg(long)]
        png: Option<PathBuf>,
    },
    /// Validate a DeepRacer .npy track file and print its figures.
    Import {
        /// The .npy file.
        file: PathBuf,
        /// Name to show (default: the file's stem).
        #[arg(long)]
        name: Option<String>,
        /// Draw the track top-down into this PNG file.
        #[arg(long)]
        png: Option<PathBuf>,
    },
    /// The racing line of a track: the line of least curvature inside the borders (less a
    /// margin), the fastest speeds along it for the car's limits as the simulator measures
    /// them on the track's surface, its lap time
    /// against the centre line's; written as PREFIX.npy (x, y), PREFIX.py (`racing_track =
    /// [[x, y, speed, seconds to the next point], ...]`, for a reward function) and
    /// PREFIX.png (the line coloured by speed).
    Raceline {
        /// World name or path to a DeepRacer .npy file.
        track: String,
        /// Drive the track in reverse.
        #[arg(long)]
        reversed: bool,
        /// Room kept between the car's centre and each border (m): its half-width and more.
        #[arg(long, default_value_t = 0.15)]
        margin: f64,
        /// The surface (asphalt, carpet, concrete, wood; default: the world's).
        #[arg(long)]
        surface: Option<String>,
        /// Where the files go: PREFIX.npy, PREFIX.py, PREFIX.png and
        /// PREFIX.model_metadata.json (default: TRACK-raceline).
        #[arg(long)]
        out: Option<String>,
        /// Actions in the proposed discrete action space (PREFIX.model_metadata.json).
        #[arg(long, default_value_t = 7)]
        actions: usize,
    },
    /// Make a random closed track of a given length and width (a smooth loop the car can
    /// drive, no part of it near another) and write it as a DeepRacer .npy file.
    Generate {
        /// Seed of the draw: the same seed, the same track.
        #[arg(long)]
        seed: u64,
        /// Centre-line length (m).
        #[arg(long)]
        length: f64,
        /// Width between the borders (m; DeepRacer's tracks are about 1.07).
        #[arg(long, default_value_t = 1.07)]
        width: f64,
        /// The .npy file to write (default: generated-SEED.npy).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Draw the track top-down into this PNG file.
        #[arg(long)]
        png: Option<PathBuf>,
    },
}

#[derive(Subcommand)]
pub enum RewardCommand {
    /// Compile a reward file and call it on states sampled along a track; exit 0 only if it passed.
    Validate(ValidateArgs),
    /// Write a built-in reward as a DeepRacer reward file (Python) that gives the same
    /// rewards; race_line's carries the world's racing lines, both directions.
    Export {
        /// The built-in: builtin:NAME (center_line, stay_inside, object_avoidance, race_line,
        /// clearance).
        reward: String,
        /// The world whose racing line race_line follows (built-in name or .npy path).
        #[arg(long, default_value = "reinvent_base")]
        world: String,
        /// The file to write (default: reward_function.py).
        #[arg(long, default_value = "reward_function.py")]
        out: PathBuf,
    },
}

#[derive(Args)]
pub struct ValidateArgs {
    /// A DeepRacer reward file (Python), or builtin:NAME.
    pub file: String,
    /// Track to sample states on (built-in name or .npy path).
    #[arg(long, default_value = "reinvent_base")]
    pub track: String,
    /// Drive the track in reverse (DeepRacer's REVERSE_DIR).
    #[arg(long)]
    pub reversed: bool,
    /// model_metadata.json whose action space supplies speed and steering.
    #[arg(long)]
    pub model_metadata: Option<PathBuf>,
    /// Positions sampled along the track.
    #[arg(long, default_value_t = 60)]
    pub positions: usize,
    /// Seconds one call may take (the simulator's `reward_time_limit`).
    #[arg(long, default_value_t = 1.0)]
    pub time_limit: f64,
    /// Print one JSON object: `ok`, the `errors` and `warnings` (each a `line` and a
    /// `message`), and the `rewards` of the calls that returned.
    #[arg(long)]
    pub json: bool,
    /// The race whose objects the sampled states have.
    #[command(flatten)]
    pub race: RaceArgs,
}

#[derive(Args)]
pub struct DriveArgs {
    /// Track (built-in world name or .npy path).
    #[arg(long, default_value = "reinvent_base")]
    pub track: String,
    /// Laps (evaluation trials from the start line).
    #[arg(long, default_value_t = 3)]
    pub laps: u32,
    /// Reward: a DeepRacer Python file or builtin:NAME (center_line, stay_inside).
    #[arg(long, default_value = "builtin:center_line")]
    pub reward: String,
    /// Drive the track in reverse.
    #[arg(long)]
    pub reversed: bool,
    /// Off-track resets a lap survives (each costs the penalty).
    #[arg(long, default_value_t = 10)]
    pub resets: u32,
    /// Time penalty per reset (s).
    #[arg(long, default_value_t = 2.0)]
    pub penalty: f64,
    /// Time penalty per crash (s; DeepRacer's COLLISION_PENALTY).
    #[arg(long, default_value_t = 5.0)]
    pub collision_penalty: f64,
    /// A timed race instead of separate laps: keep lapping until this many seconds of race
    /// time have passed (DeepRacer's 4-minute race is 240), printing every lap.
    #[arg(long)]
    pub time_limit: Option<f64>,
    /// The driver's top speed (m/s).
    #[arg(long, default_value_t = 2.5)]
    pub max_speed: f64,
    /// Random seed (actuator noise).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Draw the track with the driven path (and the race's objects as the last lap left
    /// them) into this PNG file.
    #[arg(long)]
    pub png: Option<PathBuf>,
    /// Write a DeepRacer sim-trace CSV of every step.
    #[arg(long)]
    pub simtrace: Option<PathBuf>,
    /// Simulator configuration file (TOML; see config/default.toml).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Override a configuration key (`key=value`, repeatable), e.g. --set noise.steering_deg=0.
    #[arg(long = "set")]
    pub sets: Vec<String>,
    #[command(flatten)]
    pub race: RaceArgs,
}

#[derive(Args)]
pub struct RenderArgs {
    /// World (repeatable with --grid; default reinvent_base, or the four reinvent surfaces for --grid).
    #[arg(long)]
    pub world: Vec<String>,
    /// Car pose x,y,heading (metres, metres, degrees); default: the start line.
    #[arg(long, allow_hyphen_values = true)]
    pub pose: Option<String>,
    /// Output PNG.
    #[arg(long)]
    pub png: PathBuf,
    /// A contact sheet of several worlds.
    #[arg(long)]
    pub grid: bool,
    /// Colour instead of the policy's grayscale.
    #[arg(long)]
    pub rgb: bool,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sets(s: &[&str]) -> Vec<String> {
        s.iter().map(|s| s.to_string()).collect()
    }

    /// Issue 50: the race flags set the simulator configuration's race as typed values, and
    /// `--set race.KEY=VALUE` still has the last word.
    #[test]
    fn the_race_flags_set_the_race_and_set_overrides_win() {
        let dir = tempfile::tempdir().unwrap();
        let env = dir.path().join("run.env");
        std::fs::write(&env, "DR_RACE_TYPE=HEAD_TO_BOT\nDR_H2B_NUMBER_OF_BOT_CARS=4\nDR_H2B_BOT_CAR_SPEED=0.3\n")
            .unwrap();
        let oa = RaceType::ObjectAvoidance;
        let h2b = RaceType::HeadToBot;
        for (flags, over, want) in [
            (RaceArgs::default(), vec![], (RaceType::TimeTrial, 6, 3, 0.2)),
            (RaceArgs { race: Some("object_avoidance".into()), ..Default::default() }, vec![], (oa, 6, 3, 0.2)),
            (RaceArgs { obstacles: Some(2), ..Default::default() }, vec![], (oa, 2, 3, 0.2)),
            (RaceArgs { bots: Some(1), bot_speed: Some(0.5), ..Default::default() }, vec![], (h2b, 6, 1, 0.5)),
            (
                RaceArgs { obstacles: Some(2), ..Default::default() },
                sets(&["race.number_of_obstacles=5"]),
                (oa, 5, 3, 0.2),
            ),
            (RaceArgs { run_env: Some(env.clone()), ..Default::default() }, vec![], (h2b, 6, 4, 0.3)),
            (
                RaceArgs { run_env: Some(env.clone()), bots: Some(2), ..Default::default() },
                sets(&["race.bot_car_speed=0.4"]),
                (h2b, 6, 2, 0.4),
            ),
        ] {
            let r = flags.sim_config(None, &over).unwrap().race;
            assert_eq!((r.race_type, r.number_of_obstacles, r.number_of_bot_cars, r.bot_car_speed), want, "{flags:?}");
        }
    }

    /// Issue 50: a bad race flag, `run.env` key or `--set race.` override is refused naming it.
    #[test]
    fn a_bad_race_setting_is_refused_naming_its_flag() {
        let dir = tempfile::tempdir().unwrap();
        let env = dir.path().join("run.env");
        std::fs::write(&env, "DR_RACE_TYPE=DRAG_RACE\n").unwrap();
        for (flags, over, want) in [
            (RaceArgs { race: Some("drag".into()), ..Default::default() }, vec![], "--race drag: expected time_trial"),
            (RaceArgs { obstacles: Some(1), bots: Some(1), ..Default::default() }, vec![], "--obstacles and --bots"),
            (
                RaceArgs { run_env: Some(env.clone()), ..Default::default() },
                vec![],
                "run.env: DR_RACE_TYPE is \"DRAG_RACE\"",
            ),
            (
                RaceArgs { obstacles: Some(1), ..Default::default() },
                sets(&["race.number_of_obstacles.x=1"]),
                "--set race.number_of_obstacles.x=1: 'number_of_obstacles' is not a section",
            ),
            (RaceArgs::default(), sets(&["race.bots=2"]), "defaults with --set overrides: "),
        ] {
            let e = format!("{:#}", flags.sim_config(None, &over).unwrap_err());
            assert!(e.contains(want), "{flags:?} {over:?}: {e}");
        }
    }
}
