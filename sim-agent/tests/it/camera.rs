//! The camera: deterministic frames, road where the geometry says, surfaces that look
//! different, and a stored reference frame. Runs on lavapipe (no GPU needed; CI installs
//! mesa-vulkan-drivers); on a GPU as well (an H100 through Vulkan passed all three,
//! docs/benchmarks.md, "The camera").

use sim_agent::camera::{HEIGHT, Renderer, View, WIDTH};
use std::path::PathBuf;
use tracks::{Direction, World};

fn start_view<'a>(world: &World, track: &'a tracks::Track, lateral: f64) -> View<'a> {
    let (p, h) = track.pose_at(0.0);
    let (nx, ny) = (-h.sin(), h.cos());
    View {
        track,
        surface: world.surface,
        lighting: world.lighting,
        pose: [p.x + lateral * nx, p.y + lateral * ny, h],
        jitter: [0.0, 0.0],
        texture_seed: 0,
        objects: &[],
    }
}

/// Columns of near-white pixels (the border lines) in a row of a grayscale frame.
fn white_columns(frame: &[u8], row: usize) -> Vec<usize> {
    (0..WIDTH as usize).filter(|&x| frame[row * WIDTH as usize + x] > 200).collect()
}

fn reference_path() -> PathBuf {
    [env!("CARGO_MANIFEST_DIR"), "..", "tests", "data", "camera", "reinvent_base_start.gray"].iter().collect()
}

#[test]
fn frames_are_deterministic_and_the_road_is_where_the_geometry_says() {
    let mut r = Renderer::new().expect("an adapter (lavapipe or a GPU)");
    let world = tracks::world("reinvent_base").unwrap();
    let track = world.track(Direction::Forward);
    let centred = start_view(&world, &track, 0.0);
    let a = r.render(std::slice::from_ref(&centred), false);
    let b = r.render(std::slice::from_ref(&centred), false);
    assert_eq!(a.len(), (WIDTH * HEIGHT) as usize);
    assert_eq!(a, b, "same state, same bytes");
    // On the centre line of the start straight, facing along it: the two border lines are
    // mirror images about the middle column.
    let row = 45;
    let cols = white_columns(&a, row);
    let (left, right): (Vec<usize>, Vec<usize>) = cols.iter().partition(|&&x| x < 80);
    assert!(!left.is_empty() && !right.is_empty(), "both borders visible in row {row}: {cols:?}");
    let lm = left.iter().sum::<usize>() as f64 / left.len() as f64;
    let rm = right.iter().sum::<usize>() as f64 / right.len() as f64;
    assert!(((lm + rm) / 2.0 - 79.5).abs() < 3.0, "symmetric about the middle: {lm} {rm}");
    // Sky above the horizon (15° pitch, 51° vertical field of view: horizon near row 26).
    assert!(a[10 * WIDTH as usize..11 * WIDTH as usize].iter().all(|&p| p == 0), "nothing above the horizon");
    // The road just ahead is dark and the car is on it.
    let bottom = &a[(HEIGHT as usize - 1) * WIDTH as usize..];
    assert!(bottom[..30].iter().all(|&p| p < 80), "road at the bottom left: {:?}", &bottom[..30]);
    // 0.1 m to the left of the centre line, the borders move right in the picture.
    let shifted = r.render(&[start_view(&world, &track, 0.1)], false);
    let cols2 = white_columns(&shifted, row);
    let mean2 = cols2.iter().sum::<usize>() as f64 / cols2.len() as f64;
    let mean1 = cols.iter().sum::<usize>() as f64 / cols.len() as f64;
    assert!(mean2 > mean1 + 5.0, "{cols:?} -> {cols2:?}");
}

#[test]
fn carpet_and_wood_look_different_and_a_batch_equals_single_frames() {
    let mut r = Renderer::new().expect("an adapter");
    let worlds: Vec<World> =
        ["reinvent_carpet", "reinvent_wood", "reinvent_concrete"].iter().map(|n| tracks::world(n).unwrap()).collect();
    let tracks: Vec<tracks::Track> = worlds.iter().map(|w| w.track(Direction::Forward)).collect();
    let views: Vec<View<'_>> = worlds.iter().zip(&tracks).map(|(w, t)| start_view(w, t, 0.0)).collect();
    let batch = r.render(&views, false);
    let n = (WIDTH * HEIGHT) as usize;
    // The floor beyond the track (rows 27-33) differs between carpet and wood.
    let floor = |f: &[u8]| -> f64 {
        (27..33).flat_map(|y| (0..40).map(move |x| f[y * WIDTH as usize + x] as f64)).sum::<f64>() / 240.0
    };
    let (carpet, wood) = (&batch[..n], &batch[n..2 * n]);
    let diff: f64 = carpet.iter().zip(wood).map(|(a, b)| (*a as f64 - *b as f64).abs()).sum::<f64>() / n as f64;
    assert!(
        diff > 2.0 && (floor(carpet) - floor(wood)).abs() > 10.0,
        "mean |Δ| {diff}, floors {} vs {}",
        floor(carpet),
        floor(wood)
    );
    // A view drawn in a batch matches the same view drawn alone (its viewport sits elsewhere
    // in the atlas, so the rasteriser may round a few edge pixels differently).
    for (i, v) in views.iter().enumerate() {
        let alone = r.render(std::slice::from_ref(v), false);
        let d: f64 =
            alone.iter().zip(&batch[i * n..(i + 1) * n]).map(|(a, b)| (*a as f64 - *b as f64).abs()).sum::<f64>()
                / n as f64;
        assert!(d < 1.0, "view {i}: batched vs alone differ by {d:.2} on average");
    }
}

#[test]
fn the_start_frame_matches_the_stored_reference() {
    let mut r = Renderer::new().expect("an adapter");
    let world = tracks::world("reinvent_base").unwrap();
    let track = world.track(Direction::Forward);
    let frame = r.render(&[start_view(&world, &track, 0.0)], false);
    let path = reference_path();
    if std::env::var_os("PADDOCK_UPDATE_REFERENCE").is_some() {
        std::fs::write(&path, &frame).unwrap();
    }
    let reference = std::fs::read(&path)
        .expect("tests/data/camera/reinvent_base_start.gray (PADDOCK_UPDATE_REFERENCE=1 writes it)");
    assert_eq!(reference.len(), frame.len());
    let diffs: Vec<u32> = frame.iter().zip(&reference).map(|(a, b)| (*a as i32 - *b as i32).unsigned_abs()).collect();
    let mean = diffs.iter().sum::<u32>() as f64 / diffs.len() as f64;
    let far = diffs.iter().filter(|&&d| d > 16).count() as f64 / diffs.len() as f64;
    assert!(
        mean < 3.0 && far < 0.02,
        "mean |Δ| {mean:.2}, {:.1} % of pixels off by more than 16 (renderer {})",
        far * 100.0,
        r.adapter()
    );
}

/// Issue 31: obstacles and bots are drawn where they stand.
#[test]
fn obstacles_and_bots_are_drawn_where_they_stand() {
    use sim_agent::objects::{Kind, Object};
    use tracks::objects::{BOX_FOOTPRINT, CAR_FOOTPRINT, Lane, ObjectPose};
    let mut r = Renderer::new().expect("an adapter (lavapipe or a GPU)");
    let world = tracks::world("reinvent_base").unwrap();
    let track = world.track(Direction::Forward);
    let object = |along: f64, car: bool| {
        let (p, h) = track.pose_at(along);
        Object {
            kind: if car { Kind::Bot } else { Kind::Obstacle },
            pose: ObjectPose { position: p, heading: h, along, lane: Lane::Inner },
            footprint: if car { CAR_FOOTPRINT } else { BOX_FOOTPRINT },
            car,
        }
    };
    let plain = start_view(&world, &track, 0.0);
    let boxed = [object(1.2, false)];
    let car = [object(1.2, true)];
    let behind = [object(track.length() - 1.0, false)];
    let views = [
        plain.clone(),
        View { objects: &boxed, ..plain.clone() },
        View { objects: &car, ..plain.clone() },
        View { objects: &behind, ..plain.clone() },
    ];
    let frames = r.render(&views, false);
    let n = (WIDTH * HEIGHT) as usize;
    let frame = |i: usize| &frames[i * n..(i + 1) * n];
    let changed = |i: usize| -> Vec<usize> { (0..n).filter(|&k| frame(i)[k] != frame(0)[k]).collect() };
    // A box 1.2 m ahead on the centre line: a solid patch in the middle of the frame.
    for (i, what) in [(1, "box"), (2, "car")] {
        let px = changed(i);
        assert!(px.len() > 150, "{what}: {} pixels changed", px.len());
        let mean_col = px.iter().map(|k| k % WIDTH as usize).sum::<usize>() as f64 / px.len() as f64;
        assert!((mean_col - WIDTH as f64 / 2.0).abs() < 12.0, "{what}: centred, column {mean_col}");
        if let Ok(dir) = std::env::var("PADDOCK_DUMP_FRAMES") {
            std::fs::write(format!("{dir}/{what}.gray"), frame(i)).unwrap();
        }
        // A solid: its patch is many rows tall.
        let rows: std::collections::BTreeSet<usize> = px.iter().map(|k| k / WIDTH as usize).collect();
        assert!(rows.len() > 12, "{what}: {} rows", rows.len());
    }
    // The box (brown) and the car (dark body, light shell) do not look alike.
    assert_ne!(changed(1), changed(2));
    // Behind the camera: nothing drawn.
    assert!(changed(3).is_empty());
}
