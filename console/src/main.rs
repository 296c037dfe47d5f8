//! `console`: Paddock's web console. On one machine (no `--connect`) it starts and supervises
//! a coordinator, a learner and sim agents on loopback, as `coordinator up` does, and serves
//! the console beside them; with `--connect` it serves the console of a running cluster
//! (`coordinator serve --console ADDR` starts it so). `./paddock console` runs it.

use anyhow::{Context, Result};
use clap::Parser;
use coordinator::supervise::{Children, free_port, sibling, spawn, write_pids};
use protocol::net::NetArgs;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

/// Paddock's web console: create, train, watch, evaluate and download models in a browser.
#[derive(Parser)]
#[command(name = "console", version, args_conflicts_with_subcommands = true)]
struct Cli {
    #[command(subcommand)]
    command: Option<Sub>,
    /// Where the console listens (beyond loopback only with --tls-cert and users, or --insecure;
    /// port 0 picks a free one).
    #[arg(long, default_value = "127.0.0.1:8100")]
    listen: SocketAddr,
    /// The data folder: models, their files and runs, and (on one machine) the job database
    /// and the roles' logs. Kept across restarts.
    #[arg(long, default_value = "paddock-data")]
    data: PathBuf,
    /// Sim agent processes to start (on one machine).
    #[arg(long, default_value_t = 2)]
    agents: usize,
    /// Environments per agent (on one machine).
    #[arg(long, default_value_t = 16)]
    envs: usize,
    /// Where the learner's network maths run (on one machine): auto, cpu or gpu.
    #[arg(long, default_value = "auto")]
    device: String,
    /// Seconds between the learner's evaluations and checkpoints (on one machine).
    #[arg(long, default_value_t = 2.0)]
    checkpoint_seconds: f64,
    /// A running cluster's coordinator (Zenoh endpoint): serve its console, start nothing.
    #[arg(long)]
    connect: Vec<String>,
    /// The cluster's credentials folder (as the CLI's `--certs`).
    #[arg(long, value_name = "DIR")]
    certs: Option<PathBuf>,
    /// Listen beyond loopback without TLS and login (anyone who sees the token can use it).
    #[arg(long)]
    insecure: bool,
    /// Serve HTTPS with this certificate (PEM, the chain; `coordinator certs issue DIR console
    /// NAME` writes DIR/console-NAME.pem from the cluster's CA). Needed beyond loopback.
    #[arg(long, value_name = "FILE", requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// The certificate's private key (PEM).
    #[arg(long, value_name = "FILE", requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// The token (a new random one when not given). For scripts; the printed address carries it.
    /// Only while the data folder has no users: with users, the console asks for a login.
    #[arg(long)]
    token: Option<String>,
    /// Make this user the first admin when the data folder has no user (the console then asks
    /// for a login); its password is printed once unless --admin-password-file gives it.
    #[arg(long, value_name = "NAME")]
    admin: Option<String>,
    /// The key the learner signs models with (on one machine; `coordinator keys new NAME`
    /// writes NAME.key): cars drive only signed models. With --certs, the cluster's models key
    /// there is used.
    #[arg(long, value_name = "FILE")]
    signing_key: Option<PathBuf>,
    /// Race entries evaluated at once (each drives its laps side by side on every core).
    #[arg(long, default_value_t = 2)]
    race_workers: usize,
    /// Live races replay each entry at this many simulator seconds a second (1: as driven).
    #[arg(long, default_value_t = 1.0, value_parser = speed)]
    live_speed: f64,
    /// The first admin's password (the file's first line).
    #[arg(long, value_name = "FILE", requires = "admin")]
    admin_password_file: Option<PathBuf>,
}

#[derive(clap::Subcommand)]
enum Sub {
    /// The console's figures: Submit to the first point on the graph, the page's weight and
    /// first paint, and what N viewers of the live page cost the training (with a verdict).
    Bench(paddock_console::bench::BenchArgs),
    /// The console's users (`coordinator users` runs this): add, invite, role, quota, remove, list.
    Users(UsersArgs),
}

#[derive(clap::Args)]
struct UsersArgs {
    #[command(subcommand)]
    command: UsersCommand,
    /// The console's data folder.
    #[arg(long, global = true, default_value = "paddock-data")]
    data: PathBuf,
}

#[derive(clap::Subcommand)]
enum UsersCommand {
    /// Add a user with a password (the file's first line; without one, a new password is
    /// printed once).
    Add {
        name: String,
        #[arg(long, default_value = "racer", value_parser = ["admin", "facilitator", "racer"])]
        role: String,
        #[arg(long, value_name = "FILE")]
        password_file: Option<PathBuf>,
    },
    /// Invite a user: prints the link at which they set their password.
    Invite {
        name: String,
        #[arg(long, default_value = "racer", value_parser = ["admin", "facilitator", "racer"])]
        role: String,
        /// Hours the invitation lasts.
        #[arg(long, default_value_t = 168.0)]
        hours: f64,
        /// The console's address, for the link.
        #[arg(long, default_value = "http://127.0.0.1:8100")]
        url: String,
    },
    /// Change a user's role.
    Role {
        name: String,
        #[arg(value_parser = ["admin", "facilitator", "racer"])]
        role: String,
    },
    /// Set a user's quota, or with --instance every user's together: models and minutes of
    /// training and evaluation (`unlimited` lifts one).
    Quota {
        #[arg(required_unless_present = "instance")]
        name: Option<String>,
        #[arg(long, conflicts_with = "name")]
        instance: bool,
        #[arg(long)]
        models: Option<String>,
        #[arg(long)]
        minutes: Option<String>,
    },
    /// Remove a user (their models stay).
    Remove { name: String },
    /// List the users.
    List,
}

fn users_cmd(args: &UsersArgs) -> Result<i32> {
    use paddock_console::users::{Role, Users, new_password};
    std::fs::create_dir_all(&args.data).with_context(|| format!("--data {}", args.data.display()))?;
    let users = Users::open(&args.data)?;
    let role = |r: &str| Role::parse(r).map_err(anyhow::Error::from);
    match &args.command {
        UsersCommand::Add { name, role: r, password_file } => {
            let (password, printed) = match password_file {
                Some(f) => {
                    let text =
                        std::fs::read_to_string(f).with_context(|| format!("--password-file {}", f.display()))?;
                    (text.lines().next().unwrap_or("").to_string(), false)
                }
                None => (new_password(), true),
            };
            let u = users.add(name, role(r)?, &password)?;
            println!("added {} ({})", u.name, u.role.name());
            if printed {
                println!("password {password} (shown once: give it to {name})");
            }
        }
        UsersCommand::Invite { name, role: r, hours, url } => {
            let secret = users.invite(name, role(r)?, hours * 3600.0)?;
            println!("{}/invite/{secret}", url.trim_end_matches('/'));
        }
        UsersCommand::Role { name, role: r } => {
            let u = users.set_role(name, role(r)?)?;
            println!("{} is now {}", u.name, u.role.name());
        }
        UsersCommand::Quota { name, instance, models, minutes } => {
            let name = name.as_deref().filter(|_| !instance);
            let mut q = match name {
                Some(n) => users.get(n).ok_or_else(|| paddock_console::users::UsersError::NotFound(n.into()))?.quota,
                None => users.instance_quota(),
            };
            let limit = |flag: &str, v: &str| -> Result<Option<f64>> {
                if v == "unlimited" {
                    return Ok(None);
                }
                v.parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite() && *x >= 0.0)
                    .map(Some)
                    .with_context(|| format!("--{flag} {v}: expected a number, 0 or more, or 'unlimited'"))
            };
            if let Some(m) = models {
                q.models = limit("models", m)?.map(|x| x as u32);
            }
            if let Some(m) = minutes {
                q.minutes = limit("minutes", m)?;
            }
            let (who, q) = match name {
                Some(n) => (n.to_string(), users.set_quota(n, q)?.quota),
                None => ("the instance".to_string(), users.set_instance_quota(q)?),
            };
            let show = |x: Option<String>| x.unwrap_or_else(|| "unlimited".into());
            println!(
                "{who}: models {}, minutes {}",
                show(q.models.map(|m| m.to_string())),
                show(q.minutes.map(|m| m.to_string()))
            );
        }
        UsersCommand::Remove { name } => {
            users.remove(name)?;
            println!("removed {name}");
        }
        UsersCommand::List => {
            println!("{:<24} {:<12} {:>7} {:>9}  STATE", "USER", "ROLE", "MODELS", "MINUTES");
            for u in users.list() {
                let q = |x: Option<String>| x.unwrap_or_else(|| "-".into());
                println!(
                    "{:<24} {:<12} {:>7} {:>9}  {}",
                    u.name,
                    u.role.name(),
                    q(u.quota.models.map(|m| m.to_string())),
                    q(u.quota.minutes.map(|m| m.to_string())),
                    if u.password.is_some() { "active" } else { "invited" }
                );
            }
        }
    }
    Ok(0)
}

fn main() {
    protocol::secure::init_process("warn,zenoh=error,console=info,coordinator=info");
    let cli = Cli::parse();
    let result = match &cli.command {
        Some(Sub::Bench(args)) => paddock_console::bench::run(args),
        Some(Sub::Users(args)) => users_cmd(args),
        None => run(cli).map(|()| 0),
    };
    protocol::exit::exit(result)
}

fn run(cli: Cli) -> Result<()> {
    let store = paddock_console::store::Store::open(&cli.data)?;
    let users = paddock_console::users::Users::open(store.root())?;
    if let Some(name) = &cli.admin {
        paddock_console::first_admin(&users, name, cli.admin_password_file.as_deref())?;
    }
    paddock_console::check_listen(&cli.listen, cli.insecure, cli.tls_cert.is_some(), users.any())?;
    if let (Some(cert), Some(key)) = (&cli.tls_cert, &cli.tls_key) {
        paddock_console::tls::server_config(cert, key)?;
    }
    let certs = cli
        .certs
        .as_deref()
        .map(|d| d.canonicalize().with_context(|| format!("--certs {}", d.display())))
        .transpose()?;
    let mut children = Children(Vec::new());
    let connect = if cli.connect.is_empty() {
        let endpoint = start_roles(&cli, store.root(), certs.as_deref(), &mut children)?;
        vec![endpoint]
    } else {
        cli.connect.clone()
    };
    let local = cli.connect.is_empty();
    let hub = paddock_console::hub::Hub::start(&NetArgs { connect, certs, ..Default::default() })?;
    // On one machine the console opens once its coordinator answers; a cluster's console
    // opens at once and says on its pages when the coordinator does not answer.
    if local && !hub.wait_listed(Duration::from_secs(60)) {
        anyhow::bail!(
            "the coordinator did not answer within 60 s; see {}",
            store.root().join("logs/coordinator.log").display()
        );
    }
    // The roles are supervised while the console serves: one that exits is started again.
    let supervised = std::sync::Arc::new(std::sync::Mutex::new(children));
    {
        let s = supervised.clone();
        let logs = store.root().join("logs");
        std::thread::spawn(move || {
            loop {
                std::thread::sleep(Duration::from_secs(1));
                let mut c = s.lock().expect("roles");
                match c.supervise() {
                    Ok(events) => {
                        for e in events {
                            tracing::warn!("{e}");
                        }
                    }
                    Err(e) => tracing::error!("{e:#}"),
                }
                if !c.0.is_empty() {
                    let _ = write_pids(&logs, &c);
                }
            }
        });
    }
    let opts = paddock_console::Options {
        listen: cli.listen,
        insecure: cli.insecure,
        token: cli.token,
        race_workers: cli.race_workers,
        live_speed: cli.live_speed,
        tls: cli.tls_cert.clone().zip(cli.tls_key.clone()),
    };
    let served = paddock_console::serve(opts, store, hub);
    // The roles stop with the console.
    drop(std::mem::replace(&mut *supervised.lock().expect("roles"), Children(Vec::new())));
    served
}

/// Start a coordinator (its database in the data folder), a learner and the agents on
/// loopback; the coordinator's endpoint.
fn start_roles(
    cli: &Cli,
    data: &std::path::Path,
    certs: Option<&std::path::Path>,
    children: &mut Children,
) -> Result<String> {
    let logs = data.join("logs");
    std::fs::create_dir_all(&logs).with_context(|| format!("making {}", logs.display()))?;
    let port = free_port()?;
    let endpoint = format!("{}/127.0.0.1:{port}", if certs.is_some() { "tls" } else { "tcp" });
    let common: Vec<String> = certs.iter().flat_map(|d| ["--certs".to_string(), d.display().to_string()]).collect();
    let coordinator = sibling("coordinator")?;
    let db = data.join("coordinator.redb").display().to_string();
    let s = |v: &[&str]| v.iter().map(|x| x.to_string()).collect::<Vec<String>>();
    spawn(
        children,
        "coordinator",
        &coordinator,
        &s(&["serve", "--listen", &endpoint, "--db", &db]),
        &common,
        &logs.join("coordinator.log"),
    )?;
    let checkpoint = cli.checkpoint_seconds.to_string();
    let mut learner = s(&[
        "serve",
        "--connect",
        &endpoint,
        "--id",
        "learner-1",
        "--checkpoint-seconds",
        &checkpoint,
        "--device",
        &cli.device,
        // The agents run on this machine, and no other learner reaches its coordinator.
        "--checks-first",
        "--alone",
    ]);
    if let Some(k) = &cli.signing_key {
        let k = k.canonicalize().with_context(|| format!("--signing-key {}", k.display()))?;
        learner.extend(["--signing-key".to_string(), k.display().to_string()]);
    }
    spawn(children, "learner", &sibling("learner")?, &learner, &common, &logs.join("learner.log"))?;
    let threads = (std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1) / cli.agents.max(1)).max(1);
    for i in 1..=cli.agents {
        let id = format!("agent-{i}");
        spawn(
            children,
            &id,
            &sibling("sim-agent")?,
            &s(&[
                "serve",
                "--connect",
                &endpoint,
                "--id",
                &id,
                "--envs",
                &cli.envs.to_string(),
                "--threads",
                &threads.to_string(),
                "--device",
                &cli.device,
            ]),
            &common,
            &logs.join(format!("{id}.log")),
        )?;
    }
    write_pids(&logs, children)?;
    println!(
        "roles        coordinator on {endpoint}, learner-1, {} agent(s) x {} envs; logs in {}",
        cli.agents,
        cli.envs,
        logs.display()
    );
    Ok(endpoint)
}

fn speed(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(x) if (0.1..=100.0).contains(&x) => Ok(x),
        _ => Err(format!("'{s}': expected a number from 0.1 to 100")),
    }
}
