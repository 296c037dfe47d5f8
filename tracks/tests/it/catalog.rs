//! The built-in catalog agrees with the shipped STATS.md, and every world loads.

use tracks::{Direction, Surface, TrackSummary, world, world_names};

/// (file, centre length, min width, mean width, max width, direction) from STATS.md.
fn stats() -> Vec<(String, f64, f64, f64, f64, String)> {
    let text = include_str!("../../data/STATS.md");
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

/// Issue 12: DeepRacer's simapp drops a row that repeats the one before when it loads a
/// track, so reward functions see fewer `waypoints` than the file has rows, and
/// `closest_waypoints` counts in that shorter list. (file, rows, the repeated row, waypoints).
#[test]
fn waypoints_are_the_rows_without_repeats_on_every_shipped_track() {
    let table: &[(&str, usize, Option<usize>, usize)] = &[
        ("reinvent_base", 119, None, 119),
        ("reinvent_carpet", 119, None, 119),
        ("reinvent_concrete", 119, None, 119),
        ("reinvent_wood", 119, None, 119),
        ("reInvent2019_track", 155, Some(39), 154),
        ("reInvent2019_track_ccw", 79, None, 79),
        ("reInvent2019_track_cw", 79, None, 79),
        ("reInvent2019_wide", 112, Some(106), 111),
        ("2022_reinvent_champ_ccw", 113, None, 113),
        ("2022_reinvent_champ_cw", 113, None, 113),
        ("AWS_track", 302, Some(187), 301),
        ("Bowtie_track", 163, Some(41), 162),
        ("China_track", 172, Some(41), 171),
        ("LGSWide", 255, Some(191), 254),
        ("Mexico_track", 181, Some(27), 180),
        ("Oval_track", 102, Some(67), 101),
        ("Straight_track", 22, None, 22),
        ("Tokyo_Training_track", 169, Some(78), 168),
        ("Vegas_track", 151, Some(148), 150),
    ];
    assert_eq!(table.len(), world_names().count(), "every shipped track is in the table");
    for &(name, rows, repeated, waypoints) in table {
        let w = world(name).unwrap();
        assert_eq!(w.rows.len(), rows, "{name}: rows");
        assert_eq!(w.rows.repeated_rows(), repeated.into_iter().collect::<Vec<_>>(), "{name}: repeated rows");
        for dir in [Direction::Forward, Direction::Reversed] {
            let track = w.track(dir);
            let wp = track.waypoints();
            assert_eq!(wp.len(), waypoints, "{name} {dir:?}: waypoints");
            assert!(
                wp.windows(2).all(|p| (p[1] - p[0]).norm() > 1e-9),
                "{name} {dir:?}: a zero-length segment is left"
            );
        }
        // Just past the row after the repeat, `closest_waypoints` is [that row - 1, that row]
        // in the file's numbering less one, as on DeepRacer.
        if let Some(r) = repeated {
            let raw = r + 2; // a row after the repeat (raw index)
            if raw + 1 < rows {
                let track = w.track(Direction::Forward);
                let (a, b) = (w.rows.center[raw], w.rows.center[raw + 1]);
                let p = a + (b - a) * 0.25;
                let q = track.query(p);
                assert_eq!(q.closest_waypoints, [raw - 1, raw], "{name}: closest waypoints just past raw row {raw}");
            }
        }
    }
}
