//! Paddock's console: DeepRacer's racer workflow in a browser, on the user's machine.
//!
//! A thin web shell (axum) over the coordinator's library: models are job specs the CLI's
//! parser makes ([`models`]), started and watched through the job-control protocol's client
//! ([`hub`]), kept in a data folder ([`store`]). The pages ([`pages`]) and the JSON API
//! ([`api`]) share every function; [`auth`] guards both with the console's token.
//!
//! ```text
//! browser ──HTTP──► axum router ─┬─ pages (templates, assets)
//!                                ├─ api (JSON, server-sent events)
//!                                └─ hub thread ──Zenoh──► coordinator serve ─► learner, agents
//!                   data folder ◄┘ (models/NAME: DeepRacer's files, job.toml, run/)
//! ```

pub mod accounts;
pub mod api;
pub mod auth;
pub mod bench;
pub mod counters;
pub mod evaluations;
pub mod fleet;
pub mod hub;
pub mod live;
pub mod models;
pub mod pages;
pub mod pictures;
pub mod quota;
pub mod race_api;
pub mod races;
pub mod store;
pub mod tls;
pub mod users;

use anyhow::{Context, Result, bail};
use axum::Router;
use axum::routing::{get, patch, post};
use std::net::SocketAddr;
use std::sync::Arc;

/// The API's OpenAPI document.
pub const OPENAPI: &str = include_str!("openapi.json");

/// The largest request body (a reward file is at most 140,000 characters; an upload's limit
/// is its own).
pub const MAX_BODY: usize = 1 << 20;

/// How the console serves.
pub struct Options {
    /// Where it listens.
    pub listen: SocketAddr,
    /// Listen beyond loopback without TLS and login.
    pub insecure: bool,
    /// The secret (a new one when `None`).
    pub token: Option<String>,
    /// Race entries evaluated at once.
    pub race_workers: usize,
    /// Live races replay at this many simulator seconds a second (1: as driven).
    pub live_speed: f64,
    /// Serve HTTPS with this certificate chain and key (PEM files).
    pub tls: Option<(std::path::PathBuf, std::path::PathBuf)>,
}

/// The first admin, made when the data folder has no user yet: `--admin NAME` with the
/// password of `--admin-password-file` or, without it, a new one printed once.
pub fn first_admin(users: &users::Users, name: &str, password_file: Option<&std::path::Path>) -> Result<()> {
    if users.any() {
        return Ok(());
    }
    let (password, printed) = match password_file {
        Some(f) => {
            let text = std::fs::read_to_string(f).with_context(|| format!("--admin-password-file {}", f.display()))?;
            (text.trim_end_matches(['\n', '\r']).to_string(), false)
        }
        None => (users::new_password(), true),
    };
    users.add(name, users::Role::Admin, &password).with_context(|| format!("--admin {name}"))?;
    if printed {
        println!("admin        {name}, password {password} (shown once: keep it)");
    }
    tracing::info!(user = %name, "the first admin made");
    Ok(())
}

/// Refuse to listen beyond loopback unless the console serves HTTPS (`tls`) and asks for a
/// login (`logins`: the data folder has users), or `--insecure` says to: otherwise its token,
/// or its users' passwords, would cross the network in the clear, or anyone there could use it.
pub fn check_listen(listen: &SocketAddr, insecure: bool, tls: bool, logins: bool) -> Result<()> {
    if listen.ip().is_loopback() || insecure {
        return Ok(());
    }
    if !tls {
        bail!(
            "--listen {listen} is beyond loopback: serve HTTPS there (--tls-cert and --tls-key; \
             `coordinator certs issue DIR console NAME` makes a certificate from the cluster's CA), \
             listen on 127.0.0.1, or pass --insecure"
        );
    }
    if !logins {
        bail!(
            "--listen {listen} is beyond loopback: there the console asks for a login, and the data folder has no \
             user yet: make the first admin (--admin NAME, or `coordinator users add NAME --role admin --data DIR`)"
        );
    }
    Ok(())
}

/// The router: pages, API, assets; everything but the assets behind the token.
pub fn router(app: api::App) -> Router {
    let guarded = Router::new()
        .route("/", get(pages::models))
        .route("/models/rows", get(pages::model_rows))
        .route("/models/new", get(pages::new_model))
        .route("/models/import", get(pages::import))
        .route("/models/{name}", get(pages::model))
        .route("/licences", get(pages::licences))
        .route("/login", get(pages::login))
        .route("/invite/{secret}", get(pages::invite))
        .route("/users", get(pages::users))
        .route("/api/v1/session", post(accounts::login).get(accounts::whoami).delete(accounts::logout))
        .route("/api/v1/invitations", post(accounts::accept_invitation))
        .route("/api/v1/quota", get(accounts::quota).put(accounts::set_instance_quota))
        .route("/api/v1/users", get(accounts::list_users).post(accounts::add_user))
        .route("/api/v1/users/{name}", patch(accounts::change_user).delete(accounts::remove_user))
        .route("/cars", get(pages::cars))
        .route("/api/v1/cars", get(fleet::list))
        .route("/api/v1/cars/{car}", post(fleet::order))
        .route("/races", get(pages::races))
        .route("/races/{race}", get(pages::race))
        .route("/api/v1/races", get(race_api::list).post(race_api::create))
        .route("/api/v1/races/{race}", get(race_api::get).patch(race_api::change).delete(race_api::remove))
        .route("/api/v1/races/{race}/leaderboard", get(race_api::board))
        .route("/api/v1/races/{race}/live", get(race_api::live).post(race_api::live_action))
        .route("/api/v1/races/{race}/live/camera.png", get(race_api::live_camera))
        .route("/races/{race}/broadcast", get(pages::broadcast))
        .route("/api/v1/races/{race}/entries", get(race_api::entries).post(race_api::enter))
        .route("/api/v1/races/{race}/entries/{id}", get(race_api::entry))
        .route("/api/v1/races/{race}/entries/{id}/lap.svg", get(race_api::lap))
        .route("/api/v1/openapi.json", get(api::openapi))
        .route("/api/v1/health", get(api::health))
        .route("/api/v1/tracks", get(api::tracks))
        .route("/api/v1/tracks/{name}/picture.svg", get(api::track_picture))
        .route("/api/v1/tracks/{name}/race_line", get(api::race_line))
        .route("/api/v1/rewards/validate", post(api::validate_reward))
        .route("/api/v1/rewards/dry_run", post(api::dry_run))
        .route("/api/v1/models", get(api::list_models).post(api::create_model))
        .route("/api/v1/models/{name}", get(api::get_model).delete(api::delete_model))
        .route("/api/v1/models/{name}/stop", post(api::stop_model))
        .route("/api/v1/models/{name}/metrics", get(api::model_metrics))
        .route("/api/v1/models/{name}/events", get(api::events))
        .route("/api/v1/models/{name}/camera.png", get(api::camera))
        .route("/api/v1/models/{name}/car.tar.gz", get(api::car_archive))
        .route("/api/v1/models/{name}/policy.onnx", get(api::onnx))
        .route("/api/v1/models/{name}/run.tar.gz", get(api::run_archive))
        .route("/api/v1/models/import", post(api::import).layer(axum::extract::DefaultBodyLimit::max(api::MAX_IMPORT)))
        .route("/api/v1/models/{name}/evaluations", get(api::list_evaluations).post(api::start_evaluation))
        .route("/api/v1/models/{name}/evaluations/{id}", get(api::get_evaluation))
        .route("/api/v1/models/{name}/evaluations/{id}/lap.svg", get(api::evaluation_lap))
        .route("/api/v1/models/{name}/evaluations/{id}/frames.png", get(api::evaluation_frames))
        .fallback(|| async {
            counters::refused("an unknown address");
            api::error(axum::http::StatusCode::NOT_FOUND, "no such page or API route")
        })
        .layer(axum::middleware::from_fn_with_state(app.clone(), api::ownership))
        .with_state(app.clone())
        .layer(axum::middleware::from_fn_with_state(app.gate.clone(), auth::guard));
    Router::new()
        .route("/assets/{name}", get(pages::asset))
        .merge(guarded)
        .layer(axum::extract::DefaultBodyLimit::max(MAX_BODY))
        .layer(axum::middleware::map_response(count_oversized))
}

/// A body over its route's limit is answered 413 by the extractor: counted here.
async fn count_oversized(r: axum::response::Response) -> axum::response::Response {
    if r.status() == axum::http::StatusCode::PAYLOAD_TOO_LARGE {
        counters::refused("an oversized request");
    }
    r
}

/// Serve until Ctrl-C or SIGTERM. Prints the address with the token first (one line,
/// `console      http://ADDR/?token=…`).
pub fn serve(opts: Options, store: store::Store, hub: hub::Hub) -> Result<()> {
    let users = users::Users::open(store.root())?;
    check_listen(&opts.listen, opts.insecure, opts.tls.is_some(), users.any())?;
    let tls = opts.tls.as_ref().map(|(cert, key)| tls::server_config(cert, key)).transpose()?;
    let scheme = if tls.is_some() { "https" } else { "http" };
    let token = opts.token.unwrap_or_else(auth::new_token);
    let gate = Arc::new(auth::Gate::new(token.clone(), users));
    let races = races::Races::open(store.root());
    let app = api::App {
        store,
        hub,
        gate: gate.clone(),
        https: tls.is_some(),
        running: Default::default(),
        races,
        race_slots: Arc::new(tokio::sync::Semaphore::new(opts.race_workers.max(1))),
        live_speed: opts.live_speed,
    };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .thread_name("console")
        .build()
        .context("starting the web server's runtime")?;
    let served = rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind(opts.listen)
            .await
            .with_context(|| format!("listening on {}", opts.listen))?;
        let addr = listener.local_addr()?;
        if gate.logins() {
            println!("console      {scheme}://{addr}/login");
        } else {
            println!("console      {scheme}://{addr}/?token={token}");
        }
        use std::io::Write as _;
        std::io::stdout().flush()?;
        tracing::info!(%addr, data = %app.store.root().display(), "console serving");
        race_api::resume(&app);
        race_api::tick(&app);
        // Live pages keep their event streams open: at a stop the server is dropped, not
        // drained.
        let server = match tls {
            Some(config) => {
                let listener = tls::TlsListener::new(listener, config)?;
                let service = router(app)
                    .layer(axum::middleware::map_request(tls::peer_address))
                    .into_make_service_with_connect_info::<tls::Peer>();
                tokio::spawn(async move { axum::serve(listener, service).await })
            }
            None => {
                let service = router(app).into_make_service_with_connect_info::<SocketAddr>();
                tokio::spawn(async move { axum::serve(listener, service).await })
            }
        };
        match futures_util::future::select(server, std::pin::pin!(stopped())).await {
            futures_util::future::Either::Left((done, _)) => {
                done.context("the web server")?.context("serving the console")
            }
            futures_util::future::Either::Right(_) => Ok(()),
        }
    });
    rt.shutdown_timeout(std::time::Duration::from_secs(2));
    served
}

async fn stopped() {
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    futures_util::future::select(std::pin::pin!(tokio::signal::ctrl_c()), std::pin::pin!(term)).await;
    tracing::info!("console stopping");
}

#[cfg(test)]
mod tests {
    /// Every API route the router answers is in the OpenAPI document.
    #[test]
    fn the_openapi_document_names_every_api_route() {
        let doc: serde_json::Value = serde_json::from_str(super::OPENAPI).expect("openapi.json is JSON");
        let paths = doc["paths"].as_object().expect("paths");
        let source = include_str!("lib.rs");
        let routes: Vec<&str> = source
            .split(".route(\"")
            .skip(1)
            .filter_map(|s| s.split('"').next())
            .filter(|r| r.starts_with("/api/"))
            .collect();
        assert!(routes.len() > 30, "{routes:?}");
        // The document names a path's parameters as the router does, but any name will do.
        let shape = |p: &str| -> String {
            p.split('/').map(|s| if s.starts_with('{') { "{}" } else { s }).collect::<Vec<_>>().join("/")
        };
        let documented: Vec<String> = paths.keys().map(|k| shape(k)).collect();
        for r in routes {
            assert!(documented.contains(&shape(r)), "{r} is not in openapi.json");
        }
    }
}
