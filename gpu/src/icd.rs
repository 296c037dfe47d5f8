//! Vulkan on a headless NVIDIA server. The driver's ICD file names its GLX library, which
//! cannot start without a display, so the Vulkan loader finds no adapter (wgpu: "no graphics
//! adapter found"); the same driver's EGL library works headless. At a role's start, when
//! Vulkan shows no GPU and NVIDIA's EGL library is present, the program runs itself again with
//! an ICD file naming that library (`VK_ICD_FILENAMES`, with the machine's other ICD files kept
//! behind it) and logs which ICD it used. A user's own `VK_ICD_FILENAMES` or `VK_DRIVER_FILES`
//! is left alone.

use std::ffi::OsString;
use std::path::{Path, PathBuf};

/// Where NVIDIA's EGL library lies in the usual images (the NVIDIA container runtime's mount
/// first, then the distributions' library folders).
pub const EGL_LIBRARIES: &[&str] = &[
    "/usr/local/nvidia/lib64/libEGL_nvidia.so.0",
    "/usr/lib/x86_64-linux-gnu/libEGL_nvidia.so.0",
    "/usr/lib/aarch64-linux-gnu/libEGL_nvidia.so.0",
    "/usr/lib64/libEGL_nvidia.so.0",
    "/usr/lib/libEGL_nvidia.so.0",
];

/// The folders the Vulkan loader reads ICD files from.
pub const ICD_FOLDERS: &[&str] = &["/etc/vulkan/icd.d", "/usr/share/vulkan/icd.d", "/usr/local/share/vulkan/icd.d"];

/// Set in the program run again, so that it is tried once.
const RETRIED: &str = "PADDOCK_VK_ICD_RETRIED";

/// What a role does at its start.
#[derive(Clone, Debug, PartialEq)]
pub enum Plan {
    /// Go on as it is.
    Keep,
    /// Say that this process runs on the ICD file its parent wrote.
    Retried(OsString),
    /// Run again with `VK_ICD_FILENAMES` naming a new ICD file for `egl`, then `files`.
    Retry {
        /// NVIDIA's EGL library.
        egl: PathBuf,
        /// The machine's other ICD files, kept behind it (lavapipe, say).
        files: Vec<PathBuf>,
    },
}

/// The decision, from what the machine shows. `icd_env`: `VK_ICD_FILENAMES` or
/// `VK_DRIVER_FILES` as set; `retried`: this process is already the retry; `egl`: NVIDIA's EGL
/// library, if present; `has_gpu`: whether Vulkan shows a hardware adapter (asked only when
/// the rest leaves the question open, since it starts the loader).
pub fn plan(
    icd_env: Option<OsString>,
    retried: bool,
    egl: Option<&Path>,
    others: &[PathBuf],
    has_gpu: impl FnOnce() -> bool,
) -> Plan {
    match (icd_env, retried, egl) {
        (Some(files), true, _) => Plan::Retried(files),
        (Some(_), false, _) | (None, true, _) | (None, false, None) => Plan::Keep,
        (None, false, Some(egl)) => {
            if has_gpu() {
                Plan::Keep
            } else {
                Plan::Retry { egl: egl.to_path_buf(), files: others.to_vec() }
            }
        }
    }
}

/// An ICD file naming `egl`, with the `api_version` of the driver's own file when there is
/// one (`driver_icd`: its text).
pub fn icd_json(egl: &Path, driver_icd: Option<&str>) -> String {
    let api = driver_icd
        .and_then(|t| serde_json::from_str::<serde_json::Value>(t).ok())
        .and_then(|v| v["ICD"]["api_version"].as_str().map(str::to_string))
        .unwrap_or_else(|| "1.3.0".into());
    serde_json::json!({
        "file_format_version": "1.0.1",
        "ICD": { "library_path": egl.display().to_string(), "api_version": api },
    })
    .to_string()
}

/// Whether Vulkan shows an adapter that is not a software one.
fn vulkan_has_gpu() -> bool {
    let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
        backends: wgpu::Backends::VULKAN,
        ..wgpu::InstanceDescriptor::new_without_display_handle_from_env()
    });
    pollster::block_on(instance.enumerate_adapters(wgpu::Backends::VULKAN))
        .iter()
        .any(|a| a.get_info().device_type != wgpu::DeviceType::Cpu)
}

/// The machine's ICD files: (NVIDIA's, the others).
fn icd_files() -> (Option<PathBuf>, Vec<PathBuf>) {
    let mut nvidia = None;
    let mut others = Vec::new();
    for dir in ICD_FOLDERS {
        let Ok(entries) = std::fs::read_dir(dir) else { continue };
        let mut files: Vec<PathBuf> = entries.filter_map(|e| e.ok()).map(|e| e.path()).collect();
        files.sort();
        for f in files.into_iter().filter(|f| f.extension().is_some_and(|e| e == "json")) {
            if f.file_name().is_some_and(|n| n.to_string_lossy().contains("nvidia")) {
                nvidia.get_or_insert(f);
            } else {
                others.push(f);
            }
        }
    }
    (nvidia, others)
}

/// At a role's start, before any thread: run again with NVIDIA's EGL ICD when Vulkan shows no
/// GPU and that library is present (see the module's docs). Returns when nothing needs doing,
/// or when running again failed (the renderer then says what it finds).
pub fn headless_nvidia() {
    let icd_env = std::env::var_os("VK_ICD_FILENAMES").or_else(|| std::env::var_os("VK_DRIVER_FILES"));
    let retried = std::env::var_os(RETRIED).is_some();
    let egl = EGL_LIBRARIES.iter().map(Path::new).find(|p| p.exists());
    let (nvidia, others) = if egl.is_some() && icd_env.is_none() { icd_files() } else { (None, Vec::new()) };
    match plan(icd_env, retried, egl, &others, vulkan_has_gpu) {
        Plan::Keep => {}
        Plan::Retried(files) => {
            tracing::info!(icd = %files.to_string_lossy(), "Vulkan ICD: NVIDIA's EGL library (the machine's ICD files showed no GPU)");
        }
        Plan::Retry { egl, files } => {
            let driver = nvidia.as_deref().and_then(|p| std::fs::read_to_string(p).ok());
            let json = std::env::temp_dir().join(format!("paddock-nvidia-egl-icd-{}.json", std::process::id()));
            if let Err(e) = std::fs::write(&json, icd_json(&egl, driver.as_deref())) {
                tracing::warn!(
                    "no GPU adapter, and NVIDIA's EGL ICD file could not be written ({}: {e})",
                    json.display()
                );
                return;
            }
            let list = std::env::join_paths(std::iter::once(json.clone()).chain(files))
                .unwrap_or_else(|_| json.clone().into());
            tracing::warn!(
                egl = %egl.display(),
                "Vulkan shows no GPU with the machine's ICD files (NVIDIA's names its GLX library, which needs a display): running again with its EGL library"
            );
            let exe = std::env::current_exe();
            let err = match exe {
                Ok(exe) => {
                    use std::os::unix::process::CommandExt;
                    std::process::Command::new(exe)
                        .args(std::env::args_os().skip(1))
                        .env("VK_ICD_FILENAMES", &list)
                        .env(RETRIED, "1")
                        .exec()
                }
                Err(e) => e,
            };
            tracing::warn!("could not run again with NVIDIA's EGL ICD ({err}); going on without it");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 33: a headless NVIDIA server is run again with the EGL ICD and nothing else is.
    #[test]
    fn a_headless_nvidia_server_is_run_again_with_the_egl_icd_and_nothing_else_is() {
        let egl = Path::new("/usr/local/nvidia/lib64/libEGL_nvidia.so.0");
        let lvp = vec![PathBuf::from("/usr/share/vulkan/icd.d/lvp_icd.x86_64.json")];
        let set = || Some(OsString::from("/tmp/x.json"));
        // (the user's ICD variable, retried, the EGL library, a GPU shown, what to do)
        type Row<'a> = (Option<OsString>, bool, Option<&'a Path>, bool, Plan);
        let table: Vec<Row> = vec![
            (None, false, Some(egl), false, Plan::Retry { egl: egl.into(), files: lvp.clone() }),
            (None, false, Some(egl), true, Plan::Keep),
            (None, false, None, false, Plan::Keep),
            (set(), false, Some(egl), false, Plan::Keep),
            (set(), true, Some(egl), false, Plan::Retried("/tmp/x.json".into())),
            (None, true, Some(egl), false, Plan::Keep),
        ];
        for (env, retried, lib, gpu, want) in table {
            let mut asked = false;
            let got = plan(env.clone(), retried, lib, &lvp, || {
                asked = true;
                gpu
            });
            assert_eq!(got, want, "{env:?} {retried} {lib:?} {gpu}");
            // The loader is started only when the answer depends on it.
            assert_eq!(asked, env.is_none() && !retried && lib.is_some(), "{env:?} {retried} {lib:?}");
        }
    }

    /// Issue 33: the EGL ICD file keeps the driver's API version.
    #[test]
    fn the_egl_icd_file_keeps_the_drivers_api_version() {
        let egl = Path::new("/usr/local/nvidia/lib64/libEGL_nvidia.so.0");
        let driver =
            r#"{"file_format_version":"1.0.1","ICD":{"library_path":"libGLX_nvidia.so.0","api_version":"1.4.312"}}"#;
        for (text, api) in [(Some(driver), "1.4.312"), (None, "1.3.0"), (Some("not json"), "1.3.0")] {
            let v: serde_json::Value = serde_json::from_str(&icd_json(egl, text)).unwrap();
            assert_eq!(v["ICD"]["library_path"], egl.display().to_string());
            assert_eq!(v["ICD"]["api_version"], api);
            assert_eq!(v["file_format_version"], "1.0.1");
        }
    }
}
