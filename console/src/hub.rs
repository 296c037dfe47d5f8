//! The console's one Zenoh session, on a thread of its own (Zenoh's blocking calls stay off
//! the web server's runtime): job-control requests from the pages and the API, answered one
//! at a time through a channel, and every second the coordinator's job list, kept for the
//! pages to read; the camera frames of the jobs someone is watching, kept as PNG; the cars on
//! the network (their status, once a second each) and what an organiser tells them (a job's
//! model to drive, the e-stop).
//!
//! Every request is the CLI's own (`coordinator::control::request`): a job started here is
//! the job `coordinator job status` shows, and the reverse.

use protocol::job_reply::Body;
use protocol::job_request::Kind;
use protocol::net::{self, DropCounters, NetArgs, Sub, try_next, zenoh};
use protocol::{CameraFrame, CarAssign, CarControl, CarStatus, JobReply, JobSummary, PROTOCOL_VERSION, keys};
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, mpsc};
use std::time::{Duration, Instant};
use tokio::sync::oneshot;

/// The latest camera frame of one agent of a job: which world, the picture as PNG.
#[derive(Clone, Debug)]
pub struct Frame {
    /// The agent that sent it.
    pub agent: String,
    /// The world it drives.
    pub world: String,
    /// The policy version it drove with.
    pub policy_version: u64,
    /// A grey PNG.
    pub png: Arc<Vec<u8>>,
    /// Frames received so far from this agent for this job.
    pub count: u64,
}

/// What the hub knows, read by every page without asking the coordinator.
#[derive(Default)]
pub struct Seen {
    /// The coordinator's jobs by id, as of `listed`.
    pub jobs: BTreeMap<String, JobSummary>,
    /// When the list last came (`None`: the coordinator has not answered yet).
    pub listed: Option<Instant>,
    /// The last refusal or silence, when the coordinator did not answer.
    pub error: Option<String>,
    /// The latest frame of each agent of each watched job (job, then agent).
    pub frames: BTreeMap<String, BTreeMap<String, Frame>>,
    /// Each car's latest status and when it came.
    pub cars: BTreeMap<String, (CarStatus, Instant)>,
}

/// A car is on the network while its status keeps coming (once a second): this long at most
/// since the last.
pub const CAR_SILENCE: Duration = Duration::from_secs(3);

enum Ask {
    Request(Box<Kind>, Duration, oneshot::Sender<Result<JobReply, String>>),
    Watch(String),
    Car(String, CarOrder, oneshot::Sender<Result<(), String>>),
}

/// What an organiser tells a car.
#[derive(Debug)]
pub enum CarOrder {
    /// Follow this job's models and drive this one (a PolicyUpdate of the job).
    Assign(String, Vec<u8>),
    /// Hold (true) or release the e-stop.
    Estop(bool),
}

/// The handle the web server holds.
#[derive(Clone)]
pub struct Hub {
    asks: mpsc::Sender<Ask>,
    /// What the hub has seen.
    pub seen: Arc<Mutex<Seen>>,
}

impl Hub {
    /// Open the session (`net`) and start the hub's thread.
    pub fn start(net: &NetArgs) -> anyhow::Result<Hub> {
        let session = net::open(net)?;
        let (tx, rx) = mpsc::channel();
        let seen = Arc::new(Mutex::new(Seen::default()));
        let s = seen.clone();
        std::thread::Builder::new().name("console-hub".into()).spawn(move || run(&session, &rx, &s))?;
        Ok(Hub { asks: tx, seen })
    }

    /// One job-control request, answered by the coordinator (or an error saying why not).
    pub async fn request(&self, kind: Kind, timeout: Duration) -> Result<JobReply, String> {
        let (tx, rx) = oneshot::channel();
        self.asks
            .send(Ask::Request(Box::new(kind), timeout, tx))
            .map_err(|_| "the console's hub has stopped".to_string())?;
        rx.await.map_err(|_| "the console's hub has stopped".to_string())?
    }

    /// Keep the camera frames of `job` from now on.
    pub fn watch(&self, job: &str) {
        let _ = self.asks.send(Ask::Watch(job.to_string()));
    }

    /// Wait until the coordinator has answered once (at most `timeout`); whether it has.
    pub fn wait_listed(&self, timeout: Duration) -> bool {
        let deadline = Instant::now() + timeout;
        while Instant::now() < deadline {
            if self.seen.lock().expect("hub state").listed.is_some() {
                return true;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        false
    }

    /// Tell a car something (on its own key; the car checks what it gets).
    pub async fn order(&self, car: &str, order: CarOrder) -> Result<(), String> {
        let (tx, rx) = oneshot::channel();
        self.asks
            .send(Ask::Car(car.to_string(), order, tx))
            .map_err(|_| "the console's hub has stopped".to_string())?;
        rx.await.map_err(|_| "the console's hub has stopped".to_string())?
    }

    /// The cars heard from within [`CAR_SILENCE`], by id.
    pub fn cars(&self) -> Vec<CarStatus> {
        let s = self.seen.lock().expect("hub state");
        s.cars.values().filter(|(_, at)| at.elapsed() <= CAR_SILENCE).map(|(c, _)| c.clone()).collect()
    }

    /// The job's summary as last listed.
    pub fn job(&self, id: &str) -> Option<JobSummary> {
        self.seen.lock().expect("hub state").jobs.get(id).cloned()
    }

    /// The latest camera frame of each agent of `job`, by agent.
    pub fn frames(&self, job: &str) -> BTreeMap<String, Frame> {
        self.seen.lock().expect("hub state").frames.get(job).cloned().unwrap_or_default()
    }
}

fn run(session: &zenoh::Session, asks: &mpsc::Receiver<Ask>, seen: &Mutex<Seen>) {
    let drops = DropCounters::default();
    let mut cameras: BTreeMap<String, Sub> = BTreeMap::new();
    let cars = net::subscribe(session, keys::ALL_CAR_STATUS)
        .map_err(|e| tracing::warn!("cannot hear the cars' status: {e}"))
        .ok();
    let mut last_list = Instant::now() - Duration::from_secs(10);
    loop {
        match asks.recv_timeout(Duration::from_millis(100)) {
            Ok(Ask::Request(kind, timeout, reply)) => {
                let r = coordinator::control::request(session, *kind, timeout).map_err(|e| format!("{e:#}"));
                let _ = reply.send(r);
            }
            Ok(Ask::Watch(job)) => {
                if let std::collections::btree_map::Entry::Vacant(slot) = cameras.entry(job) {
                    match net::subscribe(session, &keys::cameras(slot.key())) {
                        Ok(sub) => {
                            slot.insert(sub);
                        }
                        Err(e) => tracing::warn!(job = %slot.key(), "cannot subscribe to the job's camera frames: {e}"),
                    }
                }
            }
            Ok(Ask::Car(car, order, reply)) => {
                let r = match order {
                    CarOrder::Assign(job, model) => {
                        let m =
                            CarAssign { protocol_version: PROTOCOL_VERSION, car_id: car.clone(), job_id: job, model };
                        net::put(session, &keys::car_assign(&car), &m)
                    }
                    CarOrder::Estop(hold) => {
                        let m = CarControl { protocol_version: PROTOCOL_VERSION, car_id: car.clone(), estop: hold };
                        // Sent a few times: a car that misses one still gets it.
                        (0..3).try_for_each(|_| net::put(session, &keys::car_control(&car), &m))
                    }
                };
                let _ = reply.send(r.map_err(|e| format!("{e:#}")));
            }
            Err(mpsc::RecvTimeoutError::Timeout) => {}
            Err(mpsc::RecvTimeoutError::Disconnected) => return,
        }
        if let Some(sub) = &cars {
            while let Some((key, c)) = try_next::<CarStatus>(sub, &drops) {
                // A status on another car's key is someone else's word about that car: refused.
                if key.split('/').nth_back(1) != Some(c.car_id.as_str()) {
                    tracing::warn!("dropped a status of car '{}' sent on {key}", c.car_id);
                    continue;
                }
                seen.lock().expect("hub state").cars.insert(c.car_id.clone(), (c, Instant::now()));
            }
        }
        for (job, sub) in &cameras {
            while let Some((key, f)) = try_next::<CameraFrame>(sub, &drops) {
                let agent = keys::last(&key).to_string();
                match protocol::exchange::frame_from_wire(f, job, &agent) {
                    Ok(f) => {
                        let Some(img) = image::GrayImage::from_raw(f.width, f.height, f.gray) else { continue };
                        let mut png = std::io::Cursor::new(Vec::new());
                        if img.write_to(&mut png, image::ImageFormat::Png).is_ok() {
                            let mut s = seen.lock().expect("hub state");
                            let agents = s.frames.entry(job.clone()).or_default();
                            let count = agents.get(&agent).map_or(0, |f| f.count) + 1;
                            agents.insert(
                                agent.clone(),
                                Frame {
                                    agent,
                                    world: f.world,
                                    policy_version: f.policy_version,
                                    png: Arc::new(png.into_inner()),
                                    count,
                                },
                            );
                        }
                    }
                    Err(e) => drops.refuse("a camera frame", &e),
                }
            }
        }
        if last_list.elapsed() >= Duration::from_secs(1) {
            last_list = Instant::now();
            let r = coordinator::control::request(session, Kind::List(true), Duration::from_secs(2));
            let mut s = seen.lock().expect("hub state");
            match r {
                Ok(JobReply { body: Some(Body::Jobs(list)), .. }) => {
                    s.jobs = list.jobs.into_iter().map(|j| (j.id.clone(), j)).collect();
                    s.listed = Some(Instant::now());
                    s.error = None;
                }
                Ok(r) => s.error = Some(format!("the coordinator answered the job list with: {}", r.text)),
                Err(e) => s.error = Some(format!("{e:#}")),
            }
        }
    }
}
