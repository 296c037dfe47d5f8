//! Every finding about a Python reward file, each on its line: what the console's editor
//! marks and `coordinator reward validate` prints (DeepRacer's console shows only the first
//! error, without its line).
//!
//! Two kinds of finding. Errors are what would fail when Paddock trains: a syntax error, no
//! `reward_function`, a `reward_function` that cannot take DeepRacer's one argument, a name
//! used but never defined (Python's `NameError` when that line runs), and what the calls on
//! sampled states raise or return ([`finding_of`]). Warnings are what DeepRacer's console
//! refuses but Paddock runs: imports other than the five it allows, the builtins it forbids,
//! imports inside a function.
//!
//! The static checks read the file with CPython's own parser (`ast` and `symtable`), so they
//! see exactly the Python the reward will run on; nothing of the file is executed.

use crate::reward::{RewardError, RewardFn};
use crate::validate::{Sampling, ValidationReport, validate_reward_all};
use pyo3::prelude::*;
use std::ffi::CString;
use std::path::Path;
use std::time::Duration;

/// How much a finding matters.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Severity {
    /// Training with this file would fail (or the reward is not what DeepRacer accepts).
    Error,
    /// DeepRacer's console would refuse the file; Paddock runs it.
    Warning,
}

/// One finding, on its line of the file when it has one.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Finding {
    /// The line (from 1), when the finding is on one.
    pub line: Option<usize>,
    /// Error or warning.
    pub severity: Severity,
    /// What is wrong, in a sentence.
    pub message: String,
}

impl Severity {
    /// `error` or `warning`.
    pub fn label(self) -> &'static str {
        match self {
            Severity::Error => "error",
            Severity::Warning => "warning",
        }
    }
}

/// The checks, in Python: `check(source, name)` returns `(line or None, "error"|"warning",
/// message)` tuples.
const CHECK_PY: &str = r#"
import ast, builtins, symtable

ALLOWED = {"math", "random", "numpy", "scipy", "shapely"}
FORBIDDEN = ["open", "exec", "eval", "compile", "input", "__import__"]

def check(source, name):
    try:
        tree = ast.parse(source, filename=name)
        table = symtable.symtable(source, name, "exec")
    except SyntaxError as e:
        return [(e.lineno, "error", "SyntaxError: %s" % e.msg)]
    out = []
    funcs = [n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.name == "reward_function"]
    try:
        s = table.lookup("reward_function")
        bound = s.is_assigned() or s.is_imported() or s.is_namespace()
    except KeyError:
        bound = False
    if funcs:
        f = funcs[-1]
        a = f.args
        positional = len(a.posonlyargs) + len(a.args)
        required = positional - len(a.defaults) + sum(1 for d in a.kw_defaults if d is None)
        if isinstance(f, ast.AsyncFunctionDef):
            out.append((f.lineno, "error", "reward_function is async: DeepRacer calls it as a plain function"))
        elif positional == 0 and a.vararg is None:
            out.append((f.lineno, "error", "reward_function takes no argument: DeepRacer calls it with one, params"))
        elif required > 1:
            out.append((f.lineno, "error", "reward_function needs %d arguments: DeepRacer calls it with one, params" % required))
    elif not bound:
        out.append((None, "error", "the file defines no reward_function(params)"))
    for node in ast.walk(tree):
        mods = []
        if isinstance(node, ast.Import):
            mods = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            mods = [("." * node.level) + (node.module or "")]
        for m in mods:
            if m.split(".")[0] not in ALLOWED:
                out.append((node.lineno, "warning", "import of %s: DeepRacer's console allows only math, random, numpy, scipy and shapely" % m))
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in FORBIDDEN:
            out.append((node.lineno, "warning", "%s(): DeepRacer's console refuses open, exec, eval, compile, input and __import__" % node.func.id))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for inner in ast.walk(node):
                if isinstance(inner, (ast.Import, ast.ImportFrom)):
                    out.append((inner.lineno, "warning", "an import inside %s(): DeepRacer's console wants imports at the top of the file" % node.name))
    out.extend(undefined(tree, table))
    out.sort(key=lambda f: (f[0] or 0, f[1], f[2]))
    return out

def undefined(tree, table):
    # A star import or names made at run time (globals(), exec) hide what is defined.
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and any(a.name == "*" for a in node.names):
            return []
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("globals", "exec", "vars"):
            return []
    defined = set(dir(builtins)) | {"__name__", "__file__", "__doc__", "__builtins__", "__spec__", "__loader__", "__package__"}
    for s in table.get_symbols():
        if s.is_assigned() or s.is_imported() or s.is_namespace():
            defined.add(s.get_name())
    for node in ast.walk(tree):
        if isinstance(node, ast.Global):
            defined.update(node.names)
    missing = set()
    def visit(t):
        for s in t.get_symbols():
            n = s.get_name()
            if not s.is_referenced() or n in defined:
                continue
            if t.get_type() == "module" or s.is_global():
                missing.add(n)
        for c in t.get_children():
            visit(c)
    visit(table)
    out = []
    seen = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Load) and node.id in missing and node.id not in seen:
            seen.add(node.id)
            out.append((node.lineno, "error", "undefined name '%s' (NameError when this line runs)" % node.id))
    return out
"#;

/// The static findings about the reward file `source` (named `name`, as tracebacks name it).
/// An error from Python itself (not the file's) is an `Err`.
pub fn check_source(source: &str, name: &str) -> Result<Vec<Finding>, String> {
    let code = CString::new(CHECK_PY).expect("no NUL");
    Python::attach(|py| {
        let module = pyo3::types::PyModule::from_code(py, &code, c"paddock_reward_check.py", c"paddock_reward_check")
            .map_err(|e| format!("the reward checker: {e}"))?;
        let found: Vec<(Option<usize>, String, String)> = module
            .getattr("check")
            .and_then(|f| f.call1((source, name)))
            .and_then(|r| r.extract())
            .map_err(|e| format!("the reward checker: {}", crate::python::format_traceback(py, &e)))?;
        Ok(found
            .into_iter()
            .map(|(line, severity, message)| Finding {
                line,
                severity: if severity == "error" { Severity::Error } else { Severity::Warning },
                message,
            })
            .collect())
    })
}

/// The reward to validate: a built-in (`builtin:NAME`), a file (its folder on `sys.path`, as
/// in training), or a file's text received from elsewhere (the console's editor), with the
/// name its tracebacks give it.
#[derive(Clone, Copy, Debug)]
pub enum RewardInput<'a> {
    /// `builtin:NAME`, or a bare built-in name.
    Builtin(&'a str),
    /// A Python reward file.
    File(&'a Path),
    /// A Python reward file's text, and its name.
    Source {
        /// What tracebacks call the file.
        name: &'a str,
        /// The file's text.
        text: &'a str,
    },
}

impl RewardInput<'_> {
    /// `builtin:NAME` or a bare built-in name is a built-in; anything else a file.
    pub fn of_spec(spec: &str) -> RewardInput<'_> {
        let name = spec.strip_prefix("builtin:").unwrap_or(spec);
        if spec.starts_with("builtin:") || crate::BuiltinReward::ALL.iter().any(|(_, n)| *n == name) {
            RewardInput::Builtin(spec)
        } else {
            RewardInput::File(Path::new(spec))
        }
    }
}

/// What validating a reward found: every finding (by line), the rewards of the calls that
/// returned, and the first failed call in full (traceback and params).
#[derive(Debug, Default)]
pub struct Validation {
    /// Every finding, by line.
    pub findings: Vec<Finding>,
    /// The calls that returned a reward (none when a static error kept the file from being
    /// called, or when every call failed).
    pub report: Option<ValidationReport>,
    /// The first failed call, or what kept the file from loading.
    pub first_failure: Option<RewardError>,
}

impl Validation {
    /// No error (warnings allowed).
    pub fn ok(&self) -> bool {
        self.count(Severity::Error) == 0
    }

    /// How many findings of `severity`.
    pub fn count(&self, severity: Severity) -> usize {
        self.findings.iter().filter(|f| f.severity == severity).count()
    }

    /// The answer as JSON, as `reward validate --json` prints it and the console's API
    /// answers: `{"ok", "errors": [{"line", "message"}], "warnings": [...], "rewards"}`, with
    /// `rewards` null when no call returned.
    pub fn to_json(&self) -> serde_json::Value {
        let listed = |s: Severity| -> Vec<serde_json::Value> {
            self.findings
                .iter()
                .filter(|f| f.severity == s)
                .map(|f| serde_json::json!({"line": f.line, "message": f.message}))
                .collect()
        };
        let rewards = self.report.as_ref().map(|r| {
            serde_json::json!({"calls": r.calls, "min": r.min, "mean": r.mean, "max": r.max,
                "mean_by_kind": r.mean_by_kind.iter().map(|(k, m)| serde_json::json!({"kind": k, "mean": m})).collect::<Vec<_>>()})
        });
        serde_json::json!({
            "ok": self.ok(),
            "errors": listed(Severity::Error),
            "warnings": listed(Severity::Warning),
            "rewards": rewards,
        })
    }
}

/// Validate `input`: the static checks of a Python file, then (when they found no error) the
/// calls on the states `at` samples, each at most `time_limit`, going on past a failed call.
/// An `Err` is a problem of Paddock's (the checker itself), not of the file.
pub fn validate(input: RewardInput<'_>, at: Sampling<'_>, time_limit: Duration) -> Result<Validation, String> {
    let mut v = Validation::default();
    let (name, loaded) = match input {
        RewardInput::Builtin(spec) => (spec.to_string(), RewardFn::from_spec(spec)),
        RewardInput::File(path) => {
            let name = path.display().to_string();
            let text = match std::fs::read_to_string(path) {
                Ok(text) => text,
                Err(e) => {
                    v.findings.push(Finding {
                        line: None,
                        severity: Severity::Error,
                        message: format!("cannot read the file: {e}"),
                    });
                    return Ok(v);
                }
            };
            v.findings = check_source(&text, &name)?;
            (name, RewardFn::from_file_text(path, &text))
        }
        RewardInput::Source { name, text } => {
            v.findings = check_source(text, name)?;
            (name.to_string(), RewardFn::from_source(name, text))
        }
    };
    if !v.ok() {
        return Ok(v);
    }
    match loaded {
        Ok(reward) => {
            let mut reward = reward.with_time_limit(time_limit);
            let (report, failures) = match validate_reward_all(&mut reward, at) {
                Ok(done) => done,
                Err(e) => (ValidationReport::default(), vec![e]),
            };
            for e in &failures {
                let f = finding_of(e, &name);
                if !v.findings.contains(&f) {
                    v.findings.push(f);
                }
            }
            v.first_failure = failures.into_iter().next();
            v.report = Some(report).filter(|r| r.calls > 0);
        }
        Err(e) => {
            v.findings.push(finding_of(&e, &name));
            v.first_failure = Some(e);
        }
    }
    v.findings.sort_by_key(|f| (f.line.unwrap_or(0), f.severity));
    Ok(v)
}

/// A failed call of the reward function as a finding: the line of the file's innermost frame
/// in the traceback (`file` is the name tracebacks give the file), and the exception's last
/// line, or what was wrong with the value returned.
pub fn finding_of(err: &RewardError, file: &str) -> Finding {
    let error = |line, message| Finding { line, severity: Severity::Error, message };
    match err {
        RewardError::Raised { traceback, .. } => {
            let last = traceback.lines().rev().find(|l| !l.trim().is_empty()).unwrap_or("").trim();
            error(line_in(traceback, file), last.to_string())
        }
        RewardError::TimedOut { traceback, limit, .. } => {
            error(line_in(traceback, file), format!("reward_function did not return within {limit:?}: stopped here"))
        }
        RewardError::BadValue { value, why, .. } => error(None, format!("reward_function returned {value}: {why}")),
        RewardError::Load { msg, .. } => {
            let last = msg.lines().rev().find(|l| !l.trim().is_empty()).unwrap_or("").trim();
            error(line_in(msg, file), last.to_string())
        }
    }
}

/// The line of the innermost frame in `file` of a Python traceback.
fn line_in(traceback: &str, file: &str) -> Option<usize> {
    let quoted = format!("File \"{file}\", line ");
    traceback.lines().rev().find_map(|l| {
        let rest = l.trim_start().strip_prefix(&quoted)?;
        rest.split(|c: char| !c.is_ascii_digit()).next()?.parse().ok()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tracebacks_innermost_frame_in_the_file_gives_the_line() {
        let tb = "Traceback (most recent call last):\n  File \"r.py\", line 9, in reward_function\n    return helper(params)\n  File \"r.py\", line 4, in helper\n    return params['speeed']\nKeyError: 'speeed'";
        assert_eq!(line_in(tb, "r.py"), Some(4));
        assert_eq!(line_in(tb, "other.py"), None);
        let f = finding_of(&RewardError::Raised { step: 2.0, traceback: tb.into(), params: "{}".into() }, "r.py");
        assert_eq!((f.line, f.severity, f.message.as_str()), (Some(4), Severity::Error, "KeyError: 'speeed'"));
    }
}
