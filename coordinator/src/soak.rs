//! `coordinator bench soak`: a cluster run long under churn, measured every `--sample-s`. The
//! README's kind of job (two worlds from pixels, two agents) on loopback with the cluster's
//! credentials: the agents join with tokens; agent 1 is killed every `--kill-every` minutes and
//! its certificate lives `--cert-minutes` (it expires during the run and the machine joins
//! again); agent 2 is revoked and joins again every `--rejoin-every`, and lives long between.
//! Each role's private resident memory (its binary's pages apart: they are read in as code
//! first runs), threads, open files and sockets, the steps/s the learner got, the agents' step
//! time (their CPU per environment step), the policy version, the stale and refused counts,
//! and the bytes the coordinator's allocations hold go to `soak.csv` each sample and to
//! `soak.svg`; the verdict comes from the slopes
//! after the warm-up, each weighed with its standard error, and from the learner's own record
//! of its memory after each update. Episodes are capped (`--episode-steps`), so that the work
//! per update holds steady once the car drives. The agents' CPU includes their evaluations,
//! which the steps they are divided by do not: a bounded, periodic share with capped episodes.

use crate::cli::UpArgs;
use crate::client::request;
use anyhow::{Context, Result, bail};
use coordinator::supervise::{Children, free_port, sibling, spawn};
use protocol::job_request::Kind;
use protocol::net::{self, NetArgs};
use protocol::secure::Role;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// What `bench soak` is given.
#[derive(clap::Args, Debug)]
pub struct SoakArgs {
    /// Minutes of the run.
    #[arg(long, default_value_t = 60.0)]
    pub minutes: f64,
    /// Seconds between samples.
    #[arg(long, default_value_t = 60.0)]
    pub sample_s: f64,
    /// Minutes between kills of agent 1 (0: none).
    #[arg(long, default_value_t = 15.0)]
    pub kill_every: f64,
    /// Minutes between a machine revoked and joined again (0: none).
    #[arg(long, default_value_t = 60.0)]
    pub rejoin_every: f64,
    /// Minutes agent 1's certificates live, so they expire during the run (0: a year).
    #[arg(long, default_value_t = 25.0)]
    pub cert_minutes: f64,
    /// Minutes at the start (and of each process's life) left out of the slopes.
    #[arg(long, default_value_t = 5.0)]
    pub warmup: f64,
    /// Rounds of churn inside the warm-up, each an agent killed and a machine revoked and
    /// joined again, spread evenly from its first minute. The coordinator's allocator grows at
    /// each kind of event until it has seen about a dozen (docs/benchmarks.md, "A cluster for
    /// days"), so the slopes after judge what each further event costs.
    #[arg(long, default_value_t = 0)]
    pub warmup_churn: usize,
    /// Environments per agent.
    #[arg(long, default_value_t = 4)]
    pub envs: usize,
    /// Steps an episode may last (0: DeepRacer's cap): episodes stop lengthening as the car
    /// learns soon after the warm-up, so the work per update holds steady and a slope is a
    /// leak or a drift, not a growing batch.
    #[arg(long, default_value_t = 200)]
    pub episode_steps: u64,
    /// The run's folder.
    #[arg(long, default_value = "runs/bench-soak")]
    pub out: PathBuf,
}

/// One process's figures from /proc.
#[derive(Clone, Copy, Default)]
struct Proc {
    /// Private resident memory (`RssAnon`): the heap and the stacks, where a leak shows.
    anon_kb: f64,
    /// Resident pages of files (`RssFile`): the binary's code and data, read in as code first
    /// runs (a churn's paths) and dropped under pressure; bounded by the binary's size.
    file_kb: f64,
    threads: f64,
    files: f64,
    sockets: f64,
    /// CPU seconds used so far (user and system).
    cpu_s: f64,
}

/// Clock ticks per second of `/proc/PID/stat`'s times (USER_HZ: 100 in every Linux ABI).
const USER_HZ: f64 = 100.0;

fn proc_of(pid: u32) -> Proc {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    let field = |k: &str| {
        status
            .lines()
            .find(|l| l.starts_with(k))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(f64::NAN)
    };
    let (mut files, mut sockets) = (0.0, 0.0);
    for e in std::fs::read_dir(format!("/proc/{pid}/fd")).into_iter().flatten().flatten() {
        files += 1.0;
        if std::fs::read_link(e.path()).is_ok_and(|l| l.to_string_lossy().starts_with("socket:")) {
            sockets += 1.0;
        }
    }
    // utime and stime: the 12th and 13th fields after the command's closing parenthesis.
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    let ticks: Option<f64> = stat.rsplit_once(')').and_then(|(_, rest)| {
        let f: Vec<&str> = rest.split_whitespace().collect();
        Some(f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?)
    });
    Proc {
        anon_kb: field("RssAnon:"),
        file_kb: field("RssFile:"),
        threads: field("Threads:"),
        files,
        sockets,
        cpu_s: ticks.map_or(f64::NAN, |t| t / USER_HZ),
    }
}

/// Minutes at the end of a run without churn: the last event's recovery is seen.
const CHURN_GRACE: f64 = 3.0;

/// Columns per role in the CSV: private memory, threads, open files, sockets, file pages.
const PER_ROLE: usize = 5;

/// The roles sampled, in the CSV's order.
const ROLES: [&str; 4] = ["coordinator", "learner", "agent-1", "agent-2"];

/// A machine's churn: what happened, when (minutes), and when it was seen again.
struct Churn {
    what: String,
    at: f64,
    agent: String,
    recovered: Option<f64>,
}

/// Least-squares slope of `ys` over `xs`.
fn slope(xs: &[f64], ys: &[f64]) -> f64 {
    let n = xs.len() as f64;
    if xs.len() < 2 {
        return f64::NAN;
    }
    let (mx, my) = (xs.iter().sum::<f64>() / n, ys.iter().sum::<f64>() / n);
    let (mut sxy, mut sxx) = (0.0, 0.0);
    for (x, y) in xs.iter().zip(ys) {
        sxy += (x - mx) * (y - my);
        sxx += (x - mx) * (x - mx);
    }
    if sxx == 0.0 { f64::NAN } else { sxy / sxx }
}

/// The slope of `ys` (over `xs` in minutes) as a share of its mean per hour, in %.
fn drift_per_hour(xs: &[f64], ys: &[f64]) -> f64 {
    let mean = ys.iter().sum::<f64>() / ys.len().max(1) as f64;
    slope(xs, ys) * 60.0 / mean * 100.0
}

fn quantile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// Join `agent` (a fresh folder, or again with --force) with a new token valid for
/// `cert_minutes`; returns the id it joined as.
fn join(session: &net::zenoh::Session, out: &Path, agent: &str, cert_minutes: f64) -> Result<String> {
    let create = protocol::TokenCreate {
        role: "agent".into(),
        ttl_s: 600,
        uses: 1,
        name: String::new(),
        cert_valid_s: (cert_minutes * 60.0).round().max(60.0) as u64,
        address: String::new(),
    };
    let r = request(session, Kind::TokenCreate(create), Duration::from_secs(10))?;
    anyhow::ensure!(r.ok, "token create: {}", r.text);
    let o = std::process::Command::new(sibling("sim-agent")?)
        .args(["join", r.text.trim(), "--force", "--certs"])
        .arg(out.join(agent))
        .output()?;
    let text = String::from_utf8_lossy(&o.stdout).to_string();
    anyhow::ensure!(o.status.success(), "{agent} join: {text}{}", String::from_utf8_lossy(&o.stderr));
    text.split_whitespace()
        .skip_while(|w| *w != "agent")
        .nth(1)
        .map(str::to_string)
        .with_context(|| format!("join printed no id: {text}"))
}

/// The warm-up's churn: the next event due at minute `now` once `done` of its `2·rounds` are
/// done, one every `gap` minutes from minute 1, a kill (`true`) and a revocation and join
/// (`false`) in turn.
fn warm_event(now: f64, done: usize, rounds: usize, gap: f64) -> Option<bool> {
    (done < 2 * rounds && now >= 1.0 + done as f64 * gap).then_some(done.is_multiple_of(2))
}

/// `bench soak`.
pub fn soak(a: SoakArgs) -> Result<i32> {
    anyhow::ensure!(a.minutes > a.warmup && a.sample_s >= 5.0, "--minutes must pass --warmup; --sample-s at least 5");
    anyhow::ensure!(a.cert_minutes == 0.0 || a.cert_minutes >= 1.0, "--cert-minutes: 0 (a year) or at least 1");
    // The warm-up's events, from its first minute to half a minute before its end, each given
    // a quarter of a minute at least to recover.
    let warm_gap = (a.warmup - 1.5) / (2 * a.warmup_churn.max(1)) as f64;
    anyhow::ensure!(
        a.warmup_churn == 0 || warm_gap >= 0.25,
        "--warmup-churn {}: its {} events need at least {:.1} minutes of --warmup (a quarter of a minute each, after the first minute)",
        a.warmup_churn,
        2 * a.warmup_churn,
        1.5 + 0.5 * a.warmup_churn as f64
    );
    if a.out.exists() {
        bail!("{} exists: pass another --out, or delete it", a.out.display());
    }
    std::fs::create_dir_all(a.out.join("logs"))?;
    let out = a.out.canonicalize()?;
    let logs = out.join("logs");
    let ca = out.join("ca");
    coordinator::certs::write(&ca, false, &[(Role::Agent, 8), (Role::Learner, 2), (Role::Car, 0)])?;
    let (zport, jport) = (free_port()?, free_port()?);
    let ep = format!("tls/127.0.0.1:{zport}");
    let me = std::env::current_exe()?;
    let s = |v: &[&str]| v.iter().map(|x| x.to_string()).collect::<Vec<String>>();
    let mut children = Children(Vec::new());
    spawn(
        &mut children,
        "coordinator",
        &me,
        &s(&["serve", "--listen", &ep, "--join-listen", &format!("127.0.0.1:{jport}")]),
        &s(&["--db", &out.join("coordinator.redb").display().to_string(), "--certs", &ca.display().to_string()]),
        &logs.join("coordinator.log"),
    )?;
    spawn(
        &mut children,
        "learner",
        &sibling("learner")?,
        &s(&["serve", "--connect", &ep, "--id", "learner-1", "--checkpoint-seconds", "600"]),
        &s(&["--certs", &ca.display().to_string()]),
        &logs.join("learner.log"),
    )?;
    let session = net::open(&NetArgs { connect: vec![ep.clone()], certs: Some(ca.clone()), ..Default::default() })?;
    let t0 = Instant::now();
    while request(&session, Kind::TokenList(true), Duration::from_secs(2)).map(|r| !r.ok).unwrap_or(true) {
        anyhow::ensure!(
            t0.elapsed() < Duration::from_secs(60),
            "the coordinator did not start; see {}",
            logs.display()
        );
        std::thread::sleep(Duration::from_millis(300));
    }
    let agent_args = |i: usize| {
        s(&["serve", "--connect", &ep, "--envs", &a.envs.to_string(), "--threads", "1", "--certs"])
            .into_iter()
            .chain([out.join(format!("agent-{i}")).display().to_string()])
            .collect::<Vec<_>>()
    };
    let mut ids = Vec::new();
    for i in 1..=2 {
        let minutes = if i == 1 && a.cert_minutes > 0.0 { a.cert_minutes } else { 365.0 * 24.0 * 60.0 };
        ids.push(join(&session, &out, &format!("agent-{i}"), minutes)?);
        spawn(
            &mut children,
            &format!("agent-{i}"),
            &sibling("sim-agent")?,
            &agent_args(i),
            &[],
            &logs.join(format!("agent-{i}.log")),
        )?;
    }
    // The job: `up`'s, two worlds from pixels, run past the soak's end.
    #[derive(clap::Parser)]
    struct Up {
        #[command(flatten)]
        up: UpArgs,
    }
    let spec_args = [
        "up",
        "--world",
        "reinvent_carpet",
        "--world",
        "reinvent_concrete",
        "--sensor",
        "camera",
        "--agents",
        "2",
        "--set",
        "record_trace=false",
        "--target-laps",
        "0",
    ];
    let (minutes_arg, envs_arg) = ((a.minutes + 10.0).to_string(), a.envs.to_string());
    let cap = format!("episode.max_steps={}", a.episode_steps);
    let capped: &[&str] = if a.episode_steps > 0 { &["--set", cap.as_str()] } else { &[] };
    let up = <Up as clap::Parser>::try_parse_from(
        spec_args
            .iter()
            .copied()
            .chain(["--minutes", minutes_arg.as_str(), "--envs", envs_arg.as_str()])
            .chain(capped.iter().copied()),
    )?
    .up;
    let spec = out.join("job.toml");
    std::fs::write(&spec, crate::up::job_spec(&up, &out)?)?;
    let job = "soak";
    let doc = coordinator::jobspec::load(&spec, job)?;
    let r = request(&session, Kind::StartJob(doc), Duration::from_secs(10))?;
    anyhow::ensure!(r.ok, "job start: {}", r.text);
    println!(
        "soak: {} min, a sample every {} s, an agent killed every {} min, a machine revoked and joined again every {} \
         min, agent-1's certificates living {} min, {} environments an agent, {}, {} rounds of churn in the {}-minute \
         warm-up; folder {}",
        a.minutes,
        a.sample_s,
        a.kill_every,
        a.rejoin_every,
        a.cert_minutes,
        a.envs,
        if a.episode_steps == 0 {
            "episodes uncapped".to_string()
        } else {
            format!("episodes capped at {} steps", a.episode_steps)
        },
        a.warmup_churn,
        a.warmup,
        out.display()
    );
    let csv_path = out.join("soak.csv");
    let mut csv = String::from("minute");
    for r in ROLES {
        csv.push_str(&format!(",{r}_anon_mb,{r}_threads,{r}_files,{r}_sockets,{r}_file_mb"));
    }
    csv.push_str(
        ",steps_per_s,agent_cpu_ms_per_step,episodes_received,dropped_stale,dropped_bad,dropped_duplicate,refused,env_steps,policy_version,coordinator_live_mb\n",
    );
    let mut rows: Vec<Vec<f64>> = Vec::new();
    let mut lives: Vec<Vec<u64>> = Vec::new();
    let mut churn: Vec<Churn> = Vec::new();
    // The agents' CPU seconds at the last sample, by process id: their CPU per environment
    // step is the step time, whatever share of the time the learner's updates take.
    let mut prev_cpu: Vec<(u64, f64)> = Vec::new();
    let mut prev_sample = 0.0;
    let mut run_dir: Option<PathBuf> = None;
    // The first revocation 0.6 of the way through the first period (a one-period run sees one,
    // clear of the kills at the quarters); a certificate is renewed half a minute after it
    // expired (its links closed meanwhile).
    let (mut next_sample, mut next_kill, mut next_rejoin) = (a.sample_s / 60.0, a.kill_every, a.rejoin_every * 0.6);
    let mut cert_due = if a.cert_minutes > 0.0 { a.cert_minutes + 0.5 } else { f64::INFINITY };
    let mut warm_done = 0usize;
    let bar = indicatif::ProgressBar::new((a.minutes * 60.0) as u64)
        .with_style(indicatif::ProgressStyle::with_template("{elapsed_precise} [{bar:25}] {msg}").expect("template"));
    let start = Instant::now();
    let mut last_status = None;
    let mut steps_now = 0.0;
    let mut prev_env: Option<(f64, f64)> = None;
    let mut next_poll = Instant::now();
    loop {
        std::thread::sleep(Duration::from_secs(1));
        let now = start.elapsed().as_secs_f64() / 60.0;
        if now >= a.minutes {
            break;
        }
        for e in children.supervise()? {
            bar.suspend(|| println!("{e}"));
        }
        // Churn, but none in the last minutes (each must have time to recover).
        let churn_open = now < a.minutes - CHURN_GRACE;
        // The warm-up's rounds: a kill, then a revocation and join, in turn.
        let warm = warm_event(now, warm_done, a.warmup_churn, warm_gap);
        warm_done += usize::from(warm.is_some());
        let regular_kill = churn_open && a.kill_every > 0.0 && now >= next_kill;
        if regular_kill {
            next_kill += a.kill_every;
        }
        if regular_kill || warm == Some(true) {
            // Always agent 1: agent 2's lives, broken only by its revocations, are long enough
            // to judge an agent's memory over.
            let agent = "agent-1".to_string();
            children.restart(&agent)?;
            bar.suspend(|| println!("{now:.1} min: {agent} killed and started again"));
            churn.push(Churn { what: "killed".into(), at: now, agent, recovered: None });
        }
        // Agent 2 is revoked and joins again; agent 1's certificate expires and it joins again.
        for expired in [false, true] {
            let regular = a.rejoin_every > 0.0 && now >= next_rejoin;
            let due = churn_open && if expired { now >= cert_due } else { regular || warm == Some(false) };
            if !due {
                continue;
            }
            let i = usize::from(!expired);
            let agent = format!("agent-{}", i + 1);
            let minutes = if expired {
                cert_due = now + a.cert_minutes + 0.5;
                a.cert_minutes
            } else {
                if regular {
                    next_rejoin += a.rejoin_every;
                }
                coordinator::certs::revoke(&ca, &[format!("agent-{}", ids[i])])?;
                365.0 * 24.0 * 60.0
            };
            ids[i] = join(&session, &out, &agent, minutes)?;
            children.restart(&agent)?;
            let what = if expired { "certificate expired, joined again" } else { "revoked, joined again" };
            bar.suspend(|| println!("{now:.1} min: {agent} {what} as {}", ids[i]));
            churn.push(Churn { what: what.into(), at: now, agent, recovered: None });
        }
        // The agents' figures (as their reports give them to the coordinator) and the job's,
        // every few seconds.
        if next_poll.elapsed() > Duration::ZERO {
            next_poll += Duration::from_secs(5);
            if let Ok(r) = request(&session, Kind::Agents(true), Duration::from_secs(3))
                && let Some(protocol::job_reply::Body::Agents(list)) = r.body
            {
                steps_now = list.agents.iter().map(|s| s.steps_per_s).sum();
                // Recovered: the machine is back under its id, started after the churn, driving.
                for c in churn.iter_mut().filter(|c| c.recovered.is_none()) {
                    let id = &ids[if c.agent == "agent-1" { 0 } else { 1 }];
                    let since = (now - c.at) * 60.0;
                    if list.agents.iter().any(|s| &s.id == id && s.up_s <= since + 1.0 && s.steps_per_s > 0.0) {
                        c.recovered = Some(now);
                    }
                }
            }
            match request(&session, Kind::StatusJobId(job.into()), Duration::from_secs(3))
                .ok()
                .and_then(|r| crate::client::status_of(&r).cloned())
            {
                Some(st) => {
                    if let Some(l) = st.record.as_ref().and_then(|j| j.learner.as_ref()) {
                        if !l.run_dir.is_empty() {
                            run_dir = Some(PathBuf::from(&l.run_dir));
                        }
                        bar.set_message(format!(
                            "v{} episodes {} steps/s {steps_now:.0}",
                            l.policy_version, l.episodes_received
                        ));
                    }
                    last_status = Some(st);
                }
                // Unknown, not stale: the sample leaves the job's figures out.
                None => last_status = None,
            }
        }
        bar.set_position(start.elapsed().as_secs());
        if now >= next_sample {
            next_sample += a.sample_s / 60.0;
            let pids = children.pids();
            lives.push(ROLES.iter().map(|r| pids[*r].as_u64().unwrap_or(0)).collect());
            let mut row = vec![now];
            let mut cpu = Vec::new();
            for r in ROLES {
                let pid = pids[r].as_u64().unwrap_or(0);
                let p = if pid > 0 { proc_of(pid as u32) } else { Proc::default() };
                row.extend([p.anon_kb / 1024.0, p.threads, p.files, p.sockets, p.file_kb / 1024.0]);
                if r.starts_with("agent") {
                    cpu.push((pid, p.cpu_s));
                }
            }
            let learner = last_status.as_ref().and_then(|s| s.record.as_ref()).and_then(|j| j.learner.clone());
            let known = learner.is_some();
            let l = learner.unwrap_or_default();
            let refused: u64 = last_status
                .as_ref()
                .map(|s| s.coordinator_refused.iter().chain(&l.refused).map(|d| d.count).sum())
                .unwrap_or(0);
            // Steps/s end to end: the learner's environment steps since the last sample.
            let env = if known { l.env_steps as f64 } else { f64::NAN };
            let steps = match prev_env {
                Some((t, e)) if env.is_finite() && now > t => (env - e) / ((now - t) * 60.0),
                _ => f64::NAN,
            };
            // The agents' CPU milliseconds per step the learner got since the last sample, when
            // both ran all along and every churn before it had recovered (a kill loses the steps
            // in flight, and a machine starting again spends CPU before it drives). The CPU
            // and the steps are taken at the same two samples.
            let same = prev_cpu.len() == cpu.len() && prev_cpu.iter().zip(&cpu).all(|(p, c)| p.0 == c.0 && c.0 > 0);
            let settled = churn.iter().all(|c| c.recovered.is_some_and(|r| r <= prev_sample));
            let ms_per_step = match prev_env {
                Some((_, e)) if same && settled && env > e => {
                    1000.0 * prev_cpu.iter().zip(&cpu).map(|(p, c)| c.1 - p.1).sum::<f64>() / (env - e)
                }
                _ => f64::NAN,
            };
            if env.is_finite() {
                prev_env = Some((now, env));
                prev_cpu = cpu;
                prev_sample = now;
            }
            row.extend([
                steps,
                ms_per_step,
                if known { l.episodes_received as f64 } else { f64::NAN },
                l.dropped_stale as f64,
                l.dropped_bad as f64,
                l.dropped_duplicate as f64,
                refused as f64,
                env,
                if known { l.policy_version as f64 } else { f64::NAN },
                last_status.as_ref().map(|s| s.coordinator_live_mb).filter(|mb| *mb > 0.0).unwrap_or(f64::NAN),
            ]);
            csv.push_str(&row.iter().map(|v| format!("{v:.3}")).collect::<Vec<_>>().join(","));
            csv.push('\n');
            std::fs::write(&csv_path, &csv)?;
            rows.push(row);
        }
    }
    bar.finish_and_clear();
    let _ = request(&session, Kind::StopJobId(job.into()), Duration::from_secs(5));
    drop(children);
    // The learner's own record of each update: its memory once the batch is freed.
    let metrics: Vec<serde_json::Value> = run_dir
        .map(|d| std::fs::read_to_string(d.join("metrics.jsonl")).unwrap_or_default())
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect();
    if metrics.is_empty() {
        println!("the learner's metrics.jsonl was not found or is empty: its memory is judged from soak.csv");
    }
    verdict(&a, &rows, &lives, &churn, &metrics, &out)
}

/// The worst memory growth (%/h, with its standard error and the minutes it was taken over)
/// over the lives of role `k` (samples with one process id) that run at least [`MIN_LIFE`]
/// minutes past their own warm-up; None when none does.
fn worst_life(a: &SoakArgs, rows: &[Vec<f64>], lives: &[Vec<u64>], k: usize) -> Option<(f64, f64, f64)> {
    let mut worst: Option<(f64, f64, f64)> = None;
    let mut i = 0;
    while i < rows.len() {
        let pid = lives[i][k];
        let mut j = i;
        while j < rows.len() && lives[j][k] == pid {
            j += 1;
        }
        let born = rows[i][0];
        let seg: Vec<&Vec<f64>> =
            rows[i..j].iter().filter(|r| r[0] >= born + a.warmup && r[1 + PER_ROLE * k].is_finite()).collect();
        if pid != 0 && seg.len() >= 3 && seg[seg.len() - 1][0] - seg[0][0] >= MIN_LIFE {
            // The floor of each window: what a process holds between its peaks (a training
            // update's buffers come and go; a leak raises the floor).
            let points: Vec<(f64, f64)> = seg.iter().map(|r| (r[0], r[1 + PER_ROLE * k])).collect();
            let (xs, ys) = windows(&points, 1, |v| v.iter().copied().fold(f64::INFINITY, f64::min));
            if xs.len() >= 3 {
                let g = (drift_per_hour(&xs, &ys), drift_error(&xs, &ys), seg[seg.len() - 1][0] - seg[0][0]);
                worst = Some(worst.map_or(g, |w: (f64, f64, f64)| if g.0 > w.0 { g } else { w }));
            }
        }
        i = j;
    }
    worst
}

/// Minutes a process's life must run past its warm-up for its memory slope to count.
const MIN_LIFE: f64 = 10.0;
/// Minutes of each window whose floor (least resident memory) the memory slope is taken over,
/// whose median step time the steps/s drift, and in which a stall has neither an episode nor
/// an update.
const FLOOR_WINDOW: f64 = 3.0;

/// Windows of [`FLOOR_WINDOW`] minutes over `(minute, value)` points: each window's mean
/// minute and `pick` of its values, for windows of at least `least` points (a window of one
/// noisy sample at the end would pull the slope hardest).
fn windows(points: &[(f64, f64)], least: usize, pick: impl Fn(&mut [f64]) -> f64) -> (Vec<f64>, Vec<f64>) {
    let (mut wx, mut wy) = (Vec::new(), Vec::new());
    let Some(first) = points.first() else { return (wx, wy) };
    for w in points.chunk_by(|p, q| ((p.0 - first.0) / FLOOR_WINDOW) as u64 == ((q.0 - first.0) / FLOOR_WINDOW) as u64)
    {
        if w.len() < least {
            continue;
        }
        wx.push(w.iter().map(|p| p.0).sum::<f64>() / w.len() as f64);
        wy.push(pick(&mut w.iter().map(|p| p.1).collect::<Vec<_>>()));
    }
    (wx, wy)
}

/// A check's outcome: a slope's verdict weighs its standard error.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Judged {
    Pass,
    Fail,
    /// The error is too wide to tell either way: about this many hours of samples would
    /// narrow two standard errors to the limit.
    Undecided(f64),
}

impl From<bool> for Judged {
    fn from(ok: bool) -> Judged {
        if ok { Judged::Pass } else { Judged::Fail }
    }
}

/// A slope `d` ± `e` (%/h, one standard error) measured over `minutes`, against `limit`:
/// passes when two errors above it stay within the limit, fails when two errors below it
/// pass the limit; `both` judges a drift either way (steps/s), otherwise growth alone
/// (memory). A slope's error shrinks as the span's 3/2 power.
fn judge(d: f64, e: f64, limit: f64, minutes: f64, both: bool) -> Judged {
    let d = if both { d.abs() } else { d };
    if !d.is_finite() || !e.is_finite() {
        return Judged::Fail;
    }
    if d + 2.0 * e <= limit {
        Judged::Pass
    } else if d - 2.0 * e > limit {
        Judged::Fail
    } else {
        Judged::Undecided(minutes / 60.0 * (2.0 * e / limit).powf(2.0 / 3.0))
    }
}

/// The standard error of [`drift_per_hour`] (%/h): how far the slope could be off, given how
/// the points scatter about it.
fn drift_error(xs: &[f64], ys: &[f64]) -> f64 {
    let n = xs.len() as f64;
    let (mx, my) = (xs.iter().sum::<f64>() / n, ys.iter().sum::<f64>() / n);
    let b = slope(xs, ys);
    let sxx: f64 = xs.iter().map(|x| (x - mx).powi(2)).sum();
    let res: f64 = xs.iter().zip(ys).map(|(x, y)| (y - my - b * (x - mx)).powi(2)).sum();
    (res / (n - 2.0).max(1.0) / sxx).sqrt() * 60.0 / my * 100.0
}

/// One figure from each of the learner's update records past the warm-up: (minute, value),
/// the records without it left out.
fn updates(
    metrics: &[serde_json::Value],
    warmup: f64,
    figure: impl Fn(&serde_json::Value) -> Option<f64>,
) -> Vec<(f64, f64)> {
    metrics.iter().filter_map(|m| Some((m["time_s"].as_f64()? / 60.0, figure(m)?))).filter(|p| p.0 >= warmup).collect()
}

/// The verdict from the samples after the warm-up (and the learner's `metrics.jsonl`):
/// memory, steps/s, episodes, recoveries.
fn verdict(
    a: &SoakArgs,
    rows: &[Vec<f64>],
    lives: &[Vec<u64>],
    churn: &[Churn],
    metrics: &[serde_json::Value],
    out: &Path,
) -> Result<i32> {
    let after: Vec<&Vec<f64>> = rows.iter().filter(|r| r[0] >= a.warmup).collect();
    anyhow::ensure!(after.len() >= 3, "too few samples after the warm-up ({}) for a slope", after.len());
    let xs: Vec<f64> = after.iter().map(|r| r[0]).collect();
    let col = |i: usize| after.iter().map(|r| r[i]).collect::<Vec<f64>>();
    let base = 1 + PER_ROLE * ROLES.len();
    let mut checks: Vec<(String, String, Judged)> = Vec::new();
    // The learner's memory once each update's batch is freed (its own record): what it keeps.
    let kept = updates(metrics, a.warmup, |m| m["resident_mb"].as_f64());
    // One learner life (a learner started again resumes its metrics.jsonl with less memory).
    let learner_kept =
        kept.len() >= 3 && kept[kept.len() - 1].0 - kept[0].0 >= MIN_LIFE && lives.iter().all(|l| l[1] == lives[0][1]);
    if !learner_kept {
        println!(
            "learner: {} updates recorded their memory past the warm-up, in one life; its floors in soak.csv are judged instead",
            kept.len()
        );
    }
    for (k, r) in ROLES.iter().enumerate() {
        if *r == "learner" && learner_kept {
            let (kx, ky): (Vec<f64>, Vec<f64>) = kept.iter().copied().unzip();
            let (g, e) = (drift_per_hour(&kx, &ky), drift_error(&kx, &ky));
            checks.push((
                "learner: resident memory after each update grows ≤ 1 %/h".into(),
                format!("{g:+.2} ± {e:.2} %/h ({:.0} → {:.0} MB over {} updates)", ky[0], ky[ky.len() - 1], ky.len()),
                judge(g, e, 1.0, kx[kx.len() - 1] - kx[0], false),
            ));
            // What its allocations hold at the same moments (where the binary counts them),
            // less the episodes waiting for the next update (in flight, bounded by the
            // rounds): a leak grows this; the allocator's keeping back only the resident memory.
            let live =
                updates(metrics, a.warmup, |m| Some(m["live_mb"].as_f64()? - m["waiting_mb"].as_f64().unwrap_or(0.0)));
            if live.len() >= 3 {
                let (lx, ly): (Vec<f64>, Vec<f64>) = live.iter().copied().unzip();
                let (g, e) = (drift_per_hour(&lx, &ly), drift_error(&lx, &ly));
                checks.push((
                    "learner: bytes held after each update, the episodes waiting aside, grow ≤ 1 %/h (no leak)".into(),
                    format!("{g:+.2} ± {e:.2} %/h ({:.0} → {:.0} MB)", ly[0], ly[ly.len() - 1]),
                    judge(g, e, 1.0, lx[lx.len() - 1] - lx[0], false),
                ));
            }
        } else {
            // A process's memory starts again with each kill: the slope is taken over each
            // life (one process id) past its warm-up, the worst life reported.
            match worst_life(a, rows, lives, k) {
                Some((g, e, span)) => checks.push((
                    format!("{r}: private memory growth ≤ 1 %/h (worst life, 3-minute floors)"),
                    format!("{g:+.2} ± {e:.2} %/h over {span:.0} min"),
                    judge(g, e, 1.0, span, false),
                )),
                None => println!("{r}: no life ran {MIN_LIFE} min past its warm-up; its memory is not judged"),
            }
        }
        if lives.iter().all(|l| l[k] == lives[0][k]) {
            let th = slope(&xs, &col(2 + PER_ROLE * k)) * 60.0;
            let fd = slope(&xs, &col(3 + PER_ROLE * k)) * 60.0;
            checks.push((
                format!("{r}: threads and open files do not grow"),
                format!("{th:+.1}/h threads, {fd:+.1}/h files"),
                (th <= 1.0 && fd <= 2.0).into(),
            ));
        }
    }
    // What the coordinator's allocations hold (its job status), each window's floor past
    // the warm-up: a leak raises it; the allocator's keeping back only the resident memory.
    let held: Vec<(f64, f64)> = after.iter().map(|r| (r[0], r[base + 9])).filter(|p| p.1.is_finite()).collect();
    let (hx, hy) = windows(&held, 1, |v| v.iter().copied().fold(f64::INFINITY, f64::min));
    if hx.len() >= 3 {
        let (g, e) = (drift_per_hour(&hx, &hy), drift_error(&hx, &hy));
        checks.push((
            "coordinator: bytes held grow ≤ 1 %/h (no leak; 3-minute floors)".into(),
            format!("{g:+.2} ± {e:.2} %/h ({:.1} → {:.1} MB)", hy[0], hy[hy.len() - 1]),
            judge(g, e, 1.0, hx[hx.len() - 1] - hx[0], false),
        ));
    }
    // Steps/s: the simulation's own rate, environment steps per second of the agents' CPU
    // (the median of each window), whatever share of the time the learner's updates take.
    // (The steps the learner gets end to end also follow how long its updates take, which
    // grows with the episodes as the car learns: printed, not judged.)
    let step_ms: Vec<(f64, f64)> =
        after.iter().map(|r| (r[0], r[base + 1])).filter(|p| p.1.is_finite() && p.1 > 0.0).collect();
    let least = ((FLOOR_WINDOW * 60.0 / a.sample_s) as usize / 2).max(1);
    let (wx, wms) = windows(&step_ms, least, |v| quantile(v, 0.5));
    let wy: Vec<f64> = wms.iter().map(|ms| 1000.0 / ms).collect();
    let mean = wy.iter().sum::<f64>() / wy.len().max(1) as f64;
    if wx.len() >= 3 {
        let (d, e) = (drift_per_hour(&wx, &wy), drift_error(&wx, &wy));
        checks.push((
            "steps/s drift ≤ 2 %/h (steps per second of the agents' CPU, window medians)".into(),
            format!("{d:+.2} ± {e:.2} %/h (mean {mean:.0} steps/s over {} windows)", wx.len()),
            judge(d, e, 2.0, wx.last().unwrap_or(&0.0) - wx.first().unwrap_or(&0.0), true),
        ));
    } else {
        // A slope needs three windows: a run this short is not judged on its drift.
        println!("steps/s: {} window(s) past the warm-up, mean {mean:.0} steps/s; its drift is not judged", wx.len());
    }
    let third_of = |v: &[(f64, f64)], part: usize| -> Vec<f64> {
        v[v.len() * part / 3..v.len() * (part + 1) / 3].iter().map(|p| p.1).collect()
    };
    if step_ms.len() >= 3 {
        let (mut first, mut last) = (third_of(&step_ms, 0), third_of(&step_ms, 2));
        println!(
            "step time (the agents' CPU ms per environment step, per sample): p50 {:.2} and p95 {:.2} in the first third, \
             p50 {:.2} and p95 {:.2} in the last",
            quantile(&mut first, 0.5),
            quantile(&mut first, 0.95),
            quantile(&mut last, 0.5),
            quantile(&mut last, 0.95)
        );
    }
    let env: Vec<(f64, f64)> = after.iter().map(|r| (r[0], r[base + 7])).filter(|p| p.1.is_finite()).collect();
    // Each window's last point: the steps by then, and when.
    let (ex, ey) = windows(&env, 1, |v| v.iter().copied().fold(f64::NEG_INFINITY, f64::max));
    let ends: Vec<f64> = ey.iter().map(|y| env.iter().find(|p| p.1 == *y).map_or(f64::NAN, |p| p.0)).collect();
    let rates: Vec<(f64, f64)> = ex
        .windows(2)
        .zip(ey.windows(2).zip(ends.windows(2)))
        .map(|(x, (y, t))| ((x[0] + x[1]) / 2.0, (y[1] - y[0]) / ((t[1] - t[0]) * 60.0)))
        .filter(|p| p.1.is_finite())
        .collect();
    let past_warmup: Vec<&serde_json::Value> =
        metrics.iter().filter(|m| m["time_s"].as_f64().is_some_and(|t| t / 60.0 >= a.warmup)).collect();
    let third = |part: usize| {
        let n = past_warmup.len();
        let m = &past_warmup[n * part / 3..n * (part + 1) / 3];
        let sum = |k: &str| m.iter().filter_map(|x| x[k].as_f64()).sum::<f64>();
        100.0 * sum("update_s") / (sum("update_s") + sum("wait_s")).max(1e-9)
    };
    if rates.len() >= 3 && past_warmup.len() >= 3 {
        let (rx, ry): (Vec<f64>, Vec<f64>) = rates.iter().copied().unzip();
        println!(
            "end to end: the learner got {:.0} steps/s in the first window and {:.0} in the last ({:+.1} %/h); \
             its updates took {:.0} %, {:.0} % and {:.0} % of its time by thirds",
            ry[0],
            ry[ry.len() - 1],
            drift_per_hour(&rx, &ry),
            third(0),
            third(1),
            third(2)
        );
    }
    let last =
        rows.iter().rev().find(|r| r[base + 2].is_finite()).cloned().unwrap_or_else(|| vec![f64::NAN; base + 10]);
    let (bad, dup) = (last[base + 4], last[base + 5]);
    // A stall: a window past the warm-up in which no episode arrived and no update was made
    // (an update takes minutes as episodes grow, and no episode is asked for meanwhile).
    let stalls = rows
        .iter()
        .enumerate()
        .filter(|(j, r)| {
            r[0] >= a.warmup + FLOOR_WINDOW
                && rows[..*j].iter().rev().find(|p| r[0] - p[0] >= FLOOR_WINDOW).is_some_and(|p| {
                    r[base + 2] <= p[base + 2]
                        && r[base + 8].partial_cmp(&p[base + 8]) != Some(std::cmp::Ordering::Greater)
                })
        })
        .count();
    checks.push((
        "no episode lost: none refused as bad or duplicate; no window without an episode or an update".into(),
        format!(
            "{bad:.0} bad, {dup:.0} duplicate, {stalls} samples {FLOOR_WINDOW} min after the last episode and update, {:.0} received",
            last[base + 2]
        ),
        (bad == 0.0 && dup == 0.0 && stalls == 0).into(),
    ));
    let unrecovered: Vec<String> = churn
        .iter()
        .filter(|c| c.recovered.is_none())
        .map(|c| format!("{} {} at {:.1} min", c.agent, c.what, c.at))
        .collect();
    let worst = churn.iter().filter_map(|c| c.recovered.map(|r| (r - c.at) * 60.0)).fold(0.0, f64::max);
    checks.push((
        "every kill, revocation and expiry recovered".into(),
        format!(
            "{} of {} (slowest {worst:.0} s){}",
            churn.len() - unrecovered.len(),
            churn.len(),
            if unrecovered.is_empty() { String::new() } else { format!("; not: {}", unrecovered.join(", ")) }
        ),
        unrecovered.is_empty().into(),
    ));
    chart(rows, out)?;
    println!("| check | figure | verdict |\n|---|---|---|");
    for (what, figure, judged) in &checks {
        let said = match judged {
            Judged::Pass => "pass".to_string(),
            Judged::Fail => "FAIL".to_string(),
            Judged::Undecided(h) => format!("undecided: the error is too wide; about {h:.1} h would tell"),
        };
        println!("| {what} | {figure} | {said} |");
    }
    let pass = checks.iter().all(|c| c.2 == Judged::Pass);
    let failed = checks.iter().any(|c| c.2 == Judged::Fail);
    println!(
        "verdict: {} ({} min, warm-up {} min, {} samples; {} and soak.svg)",
        if pass {
            "PASS"
        } else if failed {
            "FAIL"
        } else {
            "UNDECIDED"
        },
        a.minutes,
        a.warmup,
        rows.len(),
        out.join("soak.csv").display()
    );
    Ok(if pass { 0 } else { 1 })
}

/// `soak.svg`: each role's private memory, and the steps/s, against minutes.
fn chart(rows: &[Vec<f64>], out: &Path) -> Result<()> {
    use plotters::prelude::*;
    let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular());
    let path = out.join("soak.svg");
    let root = SVGBackend::new(&path, (900, 640)).into_drawing_area();
    let e = |x: &dyn std::fmt::Display| anyhow::anyhow!("{}: {x}", path.display());
    root.fill(&WHITE).map_err(|x| e(&x))?;
    let (top, bottom) = root.split_vertically(320);
    let end = rows.last().map_or(1.0, |r| r[0]).max(1.0);
    let max_mb = rows
        .iter()
        .flat_map(|r| (0..ROLES.len()).map(move |k| r[1 + PER_ROLE * k]))
        .filter(|v| v.is_finite())
        .fold(1.0, f64::max);
    let mut c = ChartBuilder::on(&top)
        .caption("private resident memory (MB)", ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(30)
        .y_label_area_size(50)
        .build_cartesian_2d(0f64..end, 0f64..max_mb * 1.1)
        .map_err(|x| e(&x))?;
    c.configure_mesh().x_desc("minutes").draw().map_err(|x| e(&x))?;
    for (k, r) in ROLES.iter().enumerate() {
        let color = Palette99::pick(k).to_rgba();
        c.draw_series(LineSeries::new(
            rows.iter().map(|row| (row[0], row[1 + PER_ROLE * k])).filter(|p| p.1.is_finite()),
            color,
        ))
        .map_err(|x| e(&x))?
        .label(*r)
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], color));
    }
    c.configure_series_labels().border_style(BLACK).background_style(WHITE).draw().map_err(|x| e(&x))?;
    let base = 1 + PER_ROLE * ROLES.len();
    // The agents' steps per CPU-second, on the same axis.
    let per_cpu = |r: &Vec<f64>| 1000.0 / r[base + 1];
    let max_steps = rows.iter().flat_map(|r| [r[base], per_cpu(r)]).filter(|v| v.is_finite()).fold(1.0, f64::max);
    let mut c = ChartBuilder::on(&bottom)
        .caption("environment steps/s: the learner got, and per second of the agents' CPU", ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(30)
        .y_label_area_size(50)
        .build_cartesian_2d(0f64..end, 0f64..max_steps * 1.1)
        .map_err(|x| e(&x))?;
    c.configure_mesh().x_desc("minutes").draw().map_err(|x| e(&x))?;
    // The learner's steps/s, and the agents' steps per CPU-second.
    let series = [(false, BLUE, "the learner got (both agents)"), (true, RED, "per second of the agents' CPU")];
    for (cpu, color, label) in series {
        let y = |r: &Vec<f64>| if cpu { per_cpu(r) } else { r[base] };
        c.draw_series(LineSeries::new(rows.iter().map(|r| (r[0], y(r))).filter(|p| p.1.is_finite()), color))
            .map_err(|x| e(&x))?
            .label(label)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], color));
    }
    c.configure_series_labels().border_style(BLACK).background_style(WHITE).draw().map_err(|x| e(&x))?;
    root.present().map_err(|x| e(&x))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn drift_is_the_slope_as_a_share_of_the_mean_per_hour() {
        let xs: Vec<f64> = (0..60).map(f64::from).collect();
        // 100 MB growing 1 MB an hour: 1 %/h (of a mean of 100.5).
        let ys: Vec<f64> = xs.iter().map(|m| 100.0 + m / 60.0).collect();
        assert!((drift_per_hour(&xs, &ys) - 100.0 / 100.49).abs() < 0.01);
        assert_eq!(drift_per_hour(&xs, &vec![5.0; 60]), 0.0);
        assert_eq!(quantile(&mut [3.0, 1.0, 2.0], 0.5), 2.0);
        // On a line the slope is exact; scatter about it widens the error.
        assert!(drift_error(&xs, &ys) < 1e-9);
        let noisy: Vec<f64> = ys.iter().enumerate().map(|(i, y)| y + if i % 2 == 0 { 1.0 } else { -1.0 }).collect();
        assert!(drift_error(&xs, &noisy) > 0.1);
    }

    #[test]
    fn windows_take_each_span_of_minutes_apart() {
        let points: Vec<(f64, f64)> = (0..10).map(|m| (f64::from(m), f64::from(m * 10))).collect();
        let (wx, wy) = windows(&points, 1, |v| quantile(v, 0.5));
        assert_eq!(wx, [1.0, 4.0, 7.0, 9.0]);
        assert_eq!(wy, [10.0, 40.0, 70.0, 90.0]);
        // The last window holds one point: left out when two are asked for.
        assert_eq!(windows(&points, 2, |v| quantile(v, 0.5)).0, [1.0, 4.0, 7.0]);
    }

    #[test]
    fn a_slope_is_judged_with_its_error() {
        // Growth: well under, well over, and too wide to tell (the hours to tell grow with
        // the error).
        assert_eq!(judge(0.2, 0.3, 1.0, 60.0, false), Judged::Pass);
        assert_eq!(judge(-5.0, 0.3, 1.0, 60.0, false), Judged::Pass);
        assert_eq!(judge(3.0, 0.5, 1.0, 60.0, false), Judged::Fail);
        let Judged::Undecided(h) = judge(0.5, 2.0, 1.0, 60.0, false) else { panic!("decided") };
        assert!((h - 4f64.powf(2.0 / 3.0)).abs() < 1e-9, "{h}");
        // Drift either way.
        assert_eq!(judge(-5.0, 0.3, 2.0, 60.0, true), Judged::Fail);
        assert_eq!(judge(f64::NAN, 0.3, 2.0, 60.0, true), Judged::Fail);
    }

    #[test]
    fn the_warm_ups_churn_kills_and_rejoins_in_turn_from_its_first_minute() {
        // Two rounds, half a minute apart, sampled each second as the soak's loop does.
        let (mut done, mut seen) = (0, Vec::new());
        for s in 0..600 {
            let now = f64::from(s) / 60.0;
            if let Some(kill) = warm_event(now, done, 2, 0.5) {
                done += 1;
                seen.push((s, kill));
            }
        }
        assert_eq!(seen, [(60, true), (90, false), (120, true), (150, false)]);
        assert_eq!(warm_event(30.0, 0, 0, 0.5), None);
    }
}
