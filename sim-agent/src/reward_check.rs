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

use crate::reward::RewardError;
use pyo3::prelude::*;
use std::ffi::CString;

/// How much a finding matters.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Severity {
    /// Training with this file would fail (or the reward is not what DeepRacer accepts).
    Error,
    /// DeepRacer's console would refuse the file; Paddock runs it.
    Warning,
}

/// One finding, on its line of the file when it has one.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
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

impl std::fmt::Display for Finding {
    /// `line N: error: message` (or without the line).
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let kind = self.severity.label();
        match self.line {
            Some(line) => write!(f, "line {line}: {kind}: {}", self.message),
            None => write!(f, "{kind}: {}", self.message),
        }
    }
}

/// The modules DeepRacer's reward validation lets a file import.
pub const DEEPRACER_IMPORTS: [&str; 5] = ["math", "random", "numpy", "scipy", "shapely"];

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
