//! Issue 52: the fleet. A real `deploy` car on loopback, fed camera frames as a car's ROS bridge
//! feeds them, appears on the cars page; an organiser assigns it a model there (signed by the
//! console's learner; the car checks the signature) and it drives that model's version; the
//! e-stop reaches it and is released.

use crate::browser::{CHROMIUM, python};
use crate::support::{Console, bin, wait_for};
use serde_json::json;
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

/// Camera frames as the car's bridge publishes them (the community layout: JPEG), 15 a second.
fn feed_frames(endpoint: &str, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<()> {
    let net = protocol::net::NetArgs { connect: vec![endpoint.to_string()], ..Default::default() };
    std::thread::spawn(move || {
        let session = protocol::net::open(&net).unwrap();
        let key = protocol::ros::CarKeys::new("").sensor;
        let mut i = 0u32;
        while !stop.load(Ordering::Relaxed) {
            let img = image::RgbImage::from_fn(160, 120, |x, y| image::Rgb([(x * 3 + i) as u8, (y * 2) as u8, 90]));
            let mut jpeg = Vec::new();
            img.write_to(&mut std::io::Cursor::new(&mut jpeg), image::ImageFormat::Jpeg).unwrap();
            let frame = protocol::ros::RawFrame::Compressed(protocol::ros::CompressedImage {
                header: Default::default(),
                format: "jpeg".into(),
                data: jpeg.into(),
            });
            let msg = protocol::ros::encode_sensor(vec![frame], &[], protocol::ros::Layout::Community);
            use protocol::net::zenoh::Wait;
            let _ = session.put(&key, msg).wait();
            i = i.wrapping_add(1);
            std::thread::sleep(std::time::Duration::from_millis(66));
        }
    })
}

#[test]
fn a_car_on_the_network_is_assigned_a_model_from_the_cars_page_and_stopped() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let o = Command::new(bin("coordinator")).args(["keys", "new"]).arg(dir.path().join("models")).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let key = dir.path().join("models.key");
    let c = Console::with_args(&data, 1, &["--signing-key", key.to_str().unwrap()]);
    let meta: serde_json::Value = serde_json::from_str(&policy::ModelMetadata::default_camera().to_json()).unwrap();
    let model = json!({"name": "cam-1", "tracks": ["reinvent_base"], "reward_function": "builtin:center_line",
                       "model_metadata": meta, "stop": {"minutes": 0.1}});
    let r = c.api("POST", "/api/v1/models", Some(&model));
    assert_eq!(r.code, 201, "{}", String::from_utf8_lossy(&r.body));
    wait_for(120, "cam-1 trained", || {
        (c.api("GET", "/api/v1/models/cam-1", None).json()["status"] == "ready").then_some(())
    });
    let manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(data.join("models/cam-1/run/model/manifest.json")).unwrap())
            .unwrap();
    let version = manifest["policy_version"].as_u64().unwrap();

    // The car waits for an assignment; its bridge sends frames.
    let mut car = Command::new(bin("deploy"))
        .args(["--connect", &c.endpoint, "--trust"])
        .arg(dir.path().join("models.pub"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let frames = feed_frames(&c.endpoint, stop.clone());
    let cars = wait_for(30, "the car on the cars API", || {
        let v = c.api("GET", "/api/v1/cars", None).json();
        (v.as_array().is_some_and(|a| !a.is_empty())).then_some(v)
    });
    assert_eq!((cars[0]["car"].as_str(), cars[0]["state"].as_str()), (Some("car"), Some("no model")), "{cars}");
    // Refusals: an unknown car, an unknown model, a malformed order.
    assert_eq!(c.api("POST", "/api/v1/cars/nobody", Some(&json!({"estop": true}))).code, 404);
    assert_eq!(c.api("POST", "/api/v1/cars/car", Some(&json!({"model": "nope"}))).code, 404);
    assert_eq!(c.api("POST", "/api/v1/cars/car", Some(&json!({"model": "cam-1", "estop": true}))).code, 400);

    // The organiser, in Chromium: assign cam-1, see it drive, hold the e-stop, release it.
    let o = Command::new(python())
        .arg("-c")
        .arg(format!("{CHROMIUM}{CARS}"))
        .args([&c.addr, crate::support::TOKEN])
        .arg(dir.path())
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout).to_string();
    // A live race's entry racing now (or else the next) is assigned as a model is.
    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_secs_f64();
    let race = json!({"name": "final", "mode": "live", "track": "reinvent_base", "max_laps": 1, "closes": now + 600.0});
    assert_eq!(c.api("POST", "/api/v1/races", Some(&race)).code, 201);
    assert_eq!(c.api("POST", "/api/v1/races/final/entries", Some(&json!({"model": "cam-1"}))).code, 202);
    let swaps = |v: &serde_json::Value| v[0]["swaps"].as_u64().unwrap_or(0);
    let before = swaps(&c.api("GET", "/api/v1/cars", None).json());
    let r = c.api("POST", "/api/v1/cars/car", Some(&json!({"race": "final"})));
    assert_eq!(r.code, 202, "{}", String::from_utf8_lossy(&r.body));
    let after = wait_for(20, "the entry's model taken", || {
        let v = c.api("GET", "/api/v1/cars", None).json();
        (swaps(&v) > before && v[0]["state"] == "driving").then_some(v)
    });
    assert_eq!(
        (after[0]["model"].as_str(), after[0]["policy_version"].as_u64()),
        (Some("cam-1"), Some(version)),
        "{after}"
    );
    assert_eq!(c.api("POST", "/api/v1/cars/car", Some(&json!({"race": "nope"}))).code, 404);
    stop.store(true, Ordering::Relaxed);
    let _ = car.kill();
    let _ = car.wait();
    frames.join().unwrap();
    assert!(o.status.success(), "the browser's run failed:\n{out}\n{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_str(out.lines().last().unwrap_or("")).unwrap();
    assert_eq!(v["row"]["model"], "cam-1", "{v}");
    assert_eq!(v["row"]["version"], format!("v{version}"), "the car drives the model's version: {v}");
    assert_eq!(v["row"]["state"], "driving", "{v}");
    assert_eq!(v["stopped"], "e-stop", "{v}");
    assert_eq!(v["released"], "driving", "{v}");
    if let Ok(keep) = std::env::var("PADDOCK_KEEP_SCREENSHOTS") {
        std::fs::copy(dir.path().join("cars.png"), std::path::Path::new(&keep).join("cars.png")).unwrap();
    }
    c.stop();
}

/// The organiser on the cars page (after [`CHROMIUM`]): prints one JSON line of what it showed.
const CARS: &str = r###"
token = sys.argv[2]
def cell(n):
    return d.find_element(By.CSS_SELECTOR, '#cars tr[data-car="car"] td:nth-child(%d)' % n).text
try:
    d.get("http://%s/?token=%s" % (addr, token))
    d.get("http://%s/cars" % addr)
    wait("the car's row", lambda: d.find_elements(By.CSS_SELECTOR, '#cars tr[data-car="car"]'))
    d.find_element(By.CSS_SELECTOR, '#cars tr[data-car="car"] option[value="model:cam-1"]').click()
    d.find_element(By.CSS_SELECTOR, '#cars tr[data-car="car"] .car-assign').click()
    wait("cam-1 driving", lambda: cell(2) == "cam-1" and cell(7) == "driving", 30)
    out["row"] = {"model": cell(2), "version": cell(3), "fps": cell(4), "state": cell(7)}
    d.save_screenshot(tmp + "/cars.png")
    d.find_element(By.CSS_SELECTOR, '#cars tr[data-car="car"] .car-estop').click()
    out["stopped"] = wait("the e-stop", lambda: cell(7) == "e-stop" and cell(7), 20)
    d.find_element(By.CSS_SELECTOR, '#cars tr[data-car="car"] .car-release').click()
    out["released"] = wait("driving again", lambda: cell(7) == "driving" and cell(7), 20)
finally:
    d.quit()
print(json.dumps(out))
"###;
