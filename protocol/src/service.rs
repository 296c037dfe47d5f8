//! Roles as systemd services: the unit `coordinator service print ROLE` writes and `join
//! --service` installs. Restarted on failure but not on a usage error (exit 2), run as a
//! dynamic user with a state folder (`/var/lib/paddock-ROLE`, which holds the credentials
//! folder `certs/` and the role's working files), the rest of the file system read-only, no
//! new privileges, no capabilities, system calls and address families limited, and a memory
//! ceiling. `systemd-analyze verify` and `security --offline=true` check it in the tests.

use crate::secure::Role;
use std::path::{Path, PathBuf};

/// Why a unit cannot be written or installed.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct ServiceError(pub String);

/// The roles that run as a service, with their binary and what they are.
pub const SERVICES: [(&str, &str, &str); 4] = [
    ("agent", "sim-agent", "Paddock sim agent"),
    ("learner", "learner", "Paddock learner"),
    ("coordinator", "coordinator", "Paddock coordinator"),
    ("car", "deploy", "Paddock on-car agent"),
];

/// The unit's file name for `role`.
pub fn unit_name(role: &str) -> String {
    format!("paddock-{role}.service")
}

/// The credentials folder a service of `role` reads (inside its state folder).
pub fn certs_dir(role: &str) -> PathBuf {
    Path::new("/var/lib").join(format!("paddock-{role}")).join("certs")
}

/// A systemd unit running `role` (`agent`, `learner`, `coordinator`, `car`) from `bin` with
/// `args` after `serve --certs …`, its memory held under `memory_max` (systemd's syntax).
pub fn unit(role: &str, bin: &Path, memory_max: &str, args: &[String]) -> Result<String, ServiceError> {
    let (_, _, what) = SERVICES.iter().find(|(r, _, _)| *r == role).ok_or_else(|| {
        ServiceError(format!(
            "role '{role}': expected one of {}",
            SERVICES.iter().map(|(r, _, _)| *r).collect::<Vec<_>>().join(", ")
        ))
    })?;
    if !bin.is_absolute() {
        return Err(ServiceError(format!("{}: the binary's path must be absolute", bin.display())));
    }
    if memory_max.is_empty() || !memory_max.chars().all(|c| c.is_ascii_alphanumeric() || c == '.' || c == '%') {
        return Err(ServiceError(format!("--memory-max '{memory_max}': expected a size like 8G or 50%")));
    }
    for a in args {
        if a.is_empty() || a == ";" || a.chars().any(|c| c.is_control() || c == '"' || c == '\'' || c == '\\') {
            return Err(ServiceError(format!(
                "argument '{}': an empty argument, a lone ';', control characters, quotes and \\ are not allowed",
                a.escape_debug()
            )));
        }
    }
    let state = format!("paddock-{role}");
    let mut exec = vec![bin.display().to_string()];
    exec.extend(serve_words(role).iter().map(|s| s.to_string()));
    exec.extend(["--certs".to_string(), format!("%S/{state}/certs")]);
    if role == "coordinator" {
        exec.push("--db".into());
        exec.push(format!("%S/{state}/coordinator.redb"));
    }
    // systemd reads `%` as a specifier and `$` as a variable in ExecStart: doubled, they stand
    // for themselves (an IPv6 address's zone, `fe80::1%eth0`, reaches the role as written).
    exec.extend(args.iter().map(|a| a.replace('%', "%%").replace('$', "$$")));
    let quoted: Vec<String> =
        exec.iter().map(|a| if a.contains(' ') { format!("\"{a}\"") } else { a.clone() }).collect();
    // The camera's software renderer (lavapipe) and a GPU's driver compile code at run time:
    // writable-and-executable memory stays allowed for the roles that may use them.
    let jit = matches!(role, "agent" | "learner");
    let mut u = format!(
        "# {unit}: written by `coordinator service print {role}`.\n\
         [Unit]\n\
         Description={what}\n\
         After=network-online.target\n\
         Wants=network-online.target\n\
         \n\
         [Service]\n\
         Type=exec\n\
         ExecStart={exec}\n\
         Restart=on-failure\n\
         RestartSec=5s\n\
         # A usage error (exit {usage}) is not fixed by restarting.\n\
         RestartPreventExitStatus={usage}\n\
         TimeoutStopSec=30s\n\
         DynamicUser=yes\n\
         StateDirectory={state}\n\
         StateDirectoryMode=0700\n\
         WorkingDirectory=%S/{state}\n\
         Environment=RUST_LOG=info\n\
         UMask=0077\n\
         MemoryMax={memory_max}\n\
         TasksMax=4096\n\
         LimitNOFILE=65536\n\
         NoNewPrivileges=yes\n\
         CapabilityBoundingSet=\n\
         AmbientCapabilities=\n\
         ProtectSystem=strict\n\
         ProtectHome=yes\n\
         PrivateTmp=yes\n\
         PrivateUsers=yes\n\
         ProtectHostname=yes\n\
         ProtectClock=yes\n\
         ProtectKernelTunables=yes\n\
         ProtectKernelModules=yes\n\
         ProtectKernelLogs=yes\n\
         ProtectControlGroups=yes\n\
         ProtectProc=invisible\n\
         ProcSubset=pid\n\
         RestrictNamespaces=yes\n\
         RestrictRealtime=yes\n\
         RestrictSUIDSGID=yes\n\
         RemoveIPC=yes\n\
         LockPersonality=yes\n\
         RestrictAddressFamilies=AF_INET AF_INET6 AF_UNIX AF_NETLINK\n\
         SystemCallArchitectures=native\n\
         SystemCallFilter=@system-service\n\
         SystemCallFilter=~@privileged @mount @swap @reboot @raw-io @module @obsolete @cpu-emulation @debug\n\
         SystemCallErrorNumber=EPERM\n",
        unit = unit_name(role),
        exec = quoted.join(" "),
        usage = crate::exit::USAGE,
    );
    if jit {
        // A GPU, when there is one: DRM render nodes and NVIDIA's devices only.
        u.push_str(
            "DevicePolicy=closed\n\
             DeviceAllow=char-drm rw\n\
             DeviceAllow=/dev/nvidiactl rw\n\
             DeviceAllow=/dev/nvidia0 rw\n\
             DeviceAllow=/dev/nvidia-uvm rw\n\
             DeviceAllow=/dev/nvidia-uvm-tools rw\n",
        );
    } else {
        u.push_str("PrivateDevices=yes\nMemoryDenyWriteExecute=yes\n");
    }
    u.push_str("\n[Install]\nWantedBy=multi-user.target\n");
    Ok(u)
}

/// The words after the binary that run `role` on the network (`deploy` drives without a
/// subcommand).
pub fn serve_words(role: &str) -> &'static [&'static str] {
    if role == "car" { &[] } else { &["serve"] }
}

/// The binary of `role` installed beside the running one (`/usr/local/bin/sim-agent` when
/// this is `/usr/local/bin/coordinator`).
pub fn sibling_binary(role: &str) -> Result<PathBuf, ServiceError> {
    let (_, bin, _) = SERVICES.iter().find(|(r, _, _)| *r == role).ok_or_else(|| {
        ServiceError(format!(
            "role '{role}': expected one of {}",
            SERVICES.iter().map(|(r, _, _)| *r).collect::<Vec<_>>().join(", ")
        ))
    })?;
    let me = std::env::current_exe().map_err(|e| ServiceError(format!("this program's path: {e}")))?;
    let me = me.canonicalize().unwrap_or(me);
    Ok(me.with_file_name(bin))
}

/// Whether systemd runs this machine (its runtime folder exists).
pub fn systemd_runs() -> bool {
    Path::new("/run/systemd/system").is_dir()
}

/// Whether a service can be installed here: refused, with what to do instead, where systemd
/// does not run.
pub fn require_systemd() -> Result<(), ServiceError> {
    if systemd_runs() {
        return Ok(());
    }
    Err(ServiceError(
        "systemd does not run this machine (no /run/systemd/system): join with --certs DIR and start \
         the role by hand with `serve --certs DIR`, or print a unit with `coordinator service print ROLE`"
            .into(),
    ))
}

/// Installing a service takes root (the unit goes into /etc/systemd/system).
pub fn require_root() -> Result<(), ServiceError> {
    #[cfg(unix)]
    if !nix::unistd::geteuid().is_root() {
        return Err(ServiceError(
            "--service installs into /etc/systemd/system, which takes root: run the join with sudo".into(),
        ));
    }
    Ok(())
}

/// `join --service`: write the unit into /etc/systemd/system, reload systemd, and enable and
/// start it. The credentials must already be in [`certs_dir`].
pub fn install(role: &str, unit_text: &str) -> Result<PathBuf, ServiceError> {
    require_systemd()?;
    let path = Path::new("/etc/systemd/system").join(unit_name(role));
    std::fs::write(&path, unit_text).map_err(|e| ServiceError(format!("{}: {e}", path.display())))?;
    // `restart`, not `start`: a machine that joined again runs with its new credentials.
    for args in [vec!["daemon-reload"], vec!["enable", &unit_name(role)], vec!["restart", &unit_name(role)]] {
        let out = std::process::Command::new("systemctl")
            .args(&args)
            .output()
            .map_err(|e| ServiceError(format!("systemctl: {e}")))?;
        if !out.status.success() {
            return Err(ServiceError(format!(
                "systemctl {}: {}",
                args.join(" "),
                String::from_utf8_lossy(&out.stderr).trim()
            )));
        }
    }
    Ok(path)
}

/// The role a [`Role`] runs as a service under.
pub fn service_role(role: Role) -> &'static str {
    match role {
        Role::Agent => "agent",
        Role::Learner => "learner",
        Role::Car => "car",
        Role::Coordinator | Role::Operator => "coordinator",
    }
}
