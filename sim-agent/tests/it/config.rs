//! The configuration: the shipped default file is the defaults; overrides and errors.

use sim_agent::SimConfig;
use sim_agent::config::{ObservationKind, load_config, parse_toml};
use std::path::PathBuf;

fn default_file() -> PathBuf {
    [env!("CARGO_MANIFEST_DIR"), "..", "config", "default.toml"].iter().collect()
}

#[test]
fn config_default_toml_is_exactly_the_defaults() {
    let text = std::fs::read_to_string(default_file()).unwrap();
    let parsed: SimConfig = parse_toml(&text, "config/default.toml").unwrap();
    assert_eq!(parsed, SimConfig::default());
    // Every key is written out: serialising the defaults yields no key the file lacks.
    let file: toml::Table = toml::from_str(&text).unwrap();
    let defaults = toml::Table::try_from(SimConfig::default()).unwrap();
    for (k, v) in &defaults {
        let f = file.get(k).unwrap_or_else(|| panic!("config/default.toml lacks '{k}'"));
        if let (Some(dt), Some(ft)) = (v.as_table(), f.as_table()) {
            for sub in dt.keys() {
                assert!(ft.contains_key(sub), "config/default.toml lacks '{k}.{sub}'");
            }
        }
    }
}

#[test]
fn set_overrides_apply_on_top_of_the_file() {
    let cfg: SimConfig = load_config(
        Some(&default_file()),
        &["noise.steering_deg=0".into(), "observation.kind=lidar".into(), "physics_substeps=2".into()],
    )
    .unwrap();
    assert_eq!(cfg.noise.steering_deg, 0.0);
    assert_eq!(cfg.observation.kind, ObservationKind::Lidar);
    assert_eq!(cfg.physics_substeps, 2);
    assert_eq!(cfg.noise.speed_fraction, SimConfig::default().noise.speed_fraction);
}

#[test]
fn errors_name_the_key_or_the_file() {
    let cases: &[(&[&str], &str)] = &[
        (&["noise.steering_degrees=1"], "steering_degrees"),
        (&["physics_substeps=fast"], "physics_substeps"),
        (&["observation.kind=radar"], "radar"),
        (&["no_equals_sign"], "expected key=value"),
    ];
    for (sets, want) in cases {
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        let err = load_config::<SimConfig>(None, &sets).unwrap_err().to_string();
        assert!(err.contains(want), "{sets:?}: {err}");
    }
    let err = load_config::<SimConfig>(Some(std::path::Path::new("/no/such.toml")), &[]).unwrap_err().to_string();
    assert!(err.contains("/no/such.toml"), "{err}");
}
