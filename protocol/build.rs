//! Generates the message types from `proto/paddock.proto` (pure Rust: protox parses the file,
//! prost-build writes the code; no protoc needed).
//!
//! The job and its status are also JSON for people and scripts (`job status --json`, `up`'s
//! `summary.json`, a job spec's `[stop]` table): those messages derive serde's traits, with
//! the job state written as its name.

fn main() {
    println!("cargo:rerun-if-changed=proto/paddock.proto");
    let fds = protox::compile(["proto/paddock.proto"], ["proto"]).expect("proto/paddock.proto compiles");
    let mut cfg = prost_build::Config::new();
    cfg.btree_map(["."]);
    for t in [
        "Job",
        "TrackLines",
        "JobRecord",
        "AgentWork",
        "LearnerStatus",
        "WorldStats",
        "AgentStats",
        "DropCount",
        "DropCounts",
        "JobStatus",
        "JobSummary",
        "JobList",
        "AgentRow",
        "AgentList",
        "JobLog",
        "TokenList",
        "TokenRow",
    ] {
        cfg.type_attribute(format!("paddock.v1.{t}"), "#[derive(serde::Serialize)]");
    }
    // A job spec's `[stop]` table is this message: every key optional, unknown keys refused.
    cfg.type_attribute(
        "paddock.v1.JobStop",
        "#[derive(serde::Serialize, serde::Deserialize)] #[serde(deny_unknown_fields, default = \"crate::job::default_stop\")]",
    );
    for f in ["JobRecord.state", "JobSummary.state", "JobLog.state"] {
        cfg.field_attribute(format!("paddock.v1.{f}"), "#[serde(serialize_with = \"crate::job::state_name\")]");
    }
    cfg.field_attribute("paddock.v1.JobStatus.record", "#[serde(flatten)]");
    cfg.compile_fds(fds).expect("prost-build generates the messages");
}
