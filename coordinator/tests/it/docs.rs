//! Every command in the README and the user guide (`docs/guide/`) runs as written (issue 50).
//!
//! The docs' fenced shell blocks (tagged `sh`, `bash`, `shell` or `console`) are split as a
//! shell splits them: line continuations, comments, quotes, environment-variable prefixes,
//! redirections, pipes, `&&`, `;` and `&`. Each command that runs one of Paddock's programs
//! (`./paddock`, or the `coordinator`, `sim-agent`, `learner` and `deploy` binaries, bare, under
//! `target/release/`, or through `cargo run -p NAME --`) is checked against the real binary:
//! each subcommand on its path, then each flag, from that subcommand's `--help`. The `paddock`
//! script's own verbs (`./paddock test`, `lint`, `bench`) are read from the script; `bench`'s
//! flags are checked against `sim-agent bench`, which it runs. Every problem is collected, with
//! its file and line, and the test fails with all of them.

use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::process::Command;

use crate::support;

/// Paddock's binaries, as cargo names them.
const BINARIES: [&str; 4] = ["coordinator", "sim-agent", "learner", "deploy"];

/// Where a binary may be written in the docs, besides bare (longest first).
const BINARY_DIRS: [&str; 4] = ["./target/release/", "target/release/", "./target/debug/", "target/debug/"];

/// Words before a program that are not the program.
const PREFIXES: [&str; 5] = ["sudo", "env", "time", "exec", "nohup"];

/// Fence tags of shell blocks.
const SHELL_TAGS: [&str; 4] = ["sh", "bash", "shell", "console"];

/// The `paddock` script's verbs that run a binary of their own (see the script): the verb, the
/// binary, and the subcommand its arguments go to.
const SCRIPT_RUNS: [(&str, &str, &str); 1] = [("bench", "sim-agent", "bench")];

/// The repository's root.
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A command of the docs that runs one of Paddock's programs.
#[derive(Debug, Clone, PartialEq)]
struct Invocation {
    /// The line (1-based) where the command starts.
    line: usize,
    /// The command as written (continued lines joined).
    text: String,
    /// What it runs.
    target: Target,
}

#[derive(Debug, Clone, PartialEq)]
enum Target {
    /// One of Paddock's binaries, with its arguments.
    Binary { name: &'static str, args: Vec<String> },
    /// A verb of the `paddock` script itself, with its arguments.
    Script { verb: String, args: Vec<String> },
}

impl Invocation {
    /// `LINE: PROGRAM ARGS`, for the extractor's table.
    fn summary(&self) -> String {
        let run = match &self.target {
            Target::Binary { name, args } => std::iter::once(name.to_string()).chain(args.iter().cloned()).collect(),
            Target::Script { verb, args } => {
                ["./paddock".to_string(), verb.clone()].into_iter().chain(args.iter().cloned()).collect::<Vec<_>>()
            }
        };
        format!("{}: {}", self.line, run.join(" "))
    }
}

/// The verbs the `paddock` script handles itself (its `case` labels); any other first argument
/// goes to the coordinator.
fn script_verbs(root: &Path) -> BTreeSet<String> {
    let script = std::fs::read_to_string(root.join("paddock")).expect("the paddock script at the repository's root");
    script
        .lines()
        .filter_map(|l| l.trim().strip_suffix(')'))
        .filter(|l| !l.is_empty() && l.chars().all(|c| c.is_ascii_lowercase() || c == '-' || c == '|'))
        .flat_map(|l| l.split('|'))
        .map(String::from)
        .collect()
}

/// An open code fence: its marker (three or more backticks or tildes) and what it holds.
#[derive(Clone)]
struct Fence {
    marker: String,
    shell: bool,
    console: bool,
}

/// The commands of a Markdown text's shell blocks that run Paddock's programs. In a `console`
/// block only lines after a `$ ` prompt are commands (the others are output).
fn extract(markdown: &str, verbs: &BTreeSet<String>) -> Vec<Invocation> {
    let mut out = vec![];
    let mut fence: Option<Fence> = None;
    // A command continued with `\`: its first line and the text so far.
    let mut pending: Option<(usize, String)> = None;
    for (i, line) in markdown.lines().enumerate() {
        let n = i + 1;
        let t = line.trim_start();
        let Some(f) = fence.clone() else {
            let first = t.chars().next().filter(|c| *c == '`' || *c == '~');
            let marker: String = t.chars().take_while(|c| Some(*c) == first).collect();
            if marker.len() >= 3 {
                let tag = t[marker.len()..].trim().split(|c: char| c.is_whitespace() || c == ',' || c == '{').next();
                let tag = tag.unwrap_or("").to_ascii_lowercase();
                fence = Some(Fence { marker, shell: SHELL_TAGS.contains(&tag.as_str()), console: tag == "console" });
            }
            continue;
        };
        let close = t.trim_end();
        if close.starts_with(&f.marker) && close.chars().all(|c| f.marker.starts_with(c)) {
            fence = None;
            pending = None;
            continue;
        }
        if !f.shell {
            continue;
        }
        let (start, text) = match pending.take() {
            // The shell drops a backslash-newline: the lines join as they are.
            Some((start, head)) => (start, head + line),
            None if f.console => match t.strip_prefix("$ ") {
                Some(command) => (n, command.to_string()),
                None => continue,
            },
            None => (n, t.to_string()),
        };
        if let Some(head) = text.strip_suffix('\\') {
            pending = Some((start, head.to_string()));
            continue;
        }
        for words in split_commands(&text) {
            if let Some(target) = resolve(&words, verbs) {
                out.push(Invocation { line: start, text: text.trim().to_string(), target });
            }
        }
    }
    out
}

/// Splits one shell line into its words, command by command.
struct Splitter {
    commands: Vec<Vec<String>>,
    word: String,
    /// A word has begun (quotes can begin an empty one).
    in_word: bool,
    /// The next word is a redirection's target, not an argument.
    redirect: bool,
}

impl Splitter {
    fn end_word(&mut self) {
        if self.in_word {
            let word = std::mem::take(&mut self.word);
            if self.redirect {
                self.redirect = false;
            } else {
                self.commands.last_mut().expect("a command").push(word);
            }
            self.in_word = false;
        }
    }

    fn end_command(&mut self) {
        self.end_word();
        if !self.commands.last().expect("a command").is_empty() {
            self.commands.push(vec![]);
        }
    }
}

/// One shell line (continuations joined) as its commands, each a list of words, as `sh` splits
/// it: quotes and backslashes, `#` comments, `|`, `||`, `&&`, `;`, `&` and parentheses between
/// commands; redirections (`>`, `>>`, `<`, `2>&1`, `&>`) are dropped with their targets.
fn split_commands(line: &str) -> Vec<Vec<String>> {
    let mut s = Splitter { commands: vec![vec![]], word: String::new(), in_word: false, redirect: false };
    let mut chars = line.chars().peekable();
    while let Some(c) = chars.next() {
        match c {
            '\\' => {
                s.word.extend(chars.next());
                s.in_word = true;
            }
            '\'' => {
                s.in_word = true;
                s.word.extend(chars.by_ref().take_while(|&q| q != '\''));
            }
            '"' => {
                s.in_word = true;
                while let Some(q) = chars.next() {
                    match q {
                        '"' => break,
                        '\\' if matches!(chars.peek(), Some('"' | '\\' | '$' | '`')) => s.word.extend(chars.next()),
                        _ => s.word.push(q),
                    }
                }
            }
            '#' if !s.in_word => break,
            '|' | ';' | '(' | ')' => {
                chars.next_if_eq(&'|');
                s.end_command();
            }
            '&' if chars.peek() == Some(&'>') => {
                chars.next();
                chars.next_if_eq(&'>');
                s.end_word();
                s.redirect = true;
            }
            '&' => {
                chars.next_if_eq(&'&');
                s.end_command();
            }
            '>' | '<' => {
                // A number just before the operator is the descriptor it redirects (`2>`).
                if s.in_word && s.word.chars().all(|d| d.is_ascii_digit()) {
                    s.word.clear();
                    s.in_word = false;
                } else {
                    s.end_word();
                }
                chars.next_if(|&d| d == '>' || d == '&');
                s.redirect = true;
            }
            c if c.is_whitespace() => s.end_word(),
            c => {
                s.word.push(c);
                s.in_word = true;
            }
        }
    }
    s.end_command();
    s.commands.into_iter().filter(|c| !c.is_empty()).collect()
}

/// The Paddock program a command runs, if it runs one.
fn resolve(words: &[String], verbs: &BTreeSet<String>) -> Option<Target> {
    let assignment = |w: &str| {
        w.split_once('=').is_some_and(|(name, _)| {
            name.chars().next().is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
                && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        })
    };
    let words: Vec<&str> =
        words.iter().map(String::as_str).skip_while(|w| assignment(w) || PREFIXES.contains(w)).collect();
    let (&program, args) = words.split_first()?;
    let args: Vec<String> = args.iter().map(|a| a.to_string()).collect();
    if program == "./paddock" {
        return Some(match args.split_first() {
            Some((verb, rest)) if verbs.contains(verb) => Target::Script { verb: verb.clone(), args: rest.to_vec() },
            _ => Target::Binary { name: "coordinator", args },
        });
    }
    if program == "cargo" && args.first().is_some_and(|a| a == "run") {
        return cargo_run(&args[1..]);
    }
    let bare = BINARY_DIRS.iter().find_map(|d| program.strip_prefix(d)).unwrap_or(program);
    let name = BINARIES.iter().find(|b| **b == bare).copied()?;
    Some(Target::Binary { name, args })
}

/// `cargo run [OPTIONS] -p NAME -- ARGS` (or `--bin NAME`), when NAME is a Paddock binary.
fn cargo_run(args: &[String]) -> Option<Target> {
    let (options, rest) = match args.iter().position(|a| a == "--") {
        Some(i) => (&args[..i], args[i + 1..].to_vec()),
        None => (args, vec![]),
    };
    let mut name = None;
    let mut options = options.iter().map(String::as_str);
    while let Some(o) = options.next() {
        match o {
            "-p" | "--package" | "--bin" => name = options.next(),
            _ => {
                if let Some(n) = o.strip_prefix("--package=").or_else(|| o.strip_prefix("--bin=")) {
                    name = Some(n);
                }
            }
        }
    }
    let name = BINARIES.iter().find(|b| Some(**b) == name).copied()?;
    Some(Target::Binary { name, args: rest })
}

/// What one `--help` lists: the subcommands and the flags there, and whether it takes
/// positional arguments.
#[derive(Clone, Debug, Default)]
struct Help {
    commands: BTreeSet<String>,
    flags: BTreeSet<String>,
    positionals: bool,
}

/// Reads clap's help: section headings at the margin (`Commands:`, `Arguments:`,
/// `Options:`), a subcommand's name two spaces in, a flag's line starting with `-` at most six
/// spaces in (descriptions are indented further).
fn parse_help(text: &str) -> Help {
    let mut help = Help::default();
    let mut section = "";
    for line in text.lines() {
        let t = line.trim();
        let indent = line.len() - line.trim_start().len();
        if t.is_empty() {
            continue;
        }
        if indent == 0 {
            section = t.split(':').next().unwrap_or("");
            help.positionals |= section == "Arguments";
            continue;
        }
        if section == "Commands" && indent == 2 {
            help.commands.extend(t.split_whitespace().next().map(String::from));
        } else if section != "Commands" && indent <= 6 && t.starts_with('-') {
            for token in t.split(|c: char| c.is_whitespace() || c == ',').filter(|s| !s.is_empty()) {
                if !token.starts_with('-') {
                    break;
                }
                help.flags.insert(token.split(['=', '[', '<']).next().unwrap_or(token).to_string());
            }
        }
    }
    help
}

/// The real binaries' help, asked once per subcommand path.
#[derive(Default)]
struct Clis {
    cache: HashMap<(String, Vec<String>), Result<Help, String>>,
}

impl Clis {
    /// `NAME PATH... --help`, read.
    fn help(&mut self, name: &str, path: &[String]) -> Result<Help, String> {
        let key = (name.to_string(), path.to_vec());
        self.cache
            .entry(key)
            .or_insert_with(|| {
                let bin = support::bin(name);
                if !bin.exists() {
                    return Err(format!(
                        "{} is not built (build every binary: `cargo build --release --workspace`)",
                        bin.display()
                    ));
                }
                let what = shown(name, path);
                let o = Command::new(&bin)
                    .args(path)
                    .arg("--help")
                    .env("NO_COLOR", "1")
                    .output()
                    .map_err(|e| format!("running `{what} --help`: {e}"))?;
                if !o.status.success() {
                    return Err(format!("`{what} --help` failed: {}", String::from_utf8_lossy(&o.stderr).trim()));
                }
                Ok(parse_help(&String::from_utf8_lossy(&o.stdout)))
            })
            .clone()
    }

    /// What in this command does not exist: a subcommand or a flag (none: it runs as written).
    fn check(&mut self, invocation: &Invocation) -> Vec<String> {
        match &invocation.target {
            Target::Binary { name, args } => self.check_args(name, args),
            Target::Script { verb, args } => match SCRIPT_RUNS.iter().find(|(v, ..)| *v == verb.as_str()) {
                Some((_, name, sub)) => {
                    let args: Vec<String> = std::iter::once(sub.to_string()).chain(args.iter().cloned()).collect();
                    self.check_args(name, &args)
                }
                // `test` and `lint` hand their arguments to cargo (nextest, clippy).
                None => vec![],
            },
        }
    }

    /// Walks `args`' subcommands from the binary's top, then checks every flag after them.
    fn check_args(&mut self, name: &str, args: &[String]) -> Vec<String> {
        let mut path: Vec<String> = vec![];
        let mut rest = args;
        let help = loop {
            let help = match self.help(name, &path) {
                Ok(help) => help,
                Err(e) => return vec![e],
            };
            match rest.split_first() {
                Some((word, tail)) if !word.starts_with('-') && !help.commands.is_empty() => {
                    if help.commands.contains(word) {
                        path.push(word.clone());
                        rest = tail;
                        continue;
                    }
                    if !help.positionals {
                        return vec![format!("`{}` has no subcommand `{word}`", shown(name, &path))];
                    }
                    break help;
                }
                _ => break help,
            }
        };
        let mut problems = vec![];
        for word in rest.iter().map(String::as_str).take_while(|w| *w != "--") {
            let flag = if word.starts_with("--") {
                word.split('=').next().unwrap_or(word)
            } else if word.len() >= 2 && word.starts_with('-') && word.as_bytes()[1].is_ascii_alphabetic() {
                &word[..2]
            } else {
                continue;
            };
            if !help.flags.contains(flag) {
                problems.push(format!("`{}` has no flag `{flag}`", shown(name, &path)));
            }
        }
        problems
    }
}

/// `NAME SUB SUB`.
fn shown(name: &str, path: &[String]) -> String {
    [name].into_iter().chain(path.iter().map(String::as_str)).collect::<Vec<_>>().join(" ")
}

/// Issue 50: every command in the README and the user guide runs as written: each subcommand
/// and flag it gives one of Paddock's programs exists (asked of the real binaries' `--help`).
#[test]
fn every_documented_command_exists() {
    let root = root();
    let verbs = script_verbs(&root);
    let mut guide: Vec<PathBuf> = std::fs::read_dir(root.join("docs/guide"))
        .expect("the user guide, docs/guide/")
        .map(|e| e.expect("a guide page").path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    guide.sort();
    assert!(!guide.is_empty(), "docs/guide/ has no pages");
    let mut clis = Clis::default();
    let (mut commands, mut problems) = (0, vec![]);
    for file in std::iter::once(root.join("README.md")).chain(guide) {
        let text = std::fs::read_to_string(&file).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
        let rel = file.strip_prefix(&root).unwrap_or(&file).display().to_string();
        for invocation in extract(&text, &verbs) {
            commands += 1;
            for p in clis.check(&invocation) {
                problems.push(format!("{rel}:{}: `{}`: {p}", invocation.line, invocation.text));
            }
        }
    }
    assert!(commands >= 20, "only {commands} commands found in the README and the guide: are the shell blocks read?");
    assert!(
        problems.is_empty(),
        "{} documented command(s) do not run as written:\n{}",
        problems.len(),
        problems.join("\n")
    );
}

/// Issue 50: the extractor reads shell blocks as the shell would (continuations, comments,
/// quotes, environment prefixes, redirections, pipes, `&&`, `&`, `cargo run`), and leaves
/// other blocks, a console block's output and prose alone.
#[test]
fn the_extractor_finds_each_command_of_the_shell_blocks() {
    let verbs: BTreeSet<String> = ["test", "lint", "bench"].map(String::from).into();
    let cases: [(&str, &[&str]); 7] = [
        (
            "```sh\n./paddock up --world a --agents 2   # the main job\n./paddock test\n```\n",
            &["2: coordinator up --world a --agents 2", "3: ./paddock test"],
        ),
        (
            "```bash\nPYO3_PYTHON=/usr/bin/python3 target/release/learner bench \\\n    --learners 2 --check   # a team\n\
             ./paddock tracks list | head -3 && sim-agent serve --envs 4 &\n```\n",
            &["2: learner bench --learners 2 --check", "4: coordinator tracks list", "4: sim-agent serve --envs 4"],
        ),
        (
            "```console\n$ ./paddock job status J --watch\nstate: running --not-a-flag\n$ ./paddock lint > lint.txt 2>&1\n```\n",
            &["2: coordinator job status J --watch", "4: ./paddock lint"],
        ),
        (
            "Run `./paddock train --nope` in prose.\n```toml\nreward = \"x.py\" # ./paddock train --nope\n```\n\
             ```python\n./paddock train --nope\n```\n```sh\ncargo install cargo-fuzz\nzenoh-bridge-ros2dds -n /car7 &\n```\n",
            &[],
        ),
        (
            "```shell\n./paddock train --set 'camera.randomize=true' --reward \"my reward.py\"\n\
             cargo run --release -p learner -- bench --learners 2\n./target/release/deploy --model-dir m --trust k.pub\n```\n",
            &[
                "2: coordinator train --set camera.randomize=true --reward my reward.py",
                "3: learner bench --learners 2",
                "4: deploy --model-dir m --trust k.pub",
            ],
        ),
        ("```sh\n./paddock bench --seconds 2\n```\n", &["2: ./paddock bench --seconds 2"]),
        (
            "- In a list:\n\n  ~~~sh\n  coordinator tracks show x --png t.png\n  ~~~\n",
            &["4: coordinator tracks show x --png t.png"],
        ),
    ];
    for (markdown, want) in cases {
        let got: Vec<String> = extract(markdown, &verbs).iter().map(Invocation::summary).collect();
        assert_eq!(got, want, "from:\n{markdown}");
    }
}

/// Issue 50: a made-up flag or subcommand in a documented command is reported, each with its
/// line and what is missing, against the real binaries; real ones pass.
#[test]
fn a_made_up_flag_or_subcommand_is_reported() {
    let verbs = script_verbs(&root());
    for verb in ["test", "lint", "bench"] {
        assert!(verbs.contains(verb), "the paddock script's verbs: {verbs:?}");
    }
    let markdown = "```sh\n\
        ./paddock train --world reinvent_base --minutes 1 --set noise.steering_deg=0\n\
        ./paddock train --bogus-flag 3\n\
        ./paddock job frobnicate J\n\
        target/release/sim-agent serve --envs 4 \\\n  --no-such-flag\n\
        ./paddock bench --nope\n\
        deploy --job J -c z.json5 --trust k.pub\n\
        ./paddock test\n\
        ```\n";
    let mut clis = Clis::default();
    let mut got = vec![];
    for invocation in extract(markdown, &verbs) {
        got.extend(clis.check(&invocation).into_iter().map(|p| format!("{}: {p}", invocation.line)));
    }
    assert_eq!(
        got,
        [
            "3: `coordinator train` has no flag `--bogus-flag`",
            "4: `coordinator job` has no subcommand `frobnicate`",
            "5: `sim-agent serve` has no flag `--no-such-flag`",
            "7: `sim-agent bench` has no flag `--nope`",
        ]
    );
}
