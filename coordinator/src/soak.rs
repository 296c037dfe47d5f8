//! `coordinator bench soak`: a cluster run long under churn, measured every minute. The
//! README's kind of job (two worlds from pixels, two agents) on loopback with the cluster's
//! credentials: the agents join with tokens; one is killed every `--kill-every` minutes, one
//! machine is revoked and joined again every `--rejoin-every`, and one agent's certificate
//! lives `--cert-minutes` (it expires during the run and the machine joins again). Each role's
//! resident memory, threads, open files and sockets, the agents' step time (p50/p95) and
//! steps/s, the stale and refused counts go to `soak.csv` each sample and to `soak.svg`; the
//! verdict comes from the slopes after the warm-up.

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
pub struct SoakArgs {
    /// Minutes of the run.
    pub minutes: f64,
    /// Seconds between samples.
    pub sample_s: f64,
    /// Minutes between agent kills (0: none).
    pub kill_every: f64,
    /// Minutes between a machine revoked and joined again (0: none).
    pub rejoin_every: f64,
    /// Minutes agent 1's certificates live (0: a year).
    pub cert_minutes: f64,
    /// Minutes left out of the slopes at the start.
    pub warmup: f64,
    /// Environments per agent.
    pub envs: usize,
    /// The run's folder.
    pub out: PathBuf,
}

/// One process's figures from /proc.
#[derive(Clone, Copy, Default)]
struct Proc {
    rss_kb: f64,
    threads: f64,
    files: f64,
    sockets: f64,
}

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
    Proc { rss_kb: field("VmRSS:"), threads: field("Threads:"), files, sockets }
}

/// Minutes at the end of a run without churn: the last event's recovery is seen.
const CHURN_GRACE: f64 = 3.0;

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

/// `bench soak`.
pub fn soak(a: SoakArgs) -> Result<i32> {
    anyhow::ensure!(a.minutes > a.warmup && a.sample_s >= 5.0, "--minutes must pass --warmup; --sample-s at least 5");
    anyhow::ensure!(a.cert_minutes == 0.0 || a.cert_minutes >= 1.0, "--cert-minutes: 0 (a year) or at least 1");
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
        "--minutes",
    ];
    let minutes_arg = (a.minutes + 10.0).to_string();
    let up = <Up as clap::Parser>::try_parse_from(spec_args.iter().copied().chain([minutes_arg.as_str()]))?.up;
    let spec = out.join("job.toml");
    std::fs::write(&spec, crate::up::job_spec(&up, &out)?)?;
    let job = "soak";
    let doc = coordinator::jobspec::load(&spec, job)?;
    let r = request(&session, Kind::StartJob(doc), Duration::from_secs(10))?;
    anyhow::ensure!(r.ok, "job start: {}", r.text);
    println!(
        "soak: {} min, a sample every {} s, an agent killed every {} min, a machine revoked and joined again every {} \
         min, agent-1's certificates living {} min; folder {}",
        a.minutes,
        a.sample_s,
        a.kill_every,
        a.rejoin_every,
        a.cert_minutes,
        out.display()
    );
    let csv_path = out.join("soak.csv");
    let mut csv = String::from("minute");
    for r in ROLES {
        csv.push_str(&format!(",{r}_rss_mb,{r}_threads,{r}_files,{r}_sockets"));
    }
    csv.push_str(
        ",steps_per_s,step_ms_p50,step_ms_p95,episodes_received,dropped_stale,dropped_bad,dropped_duplicate,refused,env_steps\n",
    );
    let mut rows: Vec<Vec<f64>> = Vec::new();
    let mut lives: Vec<Vec<u64>> = Vec::new();
    let mut churn: Vec<Churn> = Vec::new();
    let mut step_ms: Vec<f64> = Vec::new();
    // The first revocation half-way through the first period (a one-period run sees one); a
    // certificate is renewed half a minute after it expired (its links closed meanwhile).
    let (mut next_sample, mut next_kill, mut next_rejoin) = (a.sample_s / 60.0, a.kill_every, a.rejoin_every / 2.0);
    let mut cert_due = if a.cert_minutes > 0.0 { a.cert_minutes + 0.5 } else { f64::INFINITY };
    let mut kills = 0usize;
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
        if churn_open && a.kill_every > 0.0 && now >= next_kill {
            next_kill += a.kill_every;
            let agent = format!("agent-{}", 1 + kills % 2);
            kills += 1;
            children.restart(&agent)?;
            bar.suspend(|| println!("{now:.1} min: {agent} killed and started again"));
            churn.push(Churn { what: "killed".into(), at: now, agent, recovered: None });
        }
        // Agent 2 is revoked and joins again; agent 1's certificate expires and it joins again.
        for expired in [false, true] {
            let due = churn_open && if expired { now >= cert_due } else { a.rejoin_every > 0.0 && now >= next_rejoin };
            if !due {
                continue;
            }
            let i = usize::from(!expired);
            let agent = format!("agent-{}", i + 1);
            let minutes = if expired {
                cert_due = now + a.cert_minutes + 0.5;
                a.cert_minutes
            } else {
                next_rejoin += a.rejoin_every;
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
                for s in list.agents.iter().filter(|s| s.steps_per_s > 0.0) {
                    // ms per step of one environment.
                    step_ms.push(1000.0 * s.envs as f64 / s.steps_per_s);
                }
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
            for r in ROLES {
                let p = pids[r].as_u64().map(|p| proc_of(p as u32)).unwrap_or_default();
                row.extend([p.rss_kb / 1024.0, p.threads, p.files, p.sockets]);
            }
            let l = last_status
                .as_ref()
                .and_then(|s| s.record.as_ref())
                .and_then(|j| j.learner.clone())
                .unwrap_or_default();
            let refused: u64 = last_status
                .as_ref()
                .map(|s| s.coordinator_refused.iter().chain(&l.refused).map(|d| d.count).sum())
                .unwrap_or(0);
            // Steps/s end to end: the learner's environment steps since the last sample.
            let env = if last_status.is_some() { l.env_steps as f64 } else { f64::NAN };
            let steps = match prev_env {
                Some((t, e)) if env.is_finite() && now > t => (env - e) / ((now - t) * 60.0),
                _ => f64::NAN,
            };
            if env.is_finite() {
                prev_env = Some((now, env));
            }
            row.extend([
                steps,
                quantile(&mut step_ms.clone(), 0.5),
                quantile(&mut step_ms.clone(), 0.95),
                if last_status.is_some() { l.episodes_received as f64 } else { f64::NAN },
                l.dropped_stale as f64,
                l.dropped_bad as f64,
                l.dropped_duplicate as f64,
                refused as f64,
                env,
            ]);
            step_ms.clear();
            csv.push_str(&row.iter().map(|v| format!("{v:.3}")).collect::<Vec<_>>().join(","));
            csv.push('\n');
            std::fs::write(&csv_path, &csv)?;
            rows.push(row);
        }
    }
    bar.finish_and_clear();
    let _ = request(&session, Kind::StopJobId(job.into()), Duration::from_secs(5));
    drop(children);
    verdict(&a, &rows, &lives, &churn, &out)
}

/// The worst memory growth (%/h) over the lives of role `k` (samples with one process id)
/// that run at least [`MIN_LIFE`] minutes past their own warm-up; None when none does.
fn worst_life(a: &SoakArgs, rows: &[Vec<f64>], lives: &[Vec<u64>], k: usize) -> Option<f64> {
    let mut worst: Option<f64> = None;
    let mut i = 0;
    while i < rows.len() {
        let pid = lives[i][k];
        let mut j = i;
        while j < rows.len() && lives[j][k] == pid {
            j += 1;
        }
        let born = rows[i][0];
        let seg: Vec<&Vec<f64>> =
            rows[i..j].iter().filter(|r| r[0] >= born + a.warmup && r[1 + 4 * k].is_finite()).collect();
        if pid != 0 && seg.len() >= 3 && seg[seg.len() - 1][0] - seg[0][0] >= MIN_LIFE {
            // The floor of each window: what a process holds between its peaks (a training
            // update's buffers come and go; a leak raises the floor).
            let (mut xs, mut ys) = (Vec::new(), Vec::new());
            for w in seg.chunk_by(|p, q| {
                ((p[0] - seg[0][0]) / FLOOR_WINDOW) as u64 == ((q[0] - seg[0][0]) / FLOOR_WINDOW) as u64
            }) {
                xs.push(w.iter().map(|r| r[0]).sum::<f64>() / w.len() as f64);
                ys.push(w.iter().map(|r| r[1 + 4 * k]).fold(f64::INFINITY, f64::min));
            }
            if xs.len() >= 3 {
                let g = drift_per_hour(&xs, &ys);
                worst = Some(worst.map_or(g, |w: f64| w.max(g)));
            }
        }
        i = j;
    }
    worst
}

/// Minutes a process's life must run past its warm-up for its memory slope to count.
const MIN_LIFE: f64 = 10.0;
/// Minutes of each window whose floor (least resident memory) the memory slope is taken over,
/// and whose mean the steps/s drift.
const FLOOR_WINDOW: f64 = 3.0;

/// The verdict from the samples after the warm-up: memory, steps/s, episodes, recoveries.
fn verdict(a: &SoakArgs, rows: &[Vec<f64>], lives: &[Vec<u64>], churn: &[Churn], out: &Path) -> Result<i32> {
    let after: Vec<&Vec<f64>> = rows.iter().filter(|r| r[0] >= a.warmup).collect();
    anyhow::ensure!(after.len() >= 3, "too few samples after the warm-up ({}) for a slope", after.len());
    let xs: Vec<f64> = after.iter().map(|r| r[0]).collect();
    let col = |i: usize| after.iter().map(|r| r[i]).collect::<Vec<f64>>();
    let base = 1 + 4 * ROLES.len();
    let mut checks: Vec<(String, String, bool)> = Vec::new();
    for (k, r) in ROLES.iter().enumerate() {
        // A process's memory starts again with each kill: the slope is taken over each life
        // (one process id) past its warm-up, the worst life reported.
        match worst_life(a, rows, lives, k) {
            Some(g) => checks.push((format!("{r}: resident memory growth ≤ 1 %/h"), format!("{g:+.2} %/h"), g <= 1.0)),
            None => println!("{r}: no life ran {MIN_LIFE} min past its warm-up; its memory is not judged"),
        }
        if lives.iter().all(|l| l[k] == lives[0][k]) {
            let th = slope(&xs, &col(2 + 4 * k)) * 60.0;
            let fd = slope(&xs, &col(3 + 4 * k)) * 60.0;
            checks.push((
                format!("{r}: threads and open files do not grow"),
                format!("{th:+.1}/h threads, {fd:+.1}/h files"),
                th <= 1.0 && fd <= 2.0,
            ));
        }
    }
    // Steps/s over windows: the learner's environment steps across each window, against time.
    let env: Vec<(f64, f64)> = after.iter().map(|r| (r[0], r[base + 8])).filter(|p| p.1.is_finite()).collect();
    let (mut wx, mut wy) = (Vec::new(), Vec::new());
    if let Some(first) = env.first() {
        for w in env.chunk_by(|p, q| ((p.0 - first.0) / FLOOR_WINDOW) as u64 == ((q.0 - first.0) / FLOOR_WINDOW) as u64)
        {
            let (a0, a1) = (w[0], w[w.len() - 1]);
            if a1.0 > a0.0 {
                wx.push((a0.0 + a1.0) / 2.0);
                wy.push((a1.1 - a0.1) / ((a1.0 - a0.0) * 60.0));
            }
        }
    }
    let d = if wx.len() >= 3 { drift_per_hour(&wx, &wy) } else { f64::NAN };
    let mean = wy.iter().sum::<f64>() / wy.len().max(1) as f64;
    let spread = (wy.iter().map(|y| (y - mean).powi(2)).sum::<f64>() / wy.len().max(1) as f64).sqrt() * 100.0 / mean;
    checks.push((
        "steps/s drift ≤ 2 %/h (environment steps the learner got, per window)".into(),
        format!("{d:+.2} %/h (mean {mean:.0} steps/s over {} windows; windows spread ±{spread:.0} %)", wx.len()),
        d.abs() <= 2.0,
    ));
    let last = rows.iter().rev().find(|r| r[base + 3].is_finite()).cloned().unwrap_or_else(|| vec![f64::NAN; base + 8]);
    let (bad, dup) = (last[base + 5], last[base + 6]);
    // A stall: a minute past the warm-up in which no episode arrived.
    let stalls = rows
        .iter()
        .enumerate()
        .filter(|(j, r)| {
            r[0] >= a.warmup + 1.0
                && rows[..*j].iter().rev().find(|p| r[0] - p[0] >= 1.0).is_some_and(|p| r[base + 3] <= p[base + 3])
        })
        .count();
    checks.push((
        "no episode lost: none refused as bad or duplicate, no minute without episodes".into(),
        format!(
            "{bad:.0} bad, {dup:.0} duplicate, {stalls} samples a minute after the last episode, {:.0} received",
            last[base + 3]
        ),
        bad == 0.0 && dup == 0.0 && stalls == 0,
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
        unrecovered.is_empty(),
    ));
    chart(rows, out)?;
    println!("| check | figure | verdict |\n|---|---|---|");
    for (what, figure, ok) in &checks {
        println!("| {what} | {figure} | {} |", if *ok { "pass" } else { "FAIL" });
    }
    let pass = checks.iter().all(|c| c.2);
    println!(
        "verdict: {} ({} min, warm-up {} min, {} samples; {} and soak.svg)",
        if pass { "PASS" } else { "FAIL" },
        a.minutes,
        a.warmup,
        rows.len(),
        out.join("soak.csv").display()
    );
    Ok(if pass { 0 } else { 1 })
}

/// `soak.svg`: each role's resident memory, and the steps/s, against minutes.
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
        .flat_map(|r| (0..ROLES.len()).map(move |k| r[1 + 4 * k]))
        .filter(|v| v.is_finite())
        .fold(1.0, f64::max);
    let mut c = ChartBuilder::on(&top)
        .caption("resident memory (MB)", ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(30)
        .y_label_area_size(50)
        .build_cartesian_2d(0f64..end, 0f64..max_mb * 1.1)
        .map_err(|x| e(&x))?;
    c.configure_mesh().x_desc("minutes").draw().map_err(|x| e(&x))?;
    for (k, r) in ROLES.iter().enumerate() {
        let color = Palette99::pick(k).to_rgba();
        c.draw_series(LineSeries::new(
            rows.iter().map(|row| (row[0], row[1 + 4 * k])).filter(|p| p.1.is_finite()),
            color,
        ))
        .map_err(|x| e(&x))?
        .label(*r)
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], color));
    }
    c.configure_series_labels().border_style(BLACK).background_style(WHITE).draw().map_err(|x| e(&x))?;
    let base = 1 + 4 * ROLES.len();
    let max_steps = rows.iter().map(|r| r[base]).fold(1.0, f64::max);
    let mut c = ChartBuilder::on(&bottom)
        .caption("environment steps/s the learner got (both agents)", ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(30)
        .y_label_area_size(50)
        .build_cartesian_2d(0f64..end, 0f64..max_steps * 1.1)
        .map_err(|x| e(&x))?;
    c.configure_mesh().x_desc("minutes").draw().map_err(|x| e(&x))?;
    c.draw_series(LineSeries::new(rows.iter().map(|r| (r[0], r[base])).filter(|p| p.1.is_finite()), BLUE))
        .map_err(|x| e(&x))?;
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
    }
}
