//! The built-in catalog agrees with the shipped STATS.md, and every world loads.

use tracks::{Direction, Surface, TrackSummary, world, world_names};

/// (file, centre length, min width, mean width, max width, direction) from STATS.md.
fn stats() -> Vec<(String, f64, f64, f64, f64, String)> {
    let text = include_str!("../data/STATS.md");
    text.lines()
        .filter(|l| l.contains(".npy"))
        .map(|l| {
            let c: Vec<&str> = l.split('|').map(str::trim).collect();
            let f = |i: usize| c[i].parse::<f64>().unwrap();
            (c[1].trim_end_matches(".npy").to_string(), f(4), f(8), f(7), f(9), c[12].to_lowercase())
        })
        .collect()
}

#[test]
fn lengths_and_widths_agree_with_stats_md_to_a_millimetre() {
    let table = stats();
    assert_eq!(table.len(), 19);
    for (name, length, min_w, mean_w, max_w, dir) in table {
        let w = world(&name).unwrap();
        let s = TrackSummary::of(&name, &w.rows);
        assert!((s.length - length).abs() < 1e-3, "{name}: {} vs {length}", s.length);
        assert!((s.min_width - min_w).abs() < 1e-3, "{name}: min width {} vs {min_w}", s.min_width);
        assert!((s.mean_width - mean_w).abs() < 1e-3, "{name}: mean width {} vs {mean_w}", s.mean_width);
        assert!((s.max_width - max_w).abs() < 1e-3, "{name}: max width {} vs {max_w}", s.max_width);
        let want = if name == "Straight_track" { "open" } else { dir.as_str() };
        assert_eq!(s.direction, want, "{name}");
    }
}

#[test]
fn every_world_name_loads_and_reinvent_worlds_share_geometry_with_different_surfaces() {
    for name in world_names() {
        world(name).unwrap();
    }
    let base = world("reinvent_base").unwrap();
    let mut surfaces = vec![base.surface];
    for name in ["reinvent_carpet", "reinvent_concrete", "reinvent_wood"] {
        let w = world(name).unwrap();
        assert_eq!(w.rows, base.rows);
        surfaces.push(w.surface);
    }
    surfaces.dedup();
    assert_eq!(surfaces, vec![Surface::Asphalt, Surface::Carpet, Surface::Concrete, Surface::Wood]);
    let grips: Vec<f64> = surfaces.iter().map(|s| s.friction()).collect();
    assert!(grips.windows(2).all(|w| w[0] != w[1]), "surfaces differ in grip: {grips:?}");
}

#[test]
fn unknown_world_lists_the_known_ones() {
    let err = world("nope").unwrap_err().to_string();
    assert!(err.contains("no built-in world named 'nope'") && err.contains("reinvent_base"), "{err}");
}

#[test]
fn reversing_keeps_length_and_flips_orientation() {
    let w = world("reInvent2019_track").unwrap();
    let f = w.track(Direction::Forward);
    let r = w.track(Direction::Reversed);
    assert!((f.length() - r.length()).abs() < 1e-9);
    assert!(f.is_ccw() && !r.is_ccw());
    assert_eq!(f.waypoints().first(), r.waypoints().last());
}
