//! The reward checker's findings, each on its line: a table of reward files (read by CPython's
//! own parser) and what each must be told; every example reward and DeepRacer sample passes
//! with nothing to say; and the calls on sampled states report every distinct failure.

use sim_agent::reward_check::{Finding, RewardInput, Severity, check_source, finding_of, validate};
use sim_agent::validate::{Sampling, validate_reward_all};
use sim_agent::{RewardFn, race::RaceConfig};
use std::path::PathBuf;
use tracks::Direction;

const E: Severity = Severity::Error;
const W: Severity = Severity::Warning;

/// (what the case is, the file, the findings as (line, severity, a piece of the message)).
type Case = (&'static str, &'static str, &'static [(Option<usize>, Severity, &'static str)]);

const CASES: &[Case] = &[
    ("a clean file", "import math\ndef reward_function(params):\n    return float(math.cos(params['heading']))\n", &[]),
    (
        "a syntax error, on its line (CPython stops at the first)",
        "def reward_function(params):\n    x = (1,\n    return 1.0\n\n\n",
        &[(Some(2), E, "SyntaxError")],
    ),
    ("no reward_function", "def reward(params):\n    return 1.0\n", &[(None, E, "defines no reward_function")]),
    ("no argument", "def reward_function():\n    return 1.0\n", &[(Some(1), E, "takes no argument")]),
    ("two arguments", "def reward_function(params, extra):\n    return 1.0\n", &[(Some(1), E, "needs 2 arguments")]),
    ("a second argument with a default is fine", "def reward_function(params, k=2):\n    return 1.0 * k\n", &[]),
    (
        "every undefined name, each on the line it is first read, and every refused import",
        "import os\nimport numpy as np\nfrom shapely.geometry import Point\ndef reward_function(params):\n    s = prams['speed']\n    if s > LIMIT:\n        return 1e-3\n    return float(np.sqrt(prams['speed']))\n",
        &[(Some(1), W, "import of os"), (Some(5), E, "undefined name 'prams'"), (Some(6), E, "undefined name 'LIMIT'")],
    ),
    (
        "DeepRacer's forbidden builtins and an import inside the function",
        "def reward_function(params):\n    import math\n    open('x')\n    return eval('1.0')\n",
        &[
            (Some(2), W, "an import inside reward_function()"),
            (Some(3), W, "open(): DeepRacer's console refuses"),
            (Some(4), W, "eval(): DeepRacer's console refuses"),
        ],
    ),
    (
        "names defined anywhere at the top, by assignment, import, def, class, global or a loop, are defined",
        "import math as m\nK = 2\nclass C:\n    pass\ndef helper(x):\n    global SEEN\n    SEEN = x\n    return [y for y in range(x)]\nfor i in range(2):\n    pass\ndef reward_function(params):\n    return float(m.pi * K + helper(i)[0] + len(str(C)) + SEEN)\n",
        &[],
    ),
    (
        "a star import hides what is defined: no undefined name is claimed",
        "from math import *\ndef reward_function(params):\n    return float(pi)\n",
        &[],
    ),
];

/// Issue 51: every finding about a reward file is on its line, errors and DeepRacer's
/// refusals told apart.
#[test]
fn each_finding_about_a_reward_file_is_on_its_line() {
    for (what, source, want) in CASES {
        let got = check_source(source, "reward.py").unwrap_or_else(|e| panic!("{what}: {e}"));
        assert_eq!(got.len(), want.len(), "{what}: {got:#?}");
        for (g, (line, severity, piece)) in got.iter().zip(want.iter()) {
            assert_eq!((g.line, g.severity), (*line, *severity), "{what}: {g:?}");
            assert!(g.message.contains(piece), "{what}: {:?} does not say {piece:?}", g.message);
        }
    }
}

fn repo(path: &str) -> PathBuf {
    [env!("CARGO_MANIFEST_DIR"), "..", path].iter().collect()
}

/// Issue 51: DeepRacer's samples and Paddock's example rewards pass with nothing to say.
#[test]
fn deepracers_samples_and_the_example_rewards_have_no_finding() {
    let dir = repo("examples/rewards");
    let mut seen = 0;
    for e in std::fs::read_dir(&dir).unwrap().flatten() {
        let path = e.path();
        if path.extension().is_some_and(|x| x == "py") {
            let source = std::fs::read_to_string(&path).unwrap();
            let got = check_source(&source, &path.display().to_string()).unwrap();
            assert!(got.is_empty(), "{}: {got:#?}", path.display());
            seen += 1;
        }
    }
    assert!(seen >= 5, "{seen} example rewards");
}

/// Issue 51: the calls on sampled states go on past a failure, and each distinct failure is
/// a finding on the line that raised it.
#[test]
fn the_sampled_calls_report_every_distinct_failure_on_its_line() {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("reward_check");
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("two_faults.py");
    std::fs::write(
        &file,
        "def reward_function(params):\n    if params['is_offtrack']:\n        return params['no_such_key']\n    if params['progress'] > 50:\n        return 1 / 0\n    return 1.0\n",
    )
    .unwrap();
    let name = file.display().to_string();
    assert_eq!(check_source(&std::fs::read_to_string(&file).unwrap(), &name).unwrap(), vec![]);
    let world = tracks::world("reinvent_base").unwrap();
    let track = world.track(Direction::Forward);
    let space = policy::ActionSpace::Continuous { steering_angle: (-30.0, 30.0), speed: (0.5, 4.0) };
    let race = RaceConfig::default();
    let at = Sampling { track: &track, surface: world.surface, space: &space, positions: 12, race: &race };
    let mut reward = RewardFn::from_spec(&name).unwrap();
    let (report, failures) = validate_reward_all(&mut reward, at).unwrap();
    assert!(report.calls > 0, "the calls that returned are reported");
    let mut found: Vec<Finding> = Vec::new();
    for f in failures.iter().map(|e| finding_of(e, &name)) {
        if !found.contains(&f) {
            found.push(f);
        }
    }
    found.sort_by_key(|f| f.line);
    let lines: Vec<(Option<usize>, &str)> = found.iter().map(|f| (f.line, f.message.as_str())).collect();
    assert_eq!(lines, [(Some(3), "KeyError: 'no_such_key'"), (Some(5), "ZeroDivisionError: division by zero")]);
}

/// Issue 51: a reward file's text from an editor is validated as the file itself is (one code
/// path for the CLI and the console), and a static error keeps the file from being called.
#[test]
fn a_files_text_is_validated_as_the_file_is() {
    let text = "import os\ndef reward_function(params):\n    if params['is_offtrack']:\n        return params['no_such_key']\n    return 1.0\n";
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("reward_check_text");
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("r.py");
    std::fs::write(&file, text).unwrap();
    let world = tracks::world("reinvent_base").unwrap();
    let track = world.track(Direction::Forward);
    let space = policy::ActionSpace::Continuous { steering_angle: (-30.0, 30.0), speed: (0.5, 4.0) };
    let race = RaceConfig::default();
    let at = Sampling { track: &track, surface: world.surface, space: &space, positions: 6, race: &race };
    let limit = std::time::Duration::from_secs(1);
    let name = file.display().to_string();
    let from_file = validate(RewardInput::File(&file), at, limit).unwrap();
    let from_text = validate(RewardInput::Source { name: &name, text }, at, limit).unwrap();
    assert_eq!(from_file.findings, from_text.findings);
    let lines: Vec<(Option<usize>, Severity)> = from_file.findings.iter().map(|f| (f.line, f.severity)).collect();
    assert_eq!(lines, [(Some(1), W), (Some(4), E)], "{:#?}", from_file.findings);
    assert!(!from_file.ok() && from_file.report.as_ref().is_some_and(|r| r.calls > 0));
    assert!(from_file.first_failure.is_some());
    // A name never defined: found before any call, and no call is made.
    let broken = validate(
        RewardInput::Source { name: "b.py", text: "def reward_function(params):\n    return LIMIT\n" },
        at,
        limit,
    )
    .unwrap();
    assert_eq!((broken.count(E), broken.report.is_none()), (1, true), "{broken:#?}");
    // A built-in has nothing to find.
    let builtin = validate(RewardInput::of_spec("builtin:center_line"), at, limit).unwrap();
    assert!(builtin.ok() && builtin.findings.is_empty() && builtin.report.is_some());
}
