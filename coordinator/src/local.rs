//! The in-process transport: the training run ([`learner::run`]) on this thread and a sim
//! worker ([`sim_agent::worker::Worker`]) on another, joined by channels. The same two
//! loops run across machines over Zenoh; only these links differ.

use learner::run::{Inbound, Link, LinkError, RunStatus};
use policy::exchange::{Credit, EvalRequest, PolicyVersion};
use policy::folder::Manifest;
use policy::signature::Signer;
use sim_agent::worker::{Worker, WorkerError, WorkerInbound, WorkerLink, WorkerOutbound};
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, TryRecvError, channel};
use std::thread::JoinHandle;
use std::time::Duration;

/// The learner's side.
pub struct LocalLink {
    to_worker: Sender<WorkerInbound>,
    from_worker: Receiver<Inbound>,
    worker_id: String,
    worker: Option<JoinHandle<()>>,
    /// The run's last reported status.
    pub last_status: Option<RunStatus>,
}

/// The worker's side.
struct ChannelWorkerLink {
    inbox: Receiver<WorkerInbound>,
    outbox: Sender<Inbound>,
}

impl WorkerLink for ChannelWorkerLink {
    fn next(&mut self, timeout: Duration, _need_policy: bool) -> Result<Option<WorkerInbound>, WorkerError> {
        let got = if timeout.is_zero() {
            match self.inbox.try_recv() {
                Ok(m) => Ok(m),
                Err(TryRecvError::Empty) => return Ok(None),
                Err(TryRecvError::Disconnected) => Err(()),
            }
        } else {
            match self.inbox.recv_timeout(timeout) {
                Ok(m) => Ok(m),
                Err(RecvTimeoutError::Timeout) => return Ok(None),
                Err(RecvTimeoutError::Disconnected) => Err(()),
            }
        };
        // The learner is gone: the run is over.
        Ok(Some(got.unwrap_or(WorkerInbound::End)))
    }

    fn send(&mut self, out: WorkerOutbound) -> Result<(), WorkerError> {
        let m = match out {
            WorkerOutbound::Experience(e) => Inbound::Experience(e),
            WorkerOutbound::Eval(r) => Inbound::Eval(r),
        };
        // A closed channel means the run ended; what is left is not needed.
        let _ = self.outbox.send(m);
        Ok(())
    }
}

impl LocalLink {
    /// Start `worker` on its own thread.
    pub fn start(mut worker: Worker, worker_id: &str) -> LocalLink {
        let (to_worker, inbox) = channel();
        let (outbox, from_worker) = channel();
        let handle = std::thread::Builder::new()
            .name("sim-worker".into())
            .spawn(move || {
                let mut link = ChannelWorkerLink { inbox, outbox: outbox.clone() };
                if let Err(e) = worker.drive(&mut link) {
                    let _ = outbox.send(Inbound::Failed { worker: "local".into(), error: format!("{e:#}") });
                }
            })
            .expect("spawn the worker thread");
        LocalLink { to_worker, from_worker, worker_id: worker_id.into(), worker: Some(handle), last_status: None }
    }

    fn send(&self, m: WorkerInbound) -> Result<(), LinkError> {
        self.to_worker.send(m).map_err(|_| LinkError("the sim worker thread has ended".into()))
    }
}

impl Drop for LocalLink {
    fn drop(&mut self) {
        let _ = self.to_worker.send(WorkerInbound::End);
        if let Some(h) = self.worker.take() {
            let _ = h.join();
        }
    }
}

impl Link for LocalLink {
    fn publish(&mut self, policy: &PolicyVersion, _manifest: &Manifest, _signer: &Signer) -> Result<(), LinkError> {
        self.send(WorkerInbound::Policy(policy.clone()))
    }

    fn grant(&mut self, credit: &Credit) -> Result<(), LinkError> {
        self.send(WorkerInbound::Credit(credit.clone()))
    }

    fn request_eval(&mut self, req: &EvalRequest) -> Result<(), LinkError> {
        self.send(WorkerInbound::Eval(req.clone()))
    }

    fn next(&mut self, timeout: Duration) -> Result<Option<Inbound>, LinkError> {
        let got = if timeout.is_zero() {
            self.from_worker.try_recv().ok()
        } else {
            self.from_worker.recv_timeout(timeout).ok()
        };
        Ok(got)
    }

    fn status(&mut self, status: &RunStatus) -> Result<(), LinkError> {
        self.last_status = Some(status.clone());
        Ok(())
    }

    fn workers(&mut self) -> Vec<String> {
        vec![self.worker_id.clone()]
    }
}
