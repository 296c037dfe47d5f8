//! Unmodified DeepRacer reward files, run by embedded CPython (pyo3).
//!
//! The file is compiled once as a module (its folder goes on `sys.path`, so helper modules
//! beside it and installed packages import as usual). Each call fills one reused `dict` with
//! every params key; the `waypoints` list is built once per episode and shared by that
//! episode's calls. Calls for many environments run under one GIL acquisition.
//!
//! Every call has a time limit (default [`DEFAULT_TIME_LIMIT`]): a watchdog thread per reward
//! sees a call that has not returned in time and raises `RewardTimeLimit` (a `BaseException`,
//! so that a reward's `except Exception:` cannot swallow it) in the calling thread with
//! CPython's `PyThreadState_SetAsyncExc`, reached through `ctypes`; the call then fails with an
//! error that names the file, the step and where the code was stuck. (Code stuck inside one C
//! call that holds the GIL cannot be interrupted this way; Python code, loops included, can.)

use crate::params::RewardParams;
use crate::reward::{RewardError, check_reward, params_json};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyTuple};
use std::ffi::CString;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::time::{Duration, Instant};
use tracks::Track;

static MODULE_COUNTER: AtomicUsize = AtomicUsize::new(0);

/// How long one reward call may take unless the job says otherwise.
pub const DEFAULT_TIME_LIMIT: Duration = Duration::from_secs(1);

/// The exception raised in a reward call that ran out of time, and the helpers that raise
/// and withdraw it (plain Python: `ctypes` reaches CPython's C API without `unsafe` here).
const WATCHDOG_PY: &str = r#"
import ctypes
class RewardTimeLimit(BaseException):
    """The reward function did not return within Paddock's time limit."""
def fire(ident):
    return ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(ident), ctypes.py_object(RewardTimeLimit))
def withdraw(ident):
    ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(ident), None)
def ident():
    import threading
    return threading.get_ident()
"#;

/// The call in flight, shared with the watchdog thread.
#[derive(Default)]
struct Flight {
    /// Number of the call in flight (0: none).
    call: AtomicU64,
    /// When it started, in µs since `epoch`.
    started_us: AtomicU64,
    /// Python's id of the calling thread.
    ident: AtomicU64,
    /// The watchdog raised the time limit in call number `fired`.
    fired: AtomicU64,
    /// The reward is gone: the watchdog ends.
    done: AtomicBool,
}

/// The watchdog of one reward: wakes every 20 ms (at most a tenth of the limit), and under the
/// GIL (the calling thread is then paused inside Python) fires on a call past its limit.
fn watchdog(flight: Arc<Flight>, epoch: Instant, limit: Duration, helpers: Py<PyAny>) {
    let tick = (limit / 10).clamp(Duration::from_millis(1), Duration::from_millis(20));
    while !flight.done.load(Ordering::Relaxed) {
        std::thread::sleep(tick);
        let call = flight.call.load(Ordering::Acquire);
        if call == 0 || flight.fired.load(Ordering::Relaxed) == call {
            continue;
        }
        let started = Duration::from_micros(flight.started_us.load(Ordering::Relaxed));
        if epoch.elapsed().saturating_sub(started) < limit {
            continue;
        }
        Python::attach(|py| {
            // Still the same call, now that the caller is paused (it holds the GIL between calls).
            if flight.call.load(Ordering::Acquire) == call {
                let ident = flight.ident.load(Ordering::Relaxed);
                // Marked before it is raised: CPython may hand the GIL back to the caller
                // while `fire` is still running, and the caller, stopped by the exception,
                // must already see that the limit struck this call.
                flight.fired.store(call, Ordering::Release);
                if helpers.bind(py).getattr("fire").and_then(|f| f.call1((ident,))).is_err() {
                    flight.fired.store(0, Ordering::Release);
                }
            }
        });
    }
}

thread_local! {
    /// Python's id of this thread (asked once per thread).
    static IDENT: std::cell::Cell<Option<u64>> = const { std::cell::Cell::new(None) };
}

/// A loaded `reward_function(params)`.
pub struct PythonReward {
    path: PathBuf,
    func: Py<PyAny>,
    dict: Py<PyDict>,
    /// Per environment slot: (episode key, that episode's waypoint list).
    waypoints: Vec<Option<(u64, Py<PyList>)>>,
    /// The time limit per call.
    limit: Duration,
    flight: Arc<Flight>,
    epoch: Instant,
    helpers: Py<PyAny>,
    calls: u64,
}

impl Drop for PythonReward {
    fn drop(&mut self) {
        self.flight.done.store(true, Ordering::Relaxed);
    }
}

impl PythonReward {
    /// Read and compile `path`, and find `reward_function` in it.
    pub fn load(path: &Path) -> Result<PythonReward, RewardError> {
        let origin = path.display().to_string();
        let source = std::fs::read_to_string(path).map_err(|e| RewardError::Load { origin, msg: e.to_string() })?;
        Self::load_text(path, &source)
    }

    /// [`PythonReward::load`] of the file's text, read already.
    pub fn load_text(path: &Path, source: &str) -> Result<PythonReward, RewardError> {
        let dir = path.parent().map(|d| if d.as_os_str().is_empty() { Path::new(".") } else { d });
        Self::compile(source, path, dir)
    }

    /// Compile a reward file's text received from elsewhere (a job from the network):
    /// `name` is its file name, which tracebacks show; nothing is written to disk and no
    /// folder goes on `sys.path`.
    pub fn from_source(source: &str, name: &str) -> Result<PythonReward, RewardError> {
        Self::compile(source, Path::new(name), None)
    }

    fn compile(source: &str, path: &Path, dir: Option<&Path>) -> Result<PythonReward, RewardError> {
        let origin = path.display().to_string();
        let load_err = |msg: String| RewardError::Load { origin: origin.clone(), msg };
        let code = CString::new(source).map_err(|_| load_err("the file contains a NUL byte".into()))?;
        let file_name = CString::new(origin.clone()).map_err(|_| load_err("path contains a NUL byte".into()))?;
        let n = MODULE_COUNTER.fetch_add(1, Ordering::Relaxed);
        let module_name = CString::new(format!("paddock_reward_{n}")).expect("no NUL");
        Python::attach(|py| {
            if let Some(dir) = dir {
                let dir = dir.canonicalize().unwrap_or_else(|_| dir.to_path_buf());
                let sys_path = py.import("sys").and_then(|s| s.getattr("path"));
                if let Ok(sys_path) = sys_path {
                    let _ = sys_path.call_method1("insert", (0, dir.display().to_string()));
                }
            }
            let module = pyo3::types::PyModule::from_code(py, &code, &file_name, &module_name)
                .map_err(|e| load_err(format!("could not compile or run the file:\n{}", format_traceback(py, &e))))?;
            let func =
                module.getattr("reward_function").map_err(|_| load_err("defines no reward_function(params)".into()))?;
            if !func.is_callable() {
                return Err(load_err("reward_function is not callable".into()));
            }
            let helpers_code = CString::new(WATCHDOG_PY).expect("no NUL");
            let helpers = pyo3::types::PyModule::from_code(
                py,
                &helpers_code,
                c"paddock_reward_watchdog.py",
                &CString::new(format!("paddock_reward_watchdog_{n}")).expect("no NUL"),
            )
            .map_err(|e| load_err(format!("the reward watchdog: {e}")))?;
            let mut reward = PythonReward {
                path: path.to_path_buf(),
                func: func.unbind(),
                dict: PyDict::new(py).unbind(),
                waypoints: Vec::new(),
                limit: Duration::ZERO,
                flight: Arc::default(),
                epoch: Instant::now(),
                helpers: helpers.into_any().unbind(),
                calls: 0,
            };
            reward.set_time_limit(py, DEFAULT_TIME_LIMIT);
            Ok(reward)
        })
    }

    /// Let each call take at most `limit` (a new watchdog replaces the old one).
    pub fn time_limit(&mut self, limit: Duration) {
        Python::attach(|py| self.set_time_limit(py, limit));
    }

    fn set_time_limit(&mut self, py: Python<'_>, limit: Duration) {
        self.flight.done.store(true, Ordering::Relaxed);
        self.flight = Arc::default();
        self.limit = limit;
        let (flight, epoch, helpers) = (self.flight.clone(), self.epoch, self.helpers.clone_ref(py));
        // Dropped with its reward: `done` ends it within a tick.
        let spawned = std::thread::Builder::new()
            .name("reward-watchdog".into())
            .spawn(move || watchdog(flight, epoch, limit, helpers));
        if let Err(e) = spawned {
            tracing::warn!("no watchdog for the reward's time limit: {e}");
        }
    }

    /// The file this reward came from.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Rewards for several environments' steps under one GIL acquisition. Each item is
    /// (slot, episode key, track, params); the waypoint list of a slot is rebuilt when its
    /// episode key changes.
    pub fn call_batch<'a>(
        &mut self,
        items: impl Iterator<Item = (usize, u64, &'a Track, &'a RewardParams)>,
        out: &mut Vec<f64>,
    ) -> Result<(), RewardError> {
        Python::attach(|py| {
            for (slot, key, track, params) in items {
                out.push(self.call_one(py, slot, key, track, params)?);
            }
            Ok(())
        })
    }

    /// One reward (takes the GIL).
    pub fn call(&mut self, slot: usize, key: u64, track: &Track, params: &RewardParams) -> Result<f64, RewardError> {
        Python::attach(|py| self.call_one(py, slot, key, track, params))
    }

    fn call_one(
        &mut self,
        py: Python<'_>,
        slot: usize,
        key: u64,
        track: &Track,
        p: &RewardParams,
    ) -> Result<f64, RewardError> {
        let internal = |e: PyErr| RewardError::Raised {
            step: p.steps,
            traceback: format_traceback(py, &e),
            params: params_json(p),
        };
        if self.waypoints.len() <= slot {
            self.waypoints.resize_with(slot + 1, || None);
        }
        let stale = !matches!(&self.waypoints[slot], Some((k, _)) if *k == key);
        if stale {
            let list = PyList::empty(py);
            for w in track.waypoints() {
                list.append(PyTuple::new(py, [w.x, w.y]).map_err(internal)?).map_err(internal)?;
            }
            self.waypoints[slot] = Some((key, list.unbind()));
        }
        let waypoints = self.waypoints[slot].as_ref().map(|(_, l)| l.bind(py).clone()).expect("set above");
        let d = self.dict.bind(py);
        fill_dict(py, d, p, &waypoints).map_err(internal)?;
        let ident = match IDENT.get() {
            Some(i) => i,
            None => {
                let i: u64 =
                    self.helpers.bind(py).getattr("ident").and_then(|f| f.call0()?.extract()).map_err(internal)?;
                IDENT.set(Some(i));
                i
            }
        };
        self.calls += 1;
        let call = self.calls;
        self.flight.ident.store(ident, Ordering::Relaxed);
        self.flight.started_us.store(self.epoch.elapsed().as_micros() as u64, Ordering::Relaxed);
        self.flight.call.store(call, Ordering::Release);
        let result = self.func.bind(py).call1((d,));
        self.flight.call.store(0, Ordering::Release);
        if self.flight.fired.load(Ordering::Acquire) == call {
            // The limit was raised in this call; if the call returned before the exception
            // arrived, withdraw it so that it cannot strike later Python code of this thread.
            let _ = self.helpers.bind(py).getattr("withdraw").and_then(|f| f.call1((ident,)));
            return Err(RewardError::TimedOut {
                file: self.path.display().to_string(),
                step: p.steps,
                limit: self.limit,
                traceback: result.err().map(|e| format_traceback(py, &e)).unwrap_or_default(),
                params: params_json(p),
            });
        }
        let result = result.map_err(|e| RewardError::Raised {
            step: p.steps,
            traceback: format_traceback(py, &e),
            params: params_json(p),
        })?;
        let value: f64 = if result.is_instance_of::<pyo3::types::PyString>() || result.is_none() {
            return Err(bad_type(&result, p));
        } else {
            result.extract().map_err(|_| bad_type(&result, p))?
        };
        check_reward(value, p)
    }
}

fn bad_type(result: &Bound<'_, PyAny>, p: &RewardParams) -> RewardError {
    let ty = result.get_type().name().map(|n| n.to_string()).unwrap_or_else(|_| "?".into());
    let repr = result.repr().map(|r| r.to_string()).unwrap_or_else(|_| "<unrepresentable>".into());
    RewardError::BadValue {
        step: p.steps,
        value: format!("{repr} ({ty})"),
        why: "expected a number (int or float)".into(),
        params: params_json(p),
    }
}

/// Set every params key on `d` (all keys, every call, as DeepRacer's fresh deep copy would).
fn fill_dict<'py>(
    py: Python<'py>,
    d: &Bound<'py, PyDict>,
    p: &RewardParams,
    waypoints: &Bound<'py, PyList>,
) -> PyResult<()> {
    use pyo3::intern;
    d.set_item(intern!(py, "all_wheels_on_track"), p.all_wheels_on_track)?;
    d.set_item(intern!(py, "x"), p.x)?;
    d.set_item(intern!(py, "y"), p.y)?;
    d.set_item(intern!(py, "heading"), p.heading)?;
    d.set_item(intern!(py, "distance_from_center"), p.distance_from_center)?;
    d.set_item(intern!(py, "is_left_of_center"), p.is_left_of_center)?;
    d.set_item(intern!(py, "is_offtrack"), p.is_offtrack)?;
    d.set_item(intern!(py, "is_crashed"), p.is_crashed)?;
    d.set_item(intern!(py, "is_reversed"), p.is_reversed)?;
    d.set_item(intern!(py, "progress"), p.progress)?;
    d.set_item(intern!(py, "speed"), p.speed)?;
    d.set_item(intern!(py, "steering_angle"), p.steering_angle)?;
    d.set_item(intern!(py, "steps"), p.steps)?;
    d.set_item(intern!(py, "track_width"), p.track_width)?;
    d.set_item(intern!(py, "track_length"), p.track_length)?;
    d.set_item(intern!(py, "waypoints"), waypoints)?;
    d.set_item(intern!(py, "closest_waypoints"), PyList::new(py, p.closest_waypoints)?)?;
    let o = &p.objects;
    d.set_item(intern!(py, "closest_objects"), PyList::new(py, o.closest_objects)?)?;
    let pairs = o.objects_location.iter().map(|l| PyList::new(py, l)).collect::<PyResult<Vec<_>>>()?;
    d.set_item(intern!(py, "objects_location"), PyList::new(py, pairs)?)?;
    d.set_item(intern!(py, "objects_left_of_center"), PyList::new(py, &o.objects_left_of_center)?)?;
    d.set_item(intern!(py, "objects_speed"), PyList::new(py, &o.objects_speed)?)?;
    d.set_item(intern!(py, "objects_heading"), PyList::new(py, &o.objects_heading)?)?;
    d.set_item(intern!(py, "objects_distance_from_center"), PyList::new(py, &o.objects_distance_from_center)?)?;
    d.set_item(intern!(py, "objects_distance"), PyList::new(py, &o.objects_distance)?)?;
    d.set_item(intern!(py, "object_in_camera"), p.object_in_camera)?;
    d.set_item(intern!(py, "projection_distance"), p.projection_distance)?;
    d.set_item(intern!(py, "sim_time"), p.sim_time)?;
    Ok(())
}

/// Python's own rendering of an exception with its traceback.
pub fn format_traceback(py: Python<'_>, err: &PyErr) -> String {
    let formatted = py.import("traceback").and_then(|tb| {
        tb.call_method1("format_exception", (err.get_type(py), err.value(py), err.traceback(py)))
            .and_then(|lines| lines.extract::<Vec<String>>())
    });
    match formatted {
        Ok(lines) => lines.concat().trim_end().to_string(),
        Err(_) => err.to_string(),
    }
}
