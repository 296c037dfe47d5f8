//! The `learner` binary: `serve` (the learner role over Zenoh) and `bench` (the network
//! maths' speed).

/// mimalloc hands freed pages back to the system (glibc's malloc keeps them in its arenas),
/// at once in `serve` ([`protocol::secure::purge_freed_memory_after`]): a long run's resident
/// memory follows what it holds, not its highest peak. `main` turns transparent huge pages
/// off, which would make them resident again. `Cap` (no limit) counts the bytes held, which each update's
/// record carries beside the resident memory: a leak shows there, an allocator's retention
/// only in the resident memory.
#[global_allocator]
static ALLOCATOR: cap::Cap<mimalloc::MiMalloc> = cap::Cap::new(mimalloc::MiMalloc, usize::MAX);

mod serve;
mod team;
mod team_bench;

use anyhow::Context;
use faer::Par;
use learner::Hyperparameters;
use learner::ppo::{Batch, Workspace, loss_and_grad_factored};
use policy::{ActorCritic, ModelMetadata};
use rand::{Rng, SeedableRng};
use std::time::Instant;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "learner", version, about = "Paddock's learner: PPO on faer", after_help = protocol::exit::TABLE)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Serve a coordinator: train its running job over Zenoh.
    Serve(ServeCli),
    /// Join a Paddock cluster with a token (`coordinator token create --role learner`): make
    /// this machine's key, check the coordinator's CA against the token, write the
    /// credentials folder (`--certs DIR`, with the cluster's model-signing key); then
    /// `serve --certs DIR` (or `--service`).
    Join(protocol::join::JoinCli),
    /// The network maths' speed: PPO sample-gradients/s and inference latency.
    Bench(BenchCli),
    /// A member of `bench --learners N`'s team (started by the bench itself).
    #[command(hide = true)]
    BenchMember(MemberCli),
}

#[derive(clap::Args)]
struct MemberCli {
    #[command(flatten)]
    net: protocol::net::NetCli,
    /// Learner id.
    #[arg(long)]
    id: String,
    /// The bench's network.
    #[arg(long)]
    network: String,
    /// The bench's epochs per update.
    #[arg(long)]
    epochs: usize,
    /// The bench's algorithm is SAC.
    #[arg(long)]
    sac: bool,
}

#[derive(clap::Args)]
struct ServeCli {
    #[command(flatten)]
    net: protocol::net::NetCli,
    /// Learner id (default: learner-PID).
    #[arg(long)]
    id: Option<String>,
    /// Seconds between evaluations (and checkpoints); once an evaluation laps a trial on every
    /// world, while the job's lap target is set, every version is evaluated.
    #[arg(long, default_value_t = 5.0)]
    checkpoint_seconds: f64,
    /// The key that signs every model (PKCS#8 PEM, from `coordinator keys new NAME`); default:
    /// the credentials folder's `models.key` with `--certs DIR`, else the run folder's
    /// `signing.key`, made on first use. Learners of one team share one key (agents take
    /// policies from one key per job).
    #[arg(long)]
    signing_key: Option<std::path::PathBuf>,
    /// Threads for the update (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Where the network maths run: auto (today the CPU: on the GPU measured,
    /// faer on its cores trained faster), cpu (faer) or gpu (the GPU, a software one included,
    /// or an error).
    #[arg(long, default_value = "auto")]
    device: learner::DeviceChoice,
    /// The agents run on this machine (`coordinator up` and the console pass it): an update
    /// waits while an evaluation that may stop the run, or a verification, is under way, so
    /// that the agents' trials have the cores. Without it, a learner on a machine of its own
    /// trains on through them.
    #[arg(long)]
    checks_first: bool,
    /// This is the coordinator's only learner (`coordinator up` and the console pass it: each
    /// starts one, on a coordinator of its own on loopback): lead a job as soon as it arrives.
    /// Without it a new learner first waits 3 s to hear the others, so that a team gets one
    /// leader.
    #[arg(long)]
    alone: bool,
}

#[derive(clap::Args)]
struct BenchCli {
    /// SHALLOW, DEEP, DEEPER or MLP.
    #[arg(long, default_value = "SHALLOW")]
    network: String,
    /// Seconds per measurement (taken in 5 rounds, in turn with the others).
    #[arg(long, default_value_t = 5.0)]
    seconds: f64,
    /// Threads for the threaded row (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// gpu: also time whole updates with the maths on the GPU (any adapter, lavapipe
    /// included), against the same updates on faer; auto and cpu: faer alone.
    #[arg(long, default_value = "auto")]
    device: learner::DeviceChoice,
    /// Also measure whole updates shared by this many learner processes of one thread each
    /// (a team over Zenoh on loopback), against one learner in the same run.
    #[arg(long, default_value_t = 1)]
    learners: usize,
    /// With --learners: check that the team's weights are one learner's (to float rounding)
    /// and every member's are the leader's (bit for bit); fail otherwise. Needs --epochs 3 or
    /// fewer (rounding differences grow with every step).
    #[arg(long)]
    check: bool,
    /// Only the team rows (with --learners).
    #[arg(long)]
    team_only: bool,
    /// With --learners: epochs of each whole update (PPO's passes over the iteration's
    /// experience, which the leader sends the team once per update); DeepRacer's 10 by default.
    #[arg(long, default_value_t = 10)]
    epochs: usize,
    /// With --learners: the team shares SAC's updates (DeepRacer's continuous SAC networks,
    /// 8 gradient steps of 64 transitions an update) instead of PPO's.
    #[arg(long)]
    sac: bool,
}

fn main() {
    let cli = Cli::parse();
    if matches!(cli.command, Command::Serve(_)) {
        // An update's buffers go back as it ends (its steps reuse theirs through a workspace:
        // `learner bench`'s training step is as fast either way).
        protocol::secure::purge_freed_memory_after(0);
    }
    protocol::secure::init_process("info");
    learner::record::count_live_bytes_with(|| ALLOCATOR.allocated());
    // The maths on a headless NVIDIA server (gpu::icd), before any thread starts.
    gpu::icd::headless_nvidia();
    let result = match cli.command {
        Command::Bench(b) => (|| {
            let threads = learner::use_threads(b.threads);
            if !b.team_only {
                bench(&b.network, b.seconds, threads, b.device)?;
            }
            if b.learners > 1 {
                team_bench::run(&b.network, b.seconds, b.learners, b.epochs, b.check, b.sac)?;
            }
            Ok(())
        })(),
        Command::BenchMember(m) => {
            learner::use_threads(Some(1));
            team_bench::member(
                &m.network,
                m.epochs,
                m.sac,
                m.net.args(true).as_role(protocol::secure::Role::Learner),
                &m.id,
            )
        }
        Command::Join(j) => protocol::join::run_cli(protocol::secure::Role::Learner, j).map_err(anyhow::Error::from),
        Command::Serve(a) => {
            // With the cluster's credentials, its model-signing key (when that machine has it).
            let credentials_key =
                a.net.certs.as_ref().map(|d| d.join(protocol::secure::MODEL_KEY_FILE)).filter(|k| k.exists());
            serve::serve(serve::ServeArgs {
                net: protocol::net::NetArgs::from(a.net).as_role(protocol::secure::Role::Learner),
                id: a.id,
                threads: learner::use_threads(a.threads),
                checkpoint_seconds: a.checkpoint_seconds,
                signing_key: a.signing_key.or(credentials_key),
                device: a.device,
                checks_first: a.checks_first,
                alone: a.alone,
            })
        }
    };
    protocol::exit::exit(result.map(|()| protocol::exit::SUCCESS))
}

/// The bench's model description for a network name: (network, sensor, metadata).
pub(crate) fn bench_metadata(network: &str) -> anyhow::Result<(&'static str, &'static str, ModelMetadata)> {
    let (name, sensor) = match network {
        "SHALLOW" => ("DEEP_CONVOLUTIONAL_NETWORK_SHALLOW", "FRONT_FACING_CAMERA"),
        "DEEP" => ("DEEP_CONVOLUTIONAL_NETWORK", "FRONT_FACING_CAMERA"),
        "DEEPER" => ("DEEP_CONVOLUTIONAL_NETWORK_DEEP", "FRONT_FACING_CAMERA"),
        "MLP" => ("PADDOCK_MLP", "STATE_VECTOR"),
        other => anyhow::bail!("--network {other:?}: expected SHALLOW, DEEP, DEEPER or MLP"),
    };
    let meta = ModelMetadata::parse(
        &format!(
            r#"{{"action_space":[{{"steering_angle":-30,"speed":1}},{{"steering_angle":-15,"speed":1}},{{"steering_angle":0,"speed":1}},{{"steering_angle":15,"speed":1}},{{"steering_angle":30,"speed":1}}],"sensor":["{sensor}"],"neural_network":"{name}","version":"5"}}"#
        ),
        "bench",
    )?;
    Ok((name, sensor, meta))
}

fn bench(network: &str, seconds: f64, threads: usize, device: learner::DeviceChoice) -> anyhow::Result<()> {
    let (name, sensor, meta) = bench_metadata(network)?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let model = ActorCritic::new(&meta, 27, &mut rng);
    let os = model.obs_size();
    let params = model.pi.params.len() + model.v.params.len();
    println!("# learner bench: {name} ({sensor}), {} inputs, {params} parameters (both towers), {threads} threads", os);
    println!();
    // Camera frames are 0..255 grey levels; the state vector is about unit scale.
    let frame = |rng: &mut rand_chacha::ChaCha8Rng| -> f32 {
        if sensor == "STATE_VECTOR" { rng.random_range(-1.0..1.0) } else { rng.random_range(0..=255u8) as f32 }
    };
    let n = 64;
    let batch = random_batch(&model, n, &mut rng, &frame);
    let idx: Vec<usize> = (0..n).collect();
    let h = Hyperparameters::default();
    // The same step with bf16 products, where the CPU makes them.
    let h_bf16 = policy::nn::Precision::bf16_available()
        .then(|| Hyperparameters { precision: policy::nn::Precision::Bf16, ..h.clone() });
    // What one minibatch costs in training: forward + backward of both towers (the big dense
    // layers' weight gradients left as factors), and (`adam`) the whole gradient step as
    // `Ppo::update` takes it: those gradients multiplied out and Adam applied over every
    // parameter. Returns the work, set up once and run once untimed.
    let step = |par: Par, adam: bool, h: &Hyperparameters| {
        let mut ws = Workspace::default();
        let mut ppo = learner::ppo::Ppo::new(model.clone(), h.clone(), 0, 1, par);
        let defer = (model.pi.factorable(n), model.v.factorable(n));
        let (batch, idx, model, h) = (&batch, &idx, &model, h.clone());
        let mut once = move || {
            if adam {
                std::hint::black_box(ppo.gradient_step(batch, idx));
            } else {
                let lg = loss_and_grad_factored(&mut ws, model, batch, idx, &h, par, (&defer.0, &defer.1));
                ws.recycle(std::hint::black_box(lg));
            }
        };
        once();
        once
    };
    // Reference in the same run: the GEMMs alone (the layers' matrix products, forward and
    // backward, both towers, no im2col, no activations, no optimiser). `as_step`: in the
    // shapes the step runs them (conv layers a chunk of samples at a time, each thread on
    // its share, operands in cache): the ceiling. Otherwise one whole-batch product each.
    // Returns the work, set up once and run once untimed, as the step is (the outputs'
    // pages are first touched there).
    let gemm_only = |par: Par, as_step: bool| {
        let threads = par.degree().max(1);
        let shapes = gemm_shapes(&model.pi, n, threads, as_step);
        // One (a, b, c) per thread for the per-chunk products; the operand that holds
        // activations or their gradients (`streams`) spans the thread's whole share, a
        // chunk's slice at a time, as in the step.
        let mut bufs: Vec<Vec<Operands>> = shapes
            .iter()
            .map(|s| {
                let reps = s.chunks.max(1);
                let (ra, rc) = match s.streams {
                    Operand::A => (reps, 1),
                    Operand::C => (1, reps),
                };
                (0..if s.chunks == 0 { 1 } else { threads })
                    .map(|_| (vec![0.5f32; s.m * s.k * ra], vec![0.25f32; s.k * s.n], vec![0.0f32; s.m * s.n * rc]))
                    .collect()
            })
            .collect();
        let mut pass = move || {
            for _tower in 0..2 {
                for (s, copies) in shapes.iter().zip(bufs.iter_mut()) {
                    let (mk, mn) = (s.m * s.k, s.m * s.n);
                    let run = |(a, b, c): &mut Operands, par: Par| {
                        for i in 0..s.chunks.max(1) {
                            let (a, c) = match s.streams {
                                Operand::A => (&a[i * mk..(i + 1) * mk], &mut c[..]),
                                Operand::C => (&a[..], &mut c[i * mn..(i + 1) * mn]),
                            };
                            let (m, n, k, a_t, b_t, add) = (s.m, s.n, s.k, s.a_t, s.b_t, s.add);
                            policy::nn::gemm(c, a, b, policy::nn::Product { m, n, k, a_t, b_t, add }, par)
                        }
                    };
                    if s.chunks == 0 {
                        run(&mut copies[0], par);
                    } else {
                        use rayon::prelude::*;
                        copies.par_iter_mut().for_each(|c| run(c, Par::Seq));
                    }
                }
            }
        };
        pass();
        pass
    };
    println!(
        "| measurement (minibatch 64, both towers; medians of {ROUNDS} rounds taken in turn) | sample-gradients/s |"
    );
    println!("|---|---|");
    let mut pars = vec![(1, Par::Seq)];
    if threads > 1 {
        pars.push((threads, Par::rayon(threads)));
    }
    for (t, par) in pars {
        // The four measurements in turn, a round at a time, so that a ratio compares figures
        // taken side by side on a machine whose speed drifts (a shared VM's does, by 3-5 %
        // from one measurement to the next).
        let secs = seconds / ROUNDS as f64;
        let mut work: Vec<Box<dyn FnMut()>> = vec![
            Box::new(step(par, false, &h)),
            Box::new(step(par, true, &h)),
            Box::new(gemm_only(par, true)),
            Box::new(gemm_only(par, false)),
        ];
        if let Some(hb) = &h_bf16 {
            work.push(Box::new(step(par, true, hb)));
        }
        let rounds: Vec<[f64; 5]> = (0..ROUNDS)
            .map(|_| {
                let mut r = [0.0; 5];
                for (r, w) in r.iter_mut().zip(work.iter_mut()) {
                    *r = samples_per_second(n, secs, w);
                }
                r
            })
            .collect();
        drop(work);
        let [fb, full, ceiling, whole, bf16] = [0, 1, 2, 3, 4].map(|i| median(rounds.iter().map(|r| r[i]).collect()));
        let reach: Vec<f64> = rounds.iter().map(|r| 100.0 * r[1] / r[2]).collect();
        let (lo, hi) = (reach.iter().copied().fold(f64::MAX, f64::min), reach.iter().copied().fold(0.0, f64::max));
        let reach = median(reach);
        println!("| {t} thread(s): forward + backward (the big dense layers' weight gradients as factors) | {fb:.0} |");
        println!(
            "| {t} thread(s): forward + backward + optimiser (one training step) | {full:.0} (the optimiser step {:.0} % of it) |",
            100.0 * (1.0 - full / fb)
        );
        println!(
            "| {t} thread(s): reference, the same GEMMs alone, in the step's shapes (the ceiling) | {ceiling:.0} (the training step reaches {reach:.0} %: the median of the rounds' ratios, {lo:.0}-{hi:.0} %) |"
        );
        println!(
            "| {t} thread(s): the same GEMMs alone, each conv product over the whole batch | {whole:.0} (the training step {:.0} % of it) |",
            100.0 * full / whole
        );
        if h_bf16.is_some() {
            let ratio = median(rounds.iter().map(|r| r[4] / r[1]).collect());
            println!(
                "| {t} thread(s): one training step with bf16 products (`\"precision\": \"bf16\"`) | {bf16:.0} ({ratio:.2}× the f32 step: the median of the rounds' ratios) |"
            );
        } else {
            println!("| {t} thread(s): one training step with bf16 products | — (this CPU has no AVX-512 BF16) |");
        }
        // Adam alone over every parameter (a memory-bound pass: weights, both moments read
        // and written, the gradient read): what a step costs beyond its GEMMs at the least.
        let adam_ms = adam_alone(&model, par, seconds.min(3.0));
        let best = n as f64 / (n as f64 / ceiling + adam_ms / 1e3);
        println!(
            "| {t} thread(s): Adam alone over the {params} parameters | {adam_ms:.1} ms a step: GEMMs + Adam alone would make {best:.0}, {:.0} % of the ceiling |",
            100.0 * best / ceiling
        );
    }
    if let Some(gpu) = learner::device::Device::new(device).gpu().context("--device")? {
        gpu_rows(&model, &meta, gpu, threads, seconds, &mut rng, &frame)?;
    }
    let single: Vec<f32> = batch.obs[..os].to_vec();
    // Milliseconds a call of `work` takes, over up to 3 s (at least 10 calls).
    let ms_per_call = |work: &mut dyn FnMut()| {
        let t = Instant::now();
        let mut k = 0u64;
        while t.elapsed().as_secs_f64() < seconds.min(3.0) || k < 10 {
            work();
            k += 1;
        }
        t.elapsed().as_secs_f64() * 1e3 / k as f64
    };
    let ms = ms_per_call(&mut || {
        std::hint::black_box(model.act(&single, 1, true, &mut rng, Par::Seq));
    });
    println!("| inference at batch 1 (policy + value towers), 1 thread | {ms:.3} ms |");
    // A sim agent acts for all its environments at once (8: `up`'s default 16 over two agents).
    let envs = 8;
    let ms_envs = ms_per_call(&mut || {
        std::hint::black_box(model.act(&batch.obs[..envs * os], envs, false, &mut rng, Par::Seq));
    });
    println!(
        "| inference over {envs} environments at once (policy + value towers), 1 thread | {ms_envs:.3} ms ({:.3} ms an environment) |",
        ms_envs / envs as f64
    );
    let ms_alone = ms_per_call(&mut || {
        std::hint::black_box(model.act_policy(&batch.obs[..envs * os], envs, false, &mut rng, Par::Seq));
    });
    println!(
        "| inference over {envs} environments at once (policy tower alone, as a sim agent acts), 1 thread | {ms_alone:.3} ms ({:.3} ms an environment; {:.2}× both towers' time) |",
        ms_alone / envs as f64,
        ms_alone / ms_envs
    );
    let ms_pi = ms_per_call(&mut || {
        let mut tape = policy::nn::Tape::default();
        model.pi.forward(&single, 1, &mut tape, Par::Seq);
        std::hint::black_box(tape.output()[0]);
    });
    println!("| inference at batch 1 (policy tower only, as on the car), 1 thread | {ms_pi:.3} ms |");
    Ok(())
}

/// `n` samples of `frame`s acted by `model`, with random advantages and returns.
fn random_batch(
    model: &ActorCritic,
    n: usize,
    rng: &mut rand_chacha::ChaCha8Rng,
    frame: &dyn Fn(&mut rand_chacha::ChaCha8Rng) -> f32,
) -> Batch {
    let obs: Vec<f32> = (0..n * model.obs_size()).map(|_| frame(rng)).collect();
    let acts = model.act(&obs, n, false, rng, Par::Seq);
    Batch {
        obs_size: model.obs_size(),
        obs,
        choices: acts.iter().map(|a| a.choice).collect(),
        logp_old: acts.iter().map(|a| a.logp).collect(),
        adv: (0..n).map(|_| rng.random_range(-1.0..1.0)).collect(),
        returns: (0..n).map(|_| rng.random_range(-1.0..1.0)).collect(),
        values_old: acts.iter().map(|a| a.value).collect(),
    }
}

/// Whole updates (one epoch of 16 minibatches of 64 on a batch already made: PPO's
/// minibatches, Adam, and on the GPU the batch's upload and the weights' readback) on the
/// GPU and on faer with `threads` threads, in turn.
fn gpu_rows(
    model: &ActorCritic,
    meta: &ModelMetadata,
    gpu: std::sync::Arc<gpu::Gpu>,
    threads: usize,
    seconds: f64,
    rng: &mut rand_chacha::ChaCha8Rng,
    frame: &dyn Fn(&mut rand_chacha::ChaCha8Rng) -> f32,
) -> anyhow::Result<()> {
    let adapter = gpu.adapter.clone();
    let (mb, k) = (64, 16);
    let n = mb * k;
    let batch = random_batch(model, n, rng, frame);
    let h = Hyperparameters {
        num_epochs: 1,
        batch_size: mb,
        target_kl: None,
        value_warmup_updates: 0,
        lr: 1e-6,
        ..Hyperparameters::default()
    };
    let mut on_gpu = learner::ppo::Ppo::new(model.clone(), h.clone(), 0, 1, Par::Seq).with_gpu(gpu.clone());
    let mut on_cpu = learner::ppo::Ppo::new(model.clone(), h, 0, 1, Par::rayon(threads));
    // Each learner's updates shuffle from seeds 1, 2, …
    fn updates<'a>(p: &'a mut learner::ppo::Ppo, batch: &'a Batch) -> impl FnMut() -> anyhow::Result<()> + 'a {
        let mut seed = 0;
        move || {
            seed += 1;
            p.update_on_batch(batch, seed).map_err(|e| anyhow::anyhow!("{e}"))?;
            Ok(())
        }
    }
    let (g, c, r) = in_turn(n, seconds, &mut updates(&mut on_gpu, &batch), &mut updates(&mut on_cpu, &batch))?;
    println!(
        "| whole updates on the GPU, {adapter} (16 minibatches of 64, Adam, upload and readback) | {g:.0} ({r:.2}× faer's, the median of the rounds' ratios) |"
    );
    println!("| the same updates on faer, {threads} thread(s) | {c:.0} |");
    // What the updates' products amount to, against the kernel's own rate on one big
    // product: how far the step is from what the GEMM kernel can do.
    let flops = step_flops_per_sample(&model.pi, mb);
    let (side, tflops) = gpu_gemm_rate(&gpu, seconds)?;
    println!(
        "| the updates' matrix products on the GPU ({:.3} MFLOP a sample-gradient, both towers, forward and backward) | {:.1} GFLOP/s |",
        flops / 1e6,
        g * flops / 1e9
    );
    println!(
        "| the GEMM kernel alone, one {side}×{side}×{side} f32 product at a time, checked | {:.1} GFLOP/s |",
        tflops * 1e3
    );
    sac_gpu_rows(model, meta, &gpu, threads, seconds, rng, frame)
}

/// Floating-point operations of one sample's forward and backward pass through both towers'
/// matrix products (each tower shaped as `net`), at minibatch `batch`: 2·m·n·k a product.
fn step_flops_per_sample(net: &policy::nn::Net, batch: usize) -> f64 {
    let one: f64 = gemm_shapes(net, batch, 1, false).iter().map(|s| 2.0 * (s.m * s.n * s.k) as f64).sum();
    2.0 * one / batch as f64
}

/// The GPU's GEMM kernel alone: square f32 products (4096 on a hardware GPU, 512 on a
/// software one), eight to a submission, timed for about `seconds` after one untimed
/// submission; each result is checked. Returns the side and the median TFLOP/s.
fn gpu_gemm_rate(gpu: &gpu::Gpu, seconds: f64) -> anyhow::Result<(usize, f64)> {
    use gpu::kernels::{Gemm, Operand};
    let side = if gpu::device::is_hardware(gpu.device_type) { 4096 } else { 512 };
    let len = side * side;
    let (a, b, c) = (gpu.buffer("bench a", len)?, gpu.buffer("bench b", len)?, gpu.buffer("bench c", len)?);
    gpu.upload(&a, 0, &vec![0.5; len]);
    gpu.upload(&b, 0, &vec![0.25; len]);
    let g = Gemm {
        mnk: [side; 3],
        a: Operand { buf: &a, at: 0, t: false },
        b: Operand { buf: &b, at: 0, t: true },
        c: (&c, 0),
        add: false,
    };
    let reps = 8;
    let mut scratch = None;
    let mut submission = || -> anyhow::Result<f64> {
        let t = Instant::now();
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        for _ in 0..reps {
            gpu.gemm(&mut enc, &g, &mut scratch);
        }
        gpu.queue.submit([enc.finish()]);
        let out = gpu.download(&c, len - 1, 1)?;
        // Every product sums `side` terms of 0.125, exactly representable.
        anyhow::ensure!(out[0] == 0.125 * side as f32, "the GEMM kernel gave {} for {}", out[0], 0.125 * side as f32);
        Ok(t.elapsed().as_secs_f64())
    };
    submission()?;
    let (mut rates, t) = (Vec::new(), Instant::now());
    while rates.len() < 3 || t.elapsed().as_secs_f64() < seconds {
        rates.push(2.0 * (len * side * reps) as f64 / submission()? / 1e12);
    }
    Ok((side, median(rates)))
}

/// SAC's gradient steps (DeepRacer's SAC networks for the bench's network: the policy, the
/// critics' embedder and twin heads, V and its target) on the GPU against the same steps on
/// faer, in turn: an iteration of 16 steps of 64 transitions each, the GPU's including
/// putting the networks there and reading them back.
fn sac_gpu_rows(
    model: &ActorCritic,
    meta: &ModelMetadata,
    gpu: &std::sync::Arc<gpu::Gpu>,
    threads: usize,
    seconds: f64,
    rng: &mut rand_chacha::ChaCha8Rng,
    frame: &dyn Fn(&mut rand_chacha::ChaCha8Rng) -> f32,
) -> anyhow::Result<()> {
    use learner::sac::{Batch as SacBatch, Sac, SacGpu, SacNets, SacSettings, Tapes};
    let os = model.obs_size();
    let space = policy::ActionSpace::Continuous { steering_angle: (-30.0, 30.0), speed: (0.5, 2.0) };
    let mut meta = meta.clone();
    meta.action_space = space.clone();
    meta.training_algorithm = policy::TrainingAlgorithm::Sac;
    let nets = SacNets::new(&meta, os, rng);
    let settings = SacSettings { lr: 1e-6, ..SacSettings::for_space(&space).expect("continuous") };
    let (mb, k) = (64, 16);
    let batches: Vec<SacBatch> = (0..k)
        .map(|_| SacBatch {
            obs: (0..mb * os).map(|_| frame(rng)).collect(),
            next_obs: (0..mb * os).map(|_| frame(rng)).collect(),
            action: (0..2 * mb).map(|_| rng.random_range(-0.9..0.9)).collect(),
            reward: (0..mb).map(|_| rng.random_range(-1.0..1.0)).collect(),
            done: (0..mb).map(|i| (i % 50 == 0) as u8 as f32).collect(),
        })
        .collect();
    let on = SacGpu::new(gpu.clone());
    let mut on_gpu = Sac::new(nets.clone(), settings.clone(), 1);
    let mut on_cpu = Sac::new(nets, settings, 1);
    let par = Par::rayon(threads);
    let mut tapes = Tapes::default();
    let mut gpu_iteration = || -> anyhow::Result<()> {
        let mut session = on.begin(&on_gpu, mb)?;
        for b in &batches {
            session.step(&mut on_gpu, b)?;
        }
        session.finish(&mut on_gpu)?;
        Ok(())
    };
    let mut cpu_iteration = || {
        for b in &batches {
            std::hint::black_box(on_cpu.step(b, par, &mut tapes));
        }
        Ok(())
    };
    let (g, c, r) = in_turn(k * mb, seconds, &mut gpu_iteration, &mut cpu_iteration)?;
    println!(
        "| SAC: an iteration's gradient steps on the GPU, {} (16 steps of 64 transitions; the networks put there and read back) | {g:.0} transitions/s ({r:.2}× faer's, the median of the rounds' ratios) |",
        gpu.adapter
    );
    println!("| SAC: the same steps on faer, {threads} thread(s) | {c:.0} transitions/s |");
    Ok(())
}

/// Work on the GPU against the same work on faer, `n` samples a call: each once untimed (the
/// GPU's buffers and pipelines are made then), then in turn for [`ROUNDS`] rounds of
/// `seconds` in all. Returns the medians of the GPU's and faer's samples/s and of the rounds'
/// ratios.
fn in_turn<'a>(
    n: usize,
    seconds: f64,
    gpu: &mut (dyn FnMut() -> anyhow::Result<()> + 'a),
    cpu: &mut (dyn FnMut() -> anyhow::Result<()> + 'a),
) -> anyhow::Result<(f64, f64, f64)> {
    gpu()?;
    cpu()?;
    let (mut g, mut c) = (Vec::new(), Vec::new());
    for _ in 0..ROUNDS {
        for (work, out) in [(&mut *gpu, &mut g), (&mut *cpu, &mut c)] {
            let t = Instant::now();
            let mut k = 0;
            while t.elapsed().as_secs_f64() < seconds / ROUNDS as f64 || k < 1 {
                work()?;
                k += 1;
            }
            out.push((k * n) as f64 / t.elapsed().as_secs_f64());
        }
    }
    let ratios: Vec<f64> = g.iter().zip(&c).map(|(a, b)| a / b).collect();
    Ok((median(g), median(c), median(ratios)))
}

/// Rounds `learner bench` splits each measurement of a thread count into (see [`bench`]).
const ROUNDS: usize = 5;

/// Sample-gradients/s of `work` on `n` samples, run for `secs` (at least twice).
fn samples_per_second(n: usize, secs: f64, work: &mut dyn FnMut()) -> f64 {
    let t = Instant::now();
    let mut k = 0;
    while t.elapsed().as_secs_f64() < secs || k < 2 {
        work();
        k += 1;
    }
    (k * n) as f64 / t.elapsed().as_secs_f64()
}

/// The median of some figures (the mean of the middle two for an even count).
fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    if n % 2 == 1 { v[n / 2] } else { (v[n / 2 - 1] + v[n / 2]) / 2.0 }
}

/// Milliseconds per Adam step over both towers' parameters, on a gradient already in memory.
fn adam_alone(model: &ActorCritic, par: Par, seconds: f64) -> f64 {
    let mut opts = [
        (
            model.pi.params.clone(),
            vec![1e-3f32; model.pi.params.len()],
            policy::nn::Adam::new(model.pi.params.len(), 3e-4),
        ),
        (
            model.v.params.clone(),
            vec![1e-3f32; model.v.params.len()],
            policy::nn::Adam::new(model.v.params.len(), 3e-4),
        ),
    ];
    let t = Instant::now();
    let mut k = 0;
    while t.elapsed().as_secs_f64() < seconds || k < 3 {
        for (p, g, opt) in opts.iter_mut() {
            opt.step_with(p, g, par);
        }
        k += 1;
    }
    t.elapsed().as_secs_f64() * 1e3 / k as f64
}

/// One GEMM a tower's forward and backward pass make.
struct GemmShape {
    m: usize,
    n: usize,
    k: usize,
    a_t: bool,
    b_t: bool,
    /// 0: one product over the whole batch (threads inside it); otherwise a conv layer's
    /// per-chunk products, each of `threads` threads making `chunks` of them.
    chunks: usize,
    /// The operand that holds a layer's outputs or their gradient: it goes through memory,
    /// where the unfolded input and the weights stay in cache.
    streams: Operand,
    /// Whether the product is added to `c` (read, then written) or replaces it, as the step
    /// makes it.
    add: bool,
}

/// `a`, `b` and `c` of `c = a · b`, row-major.
type Operands = (Vec<f32>, Vec<f32>, Vec<f32>);

/// `a` or `c` of `c = a · b`.
#[derive(Clone, Copy)]
enum Operand {
    A,
    C,
}

/// Every GEMM one tower's forward and backward pass make for a batch: conv layers as
/// `policy::nn` runs them (`as_step`: a chunk of samples at a time, each thread on its share)
/// or as whole-batch products.
fn gemm_shapes(net: &policy::nn::Net, batch: usize, threads: usize, as_step: bool) -> Vec<GemmShape> {
    use policy::nn::Layer;
    let mut out = Vec::new();
    let mut push =
        |m, n, k, a_t, b_t, chunks, streams, add| out.push(GemmShape { m, n, k, a_t, b_t, chunks, streams, add });
    let factored = net.factorable(batch);
    for (i, layer) in net.layers.iter().enumerate() {
        let first = !net.layers[..i].iter().any(|l| l.param_count() > 0);
        match *layer {
            Layer::Dense { inp, out: o, .. } => {
                // Forward: onto the bias, turned as `Net::forward` makes it; the weight
                // gradient: added into the gradient, or for a factored layer multiplied out by
                // the optimiser into its buffer; the input gradient: into a buffer of its own.
                if policy::nn::turns_dense_forward(batch) {
                    push(o, batch, inp, false, true, 0, Operand::C, true);
                } else {
                    push(batch, o, inp, false, true, 0, Operand::C, true);
                }
                push(o, inp, batch, true, false, 0, Operand::A, !factored.contains(&i));
                if !first {
                    push(batch, inp, o, false, false, 0, Operand::C, false);
                }
            }
            Layer::Conv2d { filters, .. } => {
                let [oh, ow] = layer.conv_out();
                let kkc = layer.param_count() / filters - 1;
                let (samples, chunks) = if as_step {
                    let threads = threads.clamp(1, batch);
                    let chunk = layer.conv_chunk().min(batch);
                    (chunk, batch.div_ceil(threads).div_ceil(chunk))
                } else {
                    (batch, 0)
                };
                let rows = samples * oh * ow;
                // Forward: outputs (rows × filters) out; weight gradient: dᵀ (filters × rows)
                // in; input gradient: d (rows × filters) in, the unfolded gradient (in
                // cache) out.
                // (Onto the bias, added into the weight gradient, into the unfolded gradient.)
                push(rows, filters, kkc, false, true, chunks, Operand::C, true);
                push(filters, kkc, rows, true, false, chunks, Operand::A, true);
                if !first {
                    push(rows, kkc, filters, false, false, chunks, Operand::A, false);
                }
            }
            _ => {}
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::{bench_metadata, gemm_shapes, median};
    use rand::SeedableRng;

    /// Issue 8: the ceiling makes the step's GEMMs as the step makes them: a product
    /// read-modify-writes its output only where the step's does (adding into every output
    /// would read 23 MB a tower more than the step does for the big dense layer's weight
    /// gradient).
    #[test]
    fn the_ceilings_gemms_add_into_their_output_only_where_the_steps_do() {
        let (_, _, meta) = bench_metadata("SHALLOW").unwrap();
        let model = policy::ActorCritic::new(&meta, 27, &mut rand_chacha::ChaCha8Rng::seed_from_u64(1));
        let got: Vec<_> = gemm_shapes(&model.pi, 64, 1, true).iter().map(|s| (s.m, s.n, s.k, s.add)).collect();
        #[rustfmt::skip]
        let want = [
            // conv 8×8/4: forward onto the bias, weight gradient added (no input gradient)
            (1131, 32, 64, true), (32, 64, 1131, true),
            // conv 4×4/2 and 3×3/1: and the unfolded input gradient written afresh
            (234, 64, 512, true), (64, 512, 234, true), (234, 512, 64, false),
            (176, 64, 576, true), (64, 576, 176, true), (176, 576, 64, false),
            // dense 11,264 → 512: forward as outᵀ = W · xᵀ, onto the bias; its weight gradient
            // multiplied out into the optimiser's buffer
            (512, 64, 11264, true), (512, 11264, 64, false), (64, 11264, 512, false),
            // dense 512 → 5: its weight gradient added into the gradient
            (5, 64, 512, true), (5, 512, 64, true), (64, 512, 5, false),
        ];
        assert_eq!(got, want);
    }

    #[test]
    fn median_of_odd_and_even_counts_whatever_the_order() {
        assert_eq!(median(vec![3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(vec![4.0, 1.0, 3.0, 2.0]), 2.5);
        assert_eq!(median(vec![7.0]), 7.0);
        assert!(median(Vec::new()).is_nan());
    }
}
