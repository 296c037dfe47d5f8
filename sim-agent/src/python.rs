//! Unmodified DeepRacer reward files, run by embedded CPython (pyo3).
//!
//! The file is compiled once as a module (its folder goes on `sys.path`, so helper modules
//! beside it and installed packages import as usual). Each call fills one reused `dict` with
//! every params key; the `waypoints` list is built once per episode and shared by that
//! episode's calls. Calls for many environments run under one GIL acquisition.

use crate::params::RewardParams;
use crate::reward::{RewardError, check_reward, params_json};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyTuple};
use std::ffi::CString;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use tracks::Track;

static MODULE_COUNTER: AtomicUsize = AtomicUsize::new(0);

/// A loaded `reward_function(params)`.
pub struct PythonReward {
    path: PathBuf,
    func: Py<PyAny>,
    dict: Py<PyDict>,
    /// Per environment slot: (episode key, that episode's waypoint list).
    waypoints: Vec<Option<(u64, Py<PyList>)>>,
}

impl PythonReward {
    /// Read and compile `path`, and find `reward_function` in it.
    pub fn load(path: &Path) -> Result<PythonReward, RewardError> {
        let origin = path.display().to_string();
        let source = std::fs::read_to_string(path).map_err(|e| RewardError::Load { origin, msg: e.to_string() })?;
        let dir = path.parent().map(|d| if d.as_os_str().is_empty() { Path::new(".") } else { d });
        Self::compile(&source, path, dir)
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
            Ok(PythonReward {
                path: path.to_path_buf(),
                func: func.unbind(),
                dict: PyDict::new(py).unbind(),
                waypoints: Vec::new(),
            })
        })
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
        let result = self.func.bind(py).call1((d,)).map_err(|e| RewardError::Raised {
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
    d.set_item(intern!(py, "closest_objects"), PyList::new(py, p.closest_objects)?)?;
    d.set_item(intern!(py, "objects_location"), PyList::empty(py))?;
    d.set_item(intern!(py, "objects_left_of_center"), PyList::empty(py))?;
    d.set_item(intern!(py, "objects_speed"), PyList::empty(py))?;
    d.set_item(intern!(py, "objects_heading"), PyList::empty(py))?;
    d.set_item(intern!(py, "objects_distance_from_center"), PyList::empty(py))?;
    d.set_item(intern!(py, "objects_distance"), PyList::empty(py))?;
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
