//! Reading DeepRacer `.npy` files: good files load, bad ones are refused with the reason.

use crate::common::{f8_rows, npy_bytes, npy_bytes_ordered, rectangle_rows};
use tracks::{TrackSummary, parse_track_npy};

#[test]
fn a_hand_written_file_loads_with_the_right_figures() {
    let rows = parse_track_npy(&f8_rows(&rectangle_rows()), "rect.npy").unwrap();
    let s = TrackSummary::of("rect", &rows);
    assert_eq!(s.rows, 5);
    assert!((s.length - 12.0).abs() < 1e-12);
    assert!(s.closed);
    assert_eq!(s.direction, "ccw");
    assert!((s.min_width - 2f64.sqrt()).abs() < 1e-12, "corner rows are sqrt(2) apart: {}", s.min_width);
}

/// Issue 12: whole repeated rows load and are dropped as DeepRacer drops them.
#[test]
fn whole_repeated_rows_load_and_are_dropped_as_deepracer_drops_them() {
    let mut rows = rectangle_rows();
    rows.insert(2, rows[1]);
    let parsed = parse_track_npy(&f8_rows(&rows), "rep.npy").unwrap();
    assert_eq!(parsed.len(), 6);
    assert_eq!(parsed.repeated_rows(), vec![2]);
    assert_eq!(parsed.sanitized(), parse_track_npy(&f8_rows(&rectangle_rows()), "rect.npy").unwrap());
    let s = TrackSummary::of("rep", &parsed);
    assert_eq!((s.rows, s.waypoints), (6, 5));
    assert!((s.length - 12.0).abs() < 1e-12);
}

#[test]
fn fortran_order_and_big_endian_files_read_the_same() {
    let rows = rectangle_rows();
    let mut data = Vec::new();
    for col in 0..6 {
        for r in &rows {
            data.extend(r[col].to_be_bytes());
        }
    }
    let fixed = npy_bytes_ordered(">f8", true, &[5, 6], &data);
    let a = parse_track_npy(&fixed, "f.npy").unwrap();
    let b = parse_track_npy(&f8_rows(&rows), "c.npy").unwrap();
    assert_eq!(a, b);
}

/// Each bad file and a fragment the error must contain.
#[test]
fn bad_files_are_refused_naming_what_is_wrong() {
    let good = rectangle_rows();
    let mut nan = good.clone();
    nan[2][3] = f64::NAN;
    let mut inf = good.clone();
    inf[1][4] = f64::INFINITY;
    let mut dup = good.clone();
    dup.insert(2, dup[1]);
    dup[2][2] += 0.01; // same centre point, different border
    let mut crossing = good.clone();
    crossing[1][2] = 4.0; // inner border point moved across the centre line
    crossing[1][3] = -0.4;
    let f4: Vec<u8> = good.iter().flatten().flat_map(|v| (*v as f32).to_le_bytes()).collect();
    let five: Vec<u8> = good.iter().flat_map(|r| r[..5].iter()).flat_map(|v| v.to_le_bytes()).collect();
    let cases: Vec<(Vec<u8>, &str)> = vec![
        (b"not numpy at all".to_vec(), "not a numpy .npy file"),
        (npy_bytes("<f4", &[5, 6], &f4), "expected float64"),
        (npy_bytes("<f8", &[5, 5], &five), "expected (N, 6)"),
        (
            npy_bytes("<f8", &[30], &good.iter().flatten().flat_map(|v| v.to_le_bytes()).collect::<Vec<_>>()),
            "expected (N, 6)",
        ),
        (f8_rows(&nan), "row 2 column 3 (inner_y) is NaN"),
        (f8_rows(&inf), "row 1 column 4 (outer_x) is inf"),
        (f8_rows(&good[..2]), "expected at least 3"),
        (f8_rows(&[good[0], good[1], good[0]]), "expected at least 3"),
        (f8_rows(&dup), "row 2 repeats row 1's centre point with different borders"),
        (f8_rows(&crossing), "inner border segment starting at row 0 crosses the centre line"),
        (f8_rows(&good)[..200].to_vec(), "truncated"),
        (f8_rows(&good)[..60].to_vec(), "not a numpy .npy file"),
        // Issue 35: the fuzzer's header (40 brackets deep) held the header parser over 10 s.
        (deep_header(40), "the header nests brackets 42 deep"),
    ];
    for (bytes, want) in cases {
        let err = parse_track_npy(&bytes, "user.npy").expect_err(want).to_string();
        assert!(err.starts_with("user.npy: "), "error names the file: {err}");
        assert!(err.contains(want), "expected '{want}' in '{err}'");
    }
}

/// A `.npy` file whose header opens `n` braces inside a list (the fuzzer's timeout, grown).
fn deep_header(n: usize) -> Vec<u8> {
    let header = format!("{{[{}'shape': (5, 6), }}", "{".repeat(n - 1));
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend((header.len() as u16).to_le_bytes());
    b.extend(header.as_bytes());
    b
}
