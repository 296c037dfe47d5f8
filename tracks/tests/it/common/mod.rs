//! Helpers shared by the track tests: write `.npy` bytes by hand, independent of the reader.

/// A numpy v1.0 file with the given descr, shape and raw little-endian data.
pub fn npy_bytes(descr: &str, shape: &[usize], data: &[u8]) -> Vec<u8> {
    npy_bytes_ordered(descr, false, shape, data)
}

/// As [`npy_bytes`], with the `fortran_order` flag chosen.
pub fn npy_bytes_ordered(descr: &str, fortran: bool, shape: &[usize], data: &[u8]) -> Vec<u8> {
    let order = if fortran { "True" } else { "False" };
    let shape_txt = match shape {
        [n] => format!("({n},)"),
        _ => format!("({})", shape.iter().map(|s| s.to_string()).collect::<Vec<_>>().join(", ")),
    };
    let mut header = format!("{{'descr': '{descr}', 'fortran_order': {order}, 'shape': {shape_txt}, }}");
    let unpadded = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend((header.len() as u16).to_le_bytes());
    out.extend(header.as_bytes());
    out.extend(data);
    out
}

/// `<f8` rows of 6 values.
pub fn f8_rows(rows: &[[f64; 6]]) -> Vec<u8> {
    let data: Vec<u8> = rows.iter().flatten().flat_map(|v| v.to_le_bytes()).collect();
    npy_bytes("<f8", &[rows.len(), 6], &data)
}

/// A 4 m x 2 m rectangular loop (CCW), 1 m wide, corners at the waypoints.
pub fn rectangle_rows() -> Vec<[f64; 6]> {
    let c = [(0.0, 0.0), (4.0, 0.0), (4.0, 2.0), (0.0, 2.0), (0.0, 0.0)];
    let i = [(0.5, 0.5), (3.5, 0.5), (3.5, 1.5), (0.5, 1.5), (0.5, 0.5)];
    let o = [(-0.5, -0.5), (4.5, -0.5), (4.5, 2.5), (-0.5, 2.5), (-0.5, -0.5)];
    (0..5).map(|k| [c[k].0, c[k].1, i[k].0, i[k].1, o[k].0, o[k].1]).collect()
}
