//! `coordinator`: Paddock's user-facing command.
//!
//! The track catalog (`tracks list|show|import`), reward validation (`reward validate`),
//! the scripted driver (`drive`), PPO in one process (`train`, `evaluate`, `clone`), and the
//! cluster: the coordinator role (`serve`), job control (`job …`, `agents`) and the
//! one-machine launcher (`up`), reports of a run (`report`, `job report`).

/// mimalloc hands freed pages back to the system (glibc's malloc keeps them in its arenas),
/// at once in `serve` ([`protocol::secure::purge_freed_memory_after`]): a long run's resident
/// memory follows what it holds, not its highest peak. `main` turns transparent huge pages
/// off, which would make them resident again.
/// mimalloc, counting the bytes allocations hold (no limit): `job status` shows them beside
/// the resident memory, which also holds what the allocator keeps back.
#[global_allocator]
static ALLOCATOR: cap::Cap<mimalloc::MiMalloc> = cap::Cap::new(mimalloc::MiMalloc, usize::MAX);

mod bench;
mod carmodel;
mod cars;
use coordinator::certs;
mod cli;
mod client;
mod drive;
mod fuzz_bench;
mod local;
mod race_cmd;
mod render_cmd;
mod report;
mod scale;
mod serve;
mod soak;
mod tracks_cmd;
mod train;
mod up;

use clap::Parser;

fn main() {
    let cli = cli::Cli::parse();
    if matches!(cli.command, cli::Command::Serve(_)) {
        // The coordinator role runs for days and computes little: freed memory goes back at once.
        protocol::secure::purge_freed_memory_after(0);
    }
    // Paddock's own messages; the libraries' warnings (Zenoh's scouting chatter) only when
    // RUST_LOG asks for them.
    protocol::secure::init_process("warn,zenoh=error,coordinator=info,sim_agent=info");
    // The camera on a headless NVIDIA server (sim_agent::icd), before any thread starts.
    sim_agent::icd::headless_nvidia();
    let result = match cli.command {
        cli::Command::Tracks { command } => tracks_cmd::run(command),
        cli::Command::Reward { command } => match command {
            cli::RewardCommand::Validate(args) => drive::validate(args),
            cli::RewardCommand::Export { reward, world, out } => drive::export(&reward, &world, &out),
        },
        cli::Command::Drive(args) => drive::drive(args),
        cli::Command::Train(args) => train::train(args),
        cli::Command::Evaluate(args) => train::evaluate_cmd(args),
        cli::Command::Race(args) => race_cmd::race(args),
        cli::Command::Clone(args) => train::clone_cmd(args),
        cli::Command::Serve(a) => (|| -> anyhow::Result<i32> {
            let _console = a.console.as_deref().map(|addr| console_beside(&a, addr)).transpose()?;
            serve::serve(serve::ServeArgs {
                net: client::net_args(&a.net, false).as_role(protocol::secure::Role::Coordinator),
                db: a.db,
                join_listen: a.join_listen,
            })?;
            Ok(0)
        })(),
        cli::Command::Console { args } => console(&args),
        cli::Command::Users { args } => console(&[vec!["users".to_string()], args].concat()),
        cli::Command::Job { command } => client::run(command),
        cli::Command::Agents { net } => client::run(cli::JobCommand::Agents { net }),
        cli::Command::Up(args) => up::up(args),
        cli::Command::Render(args) => render_cmd::render(args),
        cli::Command::Report { run, out } => (|| -> anyhow::Result<i32> {
            let title = format!("Paddock run {}", run.display());
            let page = report::write(&run, out.as_deref(), &title)?;
            println!("report       {}", page.display());
            Ok(0)
        })(),
        cli::Command::Keys { command: cli::KeysCommand::New { name } } => cars::new_keys(&name),
        cli::Command::Certs { command: cli::CertsCommand::Slots { dir, slots } } => certs::slots(&dir, &slots.list()).map(|t| {
            println!("{t}");
            0
        }),
        cli::Command::Token { command } => client::token(command),
        cli::Command::Service { command: cli::ServiceCommand::Print { role, bin, memory_max, args } } => {
            (|| -> anyhow::Result<i32> {
                let bin = match bin {
                    Some(b) => b,
                    None => protocol::service::sibling_binary(&role)?,
                };
                print!("{}", protocol::service::unit(&role, &bin, &memory_max, &args)?);
                Ok(0)
            })()
        }
        cli::Command::Certs { command: cli::CertsCommand::New { dir, force, slots } } => certs::write(&dir, force, &slots.list()).map(|names| {
            println!("wrote {} in {}", names.join(", "), dir.display());
            println!("each role takes --certs DIR with ca.pem and its own <role>.pem and <role>.key; endpoints are tls/HOST:PORT");
            println!(
                "learners sign models with models.key (only their machines need it); agents and cars trust models.pub"
            );
            0
        }),
        cli::Command::Certs { command: cli::CertsCommand::Issue { dir, role, ids, days } } if role == "console" => {
            certs::issue_console(&dir, &ids, days).map(|names| {
                println!("wrote {} in {}", names.join(", "), dir.display());
                println!("give the console --tls-cert DIR/console-NAME.pem --tls-key DIR/console-NAME.key; browsers trust it once they trust ca.pem");
                0
            })
        }
        cli::Command::Certs { command: cli::CertsCommand::Issue { dir, role, ids, days } } => {
            certs::issue(&dir, &role, &ids, days).map(|names| {
                println!("wrote {} and ids.toml in {}", names.join(", "), dir.display());
                println!(
                    "copy ca.pem, ids.toml and a machine's two files to it; give every node the new ids.toml (each reads it when it joins)"
                );
                0
            })
        }
        cli::Command::Certs { command: cli::CertsCommand::Revoke { dir, names } } => {
            certs::revoke(&dir, &names).map(|done| {
                for (name, new) in done {
                    println!("{} {name}", if new { "revoked" } else { "already revoked" });
                }
                println!(
                    "wrote {}: a coordinator running with --certs {} hands it to every node",
                    dir.join(protocol::revocation::CRL_FILE).display(),
                    dir.display()
                );
                0
            })
        }
        cli::Command::Certs { command: cli::CertsCommand::List { dir } } => certs::list(&dir).map(|rows| {
            for r in rows {
                println!("{r}");
            }
            0
        }),
        cli::Command::Cars(args) => cars::cars(args),
        cli::Command::Export { model, car, onnx, r#virtual, virtual_dir, deepracer } => (|| -> anyhow::Result<i32> {
            if r#virtual.is_some() || virtual_dir.is_some() {
                carmodel::export_virtual(&model, r#virtual.as_deref(), virtual_dir.as_deref(), &deepracer)?;
            }
            if let Some(car) = &car {
                carmodel::export_car(&model, car)?;
            }
            if let Some(onnx) = &onnx {
                let f = policy::folder::load(&model)?;
                let bytes = coordinator::onnx::policy_to_onnx(&f.model, &model.display().to_string());
                std::fs::write(onnx, &bytes).map_err(|e| anyhow::anyhow!("{}: {e}", onnx.display()))?;
                println!(
                    "{}: policy v{} as ONNX ({:.1} MB)",
                    onnx.display(),
                    f.manifest.policy_version,
                    bytes.len() as f64 / 1e6
                );
            }
            Ok(0)
        })(),
        cli::Command::Import(args) => carmodel::import(args),
        cli::Command::Bench { command } => match command {
            cli::BenchCommand::Cluster { seconds, envs, world } => bench::cluster(seconds, envs, &world).map(|()| 0),
            cli::BenchCommand::LongJob { minutes, trials, out } => bench::long_job(minutes, trials, &out),
            cli::BenchCommand::Scale { machines, rounds, out } => scale::scale(&machines, rounds, &out),
            cli::BenchCommand::ScaleReceive { net, record } => scale::receive(client::net_args(&net, false), &record),
            cli::BenchCommand::ScaleSend { net, rounds, record } => {
                scale::send(client::net_args(&net, false), rounds, &record)
            }
            cli::BenchCommand::Soak(args) => soak::soak(args),
            cli::BenchCommand::ModelFiles { repeats } => bench::model_files(repeats).map(|()| 0),
            cli::BenchCommand::Publish { repeats } => bench::publish(repeats).map(|()| 0),
            cli::BenchCommand::Races(args) => bench::races(&args),
            cli::BenchCommand::Generated { family, unseen, sensor, minutes, seed, out } => {
                bench::generated(family, &unseen, &sensor, minutes, seed, &out)
            }
            cli::BenchCommand::Schedule { worlds, sensor, minutes, seeds, out } => {
                bench::schedule(&worlds, &sensor, minutes, &seeds, &out)
            }
            cli::BenchCommand::RaceLine { world, minutes, sensors, seed, out } => {
                bench::race_line(&world, minutes, &sensors, seed, &out)
            }
            cli::BenchCommand::Sac { world, minutes, sensors, agents, seed, out } => {
                bench::sac(&world, minutes, &sensors, &agents, seed, &out)
            }
            cli::BenchCommand::Fuzz { seconds, targets, sanitizer } => fuzz_bench::run(seconds, &targets, &sanitizer),
            cli::BenchCommand::Record { seconds, rounds } => bench::record(seconds, rounds).map(|()| 0),
            cli::BenchCommand::Wire { seconds, rounds, up_seconds } => bench::wire(seconds, rounds, up_seconds).map(|()| 0),
            cli::BenchCommand::Pixels(args) => bench::pixels(&args).map(|()| 0),
        },
    };
    protocol::exit::exit(result)
}

/// `coordinator console …` and `coordinator users …`: the `console` binary in this process's
/// place.
fn console(args: &[String]) -> anyhow::Result<i32> {
    use std::os::unix::process::CommandExt as _;
    let bin = coordinator::supervise::sibling("console")?;
    let e = std::process::Command::new(&bin).args(args).exec();
    Err(anyhow::anyhow!("starting {}: {e}", bin.display()))
}

/// `serve --console ADDR`: the console as a child of the coordinator, connected to its first
/// listen endpoint (on loopback when it listens on every address); killed when serve ends.
fn console_beside(a: &cli::ServeCli, addr: &str) -> anyhow::Result<Beside> {
    let listen = a.net.listen.first().ok_or_else(|| {
        anyhow::anyhow!("--console needs --listen ENDPOINT (for example tcp/127.0.0.1:7447): the console reaches the coordinator there")
    })?;
    let endpoint = listen.replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]");
    let data =
        a.db.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(std::path::Path::new(".")).join("console-data");
    let mut args: Vec<String> =
        ["--connect", &endpoint, "--listen", addr, "--data"].iter().map(|s| s.to_string()).collect();
    args.push(data.display().to_string());
    if let Some(c) = &a.net.certs {
        args.extend(["--certs".to_string(), c.display().to_string()]);
    }
    if a.net.insecure {
        args.push("--insecure".into());
    }
    let bin = coordinator::supervise::sibling("console")?;
    // Its output goes where serve's goes: the address with its token is printed there.
    let child = std::process::Command::new(&bin)
        .args(&args)
        .spawn()
        .map_err(|e| anyhow::anyhow!("starting {}: {e}", bin.display()))?;
    tracing::info!(%addr, "console started beside the coordinator");
    Ok(Beside(child))
}

/// A process that ends with this one.
struct Beside(std::process::Child);

impl Drop for Beside {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}
