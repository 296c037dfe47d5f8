//! One table of exit codes for every Paddock binary (`coordinator`, `learner`, `sim-agent`,
//! `deploy`), printed at the end of each one's `--help`, and the one way they end.

/// Success.
pub const SUCCESS: i32 = 0;
/// A failure: an error (printed on stderr with its causes), a job that failed, a check that
/// did not pass.
pub const FAILURE: i32 = 1;
/// The command line is wrong (clap says how; clap's own code).
pub const USAGE: i32 = 2;
/// `coordinator train` trained to its stop, but writes to the run folder failed.
pub const WRITES_FAILED: i32 = 3;

/// The table, as `--help` prints it.
pub const TABLE: &str = "\
Exit codes (the same for coordinator, learner, sim-agent and deploy):
  0  success
  1  failure: an error (printed on stderr), a job that failed, a check that did not pass
     (`reward validate`, a benchmark's verdict)
  2  usage: the command line is wrong
  3  `coordinator train`: training reached its stop, but writes to the run folder failed
     (a full disk); the last checkpoint is whole";

/// End the process: with `result`'s code, or with [`FAILURE`] after printing the error and
/// its causes (`{:#}`) on stderr.
pub fn exit<E: std::fmt::Display>(result: Result<i32, E>) -> ! {
    match result {
        Ok(code) => std::process::exit(code),
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::exit(FAILURE)
        }
    }
}
