//! `bench fuzz`: every fuzz target of `fuzz/` (cargo-fuzz's layout; the targets are
//! `tests::fuzz`'s) under libFuzzer for a bounded time each, starting from the kept corpus
//! and the committed seeds; what it finds new is kept in `fuzz/corpus/TARGET` (minimised with
//! `cargo fuzz cmin`), a crash in `fuzz/artifacts/TARGET` (the suite replays both). Prints a table and a verdict: pass when
//! no target crashed, leaked past the memory limits or timed out.

use anyhow::{Context, Result, bail};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Instant;

/// One target's run.
struct Row {
    target: String,
    runs: u64,
    exec_per_s: u64,
    coverage: u64,
    corpus_before: usize,
    corpus_after: usize,
    seconds: f64,
    /// What went wrong, with the input that shows it.
    finding: Option<String>,
}

fn files(dir: &Path) -> usize {
    std::fs::read_dir(dir).map(|d| d.filter_map(|e| e.ok()).filter(|e| e.path().is_file()).count()).unwrap_or(0)
}

/// The figure after `key` in libFuzzer's last status line ("#N DONE cov: C ft: F corp: …
/// exec/s: E rss: R Mb").
fn stat(log: &str, key: &str) -> u64 {
    log.lines()
        .rev()
        .find_map(|l| {
            if !l.starts_with('#') {
                return None;
            }
            let at = l.find(key)? + key.len();
            l[at..].split_whitespace().next()?.trim_end_matches("Mb").parse().ok()
        })
        .unwrap_or(0)
}

fn runs(log: &str) -> u64 {
    log.lines().rev().find_map(|l| l.strip_prefix("Done ")?.split_whitespace().next()?.parse().ok()).unwrap_or(0)
}

/// Run the fuzzers from the repository's root.
pub fn run(seconds: u64, only: &[String], sanitizer: &str) -> Result<i32> {
    let fuzz = Path::new("fuzz");
    if !fuzz.join("Cargo.toml").exists() {
        bail!("fuzz/Cargo.toml: not found; run `coordinator bench fuzz` from the repository's root");
    }
    let version = Command::new("cargo").args(["fuzz", "--version"]).output();
    if !version.as_ref().is_ok_and(|o| o.status.success()) {
        bail!("cargo-fuzz is not installed: `cargo install cargo-fuzz` (it runs on this stable toolchain)");
    }
    let list = Command::new("cargo").args(["fuzz", "list"]).output().context("cargo fuzz list")?;
    let mut targets: Vec<String> =
        String::from_utf8_lossy(&list.stdout).lines().map(|l| l.trim().to_string()).collect();
    targets.retain(|t| !t.is_empty());
    if !only.is_empty() {
        for t in only {
            if !targets.contains(t) {
                bail!("--targets: no target '{t}' (there are: {})", targets.join(", "));
            }
        }
        targets.retain(|t| only.contains(t));
    }
    // cargo-fuzz passes unstable flags (the sanitizers, coverage options) to rustc; this
    // toolchain is stable, so it is told to accept them.
    let cargo = |args: &[&str]| {
        let mut c = Command::new("cargo");
        c.args(["fuzz"]).args(args).env("RUSTC_BOOTSTRAP", "1");
        c
    };
    eprintln!("bench fuzz: building {} targets (sanitizer {sanitizer}) …", targets.len());
    let t = Instant::now();
    let st =
        cargo(&["build", "--sanitizer", sanitizer]).stderr(Stdio::inherit()).status().context("cargo fuzz build")?;
    if !st.success() {
        bail!("cargo fuzz build failed ({st})");
    }
    eprintln!("bench fuzz: built in {:.0} s", t.elapsed().as_secs_f64());
    let mut rows = Vec::new();
    for (i, target) in targets.iter().enumerate() {
        let corpus = fuzz.join("corpus").join(target);
        let seeds = fuzz.join("seeds").join(target);
        std::fs::create_dir_all(&corpus).with_context(|| format!("{}", corpus.display()))?;
        let before = files(&corpus);
        eprintln!("bench fuzz: [{}/{}] {target}: {seconds} s from {before} kept inputs …", i + 1, targets.len());
        let t = Instant::now();
        let corpus_s = corpus.display().to_string();
        let seeds_s = seeds.display().to_string();
        let max_time = format!("-max_total_time={seconds}");
        let mut args = vec!["run", target, "--sanitizer", sanitizer, &corpus_s];
        if seeds.exists() {
            args.push(&seeds_s);
        }
        // A slow input (over 10 s) or a memory bound broken (2 GB resident, 512 MB asked at
        // once: the largest real input, a DEEPER model's graph, is 40 MB) is a finding too.
        args.extend([
            "--",
            &max_time,
            "-timeout=10",
            "-rss_limit_mb=2048",
            "-malloc_limit_mb=512",
            "-print_final_stats=1",
        ]);
        let o = cargo(&args).stdout(Stdio::piped()).stderr(Stdio::piped()).output().context("cargo fuzz run")?;
        let log = String::from_utf8_lossy(&o.stderr).to_string() + &String::from_utf8_lossy(&o.stdout);
        let finding = if o.status.success() {
            None
        } else {
            let what = log
                .lines()
                .find(|l| l.contains("ERROR: libFuzzer") || l.contains("panicked at") || l.contains("==ERROR"))
                .unwrap_or("the fuzzer failed")
                .trim()
                .to_string();
            let input = log.lines().find_map(|l| l.split("Test unit written to ").nth(1)).unwrap_or("-").trim();
            eprintln!("{log}");
            Some(format!("{what} (input: {input})"))
        };
        // Keep a small set of inputs that reaches every edge the run reached (what is committed
        // and replayed by the suite): edges alone, not their hit counts, which keep 5× more.
        let minimised = cargo(&["cmin", target, "--sanitizer", sanitizer, &corpus_s, "--", "-use_counters=0"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        if !minimised {
            eprintln!("bench fuzz: {target}: cargo fuzz cmin failed; the corpus is kept whole");
        }
        rows.push(Row {
            target: target.clone(),
            runs: runs(&log),
            exec_per_s: stat(&log, "exec/s: "),
            coverage: stat(&log, "cov: "),
            corpus_before: before,
            corpus_after: files(&corpus),
            seconds: t.elapsed().as_secs_f64(),
            finding,
        });
    }
    println!("| target | runs | exec/s | coverage (edges) | corpus before → after (minimised) | seconds | finding |");
    println!("|---|---:|---:|---:|---:|---:|---|");
    for r in &rows {
        println!(
            "| {} | {} | {} | {} | {} → {} | {:.0} | {} |",
            r.target,
            r.runs,
            r.exec_per_s,
            r.coverage,
            r.corpus_before,
            r.corpus_after,
            r.seconds,
            r.finding.as_deref().unwrap_or("none")
        );
    }
    let failed: Vec<String> =
        rows.iter().filter(|r| r.finding.is_some()).map(|r| format!("{} found a failing input", r.target)).collect();
    Ok(crate::bench::verdict(
        &failed,
        &format!("{} targets, {} s each, nothing found; new inputs kept in fuzz/corpus", rows.len(), seconds),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn libfuzzers_final_lines_are_read() {
        let log = "#2\tINITED cov: 10 ft: 11 corp: 1/1b exec/s: 0 rss: 30Mb\n\
                   #123456\tDONE   cov: 812 ft: 2301 corp: 240/9811b lim: 4096 exec/s: 4115 rss: 61Mb\n\
                   Done 123456 runs in 31 second(s)\n";
        assert_eq!(stat(log, "cov: "), 812);
        assert_eq!(stat(log, "exec/s: "), 4115);
        assert_eq!(runs(log), 123456);
        assert_eq!(stat("", "cov: "), 0);
    }
}
