//! Camera frames to the network's input, as DeepRacer's inference node prepares them
//! (`inference_pkg/src/image_process.cpp`): decode, resize to the model's input size with
//! bilinear interpolation, convert BGR to grey, hand over 0–255 floats (the network divides
//! by 255 itself).
//!
//! JPEG frames (the community car) are decoded by the `image` crate. Resizing uses OpenCV's
//! `INTER_LINEAR` sample positions (`src = (dst + 0.5)·scale − 0.5`, edges clamped) per colour
//! channel, and grey is OpenCV's `COLOR_BGR2GRAY` fixed-point formula
//! `(4899·R + 9617·G + 1868·B + 8192) >> 14`; both are written here because no Rust crate
//! reproduces OpenCV's conventions, and a frame that already has the model's size (the
//! community car resizes at the source) passes through unchanged but for the grey conversion.
//!
//! A LiDAR model's input comes from the message's `lidar_data` ([`add_lidar`]): as the
//! sensor-fusion node sends it, already the model's input (64 clipped ranges for `LIDAR`, 8
//! sector bits for `SECTOR_LIDAR`), as DeepRacer's inference node takes it; or, when the
//! model wants sectors and the message holds the 64 raw ranges, through DeepRacer's sector
//! filter here. `DISCRETIZED_SECTOR_LIDAR`'s default 8 × 8 input is 64 values too: 64 values
//! that are all 0 or 1 are taken as its one-hot input, any others as ranges.

use policy::Sensor;
use policy::metadata::{LidarInput, clipped};
use protocol::ros::RawFrame;

/// Why a frame could not be used.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FrameError {
    /// Fewer camera images than the model needs.
    #[error("the message has {got} camera image(s), the model needs {need}")]
    Missing {
        /// Images in the message.
        got: usize,
        /// Images the model needs.
        need: usize,
    },
    /// A compressed image did not decode.
    #[error("image {index}: {msg}")]
    Decode {
        /// Which image.
        index: usize,
        /// Why.
        msg: String,
    },
    /// A raw image's fields disagree or its encoding is not one the car sends.
    #[error("image {index}: {msg}")]
    Raw {
        /// Which image.
        index: usize,
        /// Why.
        msg: String,
    },
    /// The message's `lidar_data` is not what the model's LiDAR input needs.
    #[error("lidar_data: {0}")]
    Lidar(String),
}

/// The largest frame accepted (pixels): a 4K camera, with room.
pub const MAX_PIXELS: usize = 4096 * 4096;

/// An image as 8-bit RGB.
struct Rgb {
    w: usize,
    h: usize,
    px: Vec<u8>,
}

fn decode(index: usize, f: &RawFrame) -> Result<Rgb, FrameError> {
    match f {
        RawFrame::Compressed(c) => {
            let fmt = c.format.to_ascii_lowercase();
            let guess = if fmt.contains("jpeg") || fmt.contains("jpg") {
                Some(image::ImageFormat::Jpeg)
            } else {
                image::guess_format(&c.data).ok()
            };
            let Some(format) = guess.filter(|f| *f == image::ImageFormat::Jpeg) else {
                return Err(FrameError::Decode { index, msg: format!("format '{}' is not JPEG", c.format) });
            };
            let mut reader = image::ImageReader::with_format(std::io::Cursor::new(&c.data[..]), format);
            let mut limits = image::Limits::default();
            limits.max_image_width = Some(4096);
            limits.max_image_height = Some(4096);
            limits.max_alloc = Some(64 << 20);
            reader.limits(limits);
            let img = reader.decode().map_err(|e| FrameError::Decode { index, msg: format!("JPEG: {e}") })?.to_rgb8();
            Ok(Rgb { w: img.width() as usize, h: img.height() as usize, px: img.into_raw() })
        }
        RawFrame::Raw(i) => {
            let bad = |msg: String| FrameError::Raw { index, msg };
            let (w, h, step) = (i.width as usize, i.height as usize, i.step as usize);
            let (ch, order): (usize, [usize; 3]) = match i.encoding.as_str() {
                "bgr8" => (3, [2, 1, 0]),
                "rgb8" => (3, [0, 1, 2]),
                "bgra8" => (4, [2, 1, 0]),
                "rgba8" => (4, [0, 1, 2]),
                "mono8" | "8UC1" => (1, [0, 0, 0]),
                e => return Err(bad(format!("encoding '{e}'; expected bgr8, rgb8, bgra8, rgba8 or mono8"))),
            };
            if w == 0 || h == 0 || w * h > MAX_PIXELS {
                return Err(bad(format!("{w}×{h} pixels")));
            }
            if step < w * ch || i.data.len() < step * (h - 1) + w * ch {
                return Err(bad(format!(
                    "step {step} and {} data bytes do not hold {w}×{h} {} pixels",
                    i.data.len(),
                    i.encoding
                )));
            }
            let mut px = Vec::with_capacity(w * h * 3);
            for r in 0..h {
                let row = &i.data[r * step..r * step + w * ch];
                for p in row.chunks_exact(ch) {
                    px.extend_from_slice(&[p[order[0]], p[order[1]], p[order[2]]]);
                }
            }
            Ok(Rgb { w, h, px })
        }
    }
}

/// OpenCV's INTER_LINEAR taps for one axis: (i0, i1, weight of i1) per output index.
fn taps(src: usize, dst: usize) -> Vec<(usize, usize, f32)> {
    let scale = src as f64 / dst as f64;
    (0..dst)
        .map(|d| {
            let x = ((d as f64 + 0.5) * scale - 0.5).max(0.0);
            let i0 = (x.floor() as usize).min(src - 1);
            let i1 = (i0 + 1).min(src - 1);
            (i0, i1, (x - i0 as f64).clamp(0.0, 1.0) as f32)
        })
        .collect()
}

fn resize(img: &Rgb, w: usize, h: usize) -> Rgb {
    if img.w == w && img.h == h {
        return Rgb { w, h, px: img.px.clone() };
    }
    let (tx, ty) = (taps(img.w, w), taps(img.h, h));
    let mut px = Vec::with_capacity(w * h * 3);
    for &(y0, y1, fy) in &ty {
        for &(x0, x1, fx) in &tx {
            for c in 0..3 {
                let p = |x: usize, y: usize| img.px[(y * img.w + x) * 3 + c] as f32;
                let top = p(x0, y0) * (1.0 - fx) + p(x1, y0) * fx;
                let bottom = p(x0, y1) * (1.0 - fx) + p(x1, y1) * fx;
                px.push((top * (1.0 - fy) + bottom * fy).round().clamp(0.0, 255.0) as u8);
            }
        }
    }
    Rgb { w, h, px }
}

/// OpenCV's `COLOR_BGR2GRAY` (and RGB2GRAY) on 8-bit pixels.
pub fn grey(r: u8, g: u8, b: u8) -> u8 {
    ((4899 * r as u32 + 9617 * g as u32 + 1868 * b as u32 + 8192) >> 14) as u8
}

/// The network input (`h × w × channels`, channels last, 0–255) from a message's frames: the
/// first `channels` images (one for FRONT_FACING_CAMERA, two for STEREO_CAMERAS).
pub fn preprocess(
    frames: &[RawFrame],
    h: usize,
    w: usize,
    channels: usize,
    out: &mut Vec<f32>,
) -> Result<(), FrameError> {
    if frames.len() < channels {
        return Err(FrameError::Missing { got: frames.len(), need: channels });
    }
    out.clear();
    out.resize(h * w * channels, 0.0);
    for (c, f) in frames.iter().take(channels).enumerate() {
        let img = resize(&decode(c, f)?, w, h);
        for (i, p) in img.px.chunks_exact(3).enumerate() {
            out[i * channels + c] = grey(p[0], p[1], p[2]) as f32;
        }
    }
    Ok(())
}

/// Put a LiDAR model's input from `lidar_data` (see the module documentation) before or after
/// the camera's pixels in `obs` (`lidar`: the model's LiDAR input and whether it comes first;
/// nothing to do without one).
pub fn add_lidar(lidar: Option<(LidarInput, bool)>, data: &[f32], obs: &mut Vec<f32>) -> Result<(), FrameError> {
    let Some((l, first)) = lidar else { return Ok(()) };
    // A sector input is one-hot: 64 values of which some are neither 0 nor 1 are ranges.
    let one_hot = |d: &[f32]| d.iter().all(|v| *v == 0.0 || *v == 1.0);
    let as_is =
        data.len() == l.size() && (l.sensor == Sensor::Lidar || data.len() != LidarInput::RAYS || one_hot(data));
    let values = if as_is {
        if l.sensor == Sensor::Lidar {
            clipped(data)
        } else if let Some(i) = data.iter().position(|v| !v.is_finite()) {
            return Err(FrameError::Lidar(format!(
                "value {i} is {}, expected the model's {} input",
                data[i],
                l.sensor.name()
            )));
        } else {
            data.to_vec()
        }
    } else if data.len() == LidarInput::RAYS {
        l.filter(data)
    } else {
        return Err(FrameError::Lidar(format!(
            "{} values; the model's {} takes {} (or the LiDAR's {} ranges)",
            data.len(),
            l.sensor.name(),
            l.size(),
            LidarInput::RAYS
        )));
    };
    if first {
        obs.splice(0..0, values);
    } else {
        obs.extend_from_slice(&values);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use protocol::ros::{CompressedImage, Header, Image};
    use serde_bytes::ByteBuf;

    fn raw(w: u32, h: u32, encoding: &str, data: Vec<u8>, step: u32) -> RawFrame {
        RawFrame::Raw(Image {
            header: Header::default(),
            height: h,
            width: w,
            encoding: encoding.into(),
            is_bigendian: 0,
            step,
            data: ByteBuf::from(data),
        })
    }

    #[test]
    fn opencv_grey_and_channel_orders() {
        // OpenCV: pure red 76, green 150, blue 29.
        assert_eq!((grey(255, 0, 0), grey(0, 255, 0), grey(0, 0, 255), grey(255, 255, 255)), (76, 150, 29, 255));
        let mut out = Vec::new();
        preprocess(&[raw(1, 1, "bgr8", vec![255, 0, 0], 3)], 1, 1, 1, &mut out).unwrap();
        assert_eq!(out, [29.0]); // blue first in bgr8
        preprocess(&[raw(1, 1, "rgb8", vec![255, 0, 0], 3)], 1, 1, 1, &mut out).unwrap();
        assert_eq!(out, [76.0]);
        // Row padding (step > width × 3) is skipped.
        preprocess(&[raw(1, 2, "mono8", vec![10, 99, 20, 99], 2)], 2, 1, 1, &mut out).unwrap();
        assert_eq!(out, [10.0, 20.0]);
    }

    #[test]
    fn opencv_bilinear_sample_positions() {
        // 4 → 2 samples at (d + 0.5)·2 − 0.5 = 0.5 and 2.5: halfway 0–1 and 2–3.
        assert_eq!(taps(4, 2), vec![(0, 1, 0.5), (2, 3, 0.5)]);
        // 2 → 4 samples at −0.25 (clamped to 0), 0.25, 0.75, 1.25 (the last pixel twice).
        assert_eq!(taps(2, 4), vec![(0, 1, 0.0), (0, 1, 0.25), (0, 1, 0.75), (1, 1, 0.25)]);
        let mut out = Vec::new();
        preprocess(&[raw(4, 1, "mono8", vec![0, 100, 200, 40], 4)], 1, 2, 1, &mut out).unwrap();
        assert_eq!(out, [50.0, 120.0]);
    }

    #[test]
    fn bad_frames_are_errors_not_panics() {
        let mut out = Vec::new();
        let cases = [
            raw(2, 2, "bgr8", vec![0; 11], 6),
            raw(2, 2, "bgr8", vec![0; 12], 5),
            raw(2, 2, "yuv422", vec![0; 8], 4),
            raw(0, 2, "mono8", vec![], 0),
            raw(100_000, 100_000, "mono8", vec![], 100_000),
            RawFrame::Compressed(CompressedImage {
                header: Header::default(),
                format: "jpeg".into(),
                data: ByteBuf::from(vec![0xff, 0xd8, 1, 2]),
            }),
            RawFrame::Compressed(CompressedImage {
                header: Header::default(),
                format: "png".into(),
                data: ByteBuf::from(vec![1]),
            }),
        ];
        for f in cases {
            assert!(preprocess(std::slice::from_ref(&f), 120, 160, 1, &mut out).is_err(), "{f:?}");
        }
        assert_eq!(preprocess(&[], 120, 160, 1, &mut out), Err(FrameError::Missing { got: 0, need: 1 }));
    }

    #[test]
    fn a_jpeg_frame_decodes_to_its_grey_levels() {
        // A flat grey JPEG survives compression within a level or two.
        let img = image::RgbImage::from_pixel(640, 480, image::Rgb([90, 120, 150]));
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 90).encode_image(&img).unwrap();
        let f = RawFrame::Compressed(CompressedImage {
            header: Header::default(),
            format: "jpeg".into(),
            data: ByteBuf::from(jpeg),
        });
        let mut out = Vec::new();
        preprocess(&[f], 120, 160, 1, &mut out).unwrap();
        let want = grey(90, 120, 150) as f32;
        assert_eq!(out.len(), 120 * 160);
        assert!(out.iter().all(|v| (v - want).abs() <= 2.0), "{want} vs {:?}", &out[..4]);
    }

    /// Issue 31: LiDAR data is taken as the fusion node sends it or as raw ranges.
    #[test]
    fn lidar_data_is_taken_as_the_fusion_node_sends_it_or_as_raw_ranges() {
        let input = |sensor, sectors, values, clip| LidarInput { sensor, sectors, values, clip };
        let discretized = input(Sensor::DiscretizedSectorLidar, 8, 8, 2.0);
        let mut ranges = [f32::INFINITY; 64];
        ranges[3] = 0.3;
        ranges[20] = 1.1;
        // (model input, lidar_data, its place, the values the network gets)
        let one_hot = policy::metadata::sectors(&ranges, 8, 8, 2.0);
        let table: Vec<(LidarInput, Vec<f32>, bool, Vec<f32>)> = vec![
            // DISCRETIZED's 8 × 8: one-hot values as they are; ranges through the filter.
            (discretized, one_hot.clone(), false, one_hot.clone()),
            (discretized, ranges.to_vec(), true, one_hot.clone()),
            // SECTOR_LIDAR: its 8 bits, or the 64 ranges filtered (0.3 m in sector 0).
            (
                input(Sensor::SectorLidar, 8, 1, 0.5),
                vec![0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                false,
                vec![0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            ),
            (
                input(Sensor::SectorLidar, 8, 1, 0.5),
                ranges.to_vec(),
                false,
                vec![1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            ),
            // LIDAR: the 64 ranges clipped to [0.15, 1] (infinity reads 1).
            (input(Sensor::Lidar, 64, 1, 1.0), ranges.to_vec(), true, policy::metadata::clipped(&ranges)),
        ];
        for (l, data, first, want) in table {
            let mut obs = vec![7.0; 3];
            add_lidar(Some((l, first)), &data, &mut obs).unwrap();
            let (lidar, pixels) = if first { (&obs[..want.len()], &obs[want.len()..]) } else { (&obs[3..], &obs[..3]) };
            assert_eq!((lidar, pixels), (&want[..], &[7.0; 3][..]), "{:?} from {} values", l.sensor, data.len());
        }
        // No LiDAR: nothing added. A count that fits neither, or a sector that is not a number: an error.
        let mut obs = vec![1.0];
        add_lidar(None, &[0.5; 9], &mut obs).unwrap();
        assert_eq!(obs, [1.0]);
        let e = add_lidar(Some((discretized, false)), &[0.5; 9], &mut obs).unwrap_err().to_string();
        assert_eq!(e, "lidar_data: 9 values; the model's DISCRETIZED_SECTOR_LIDAR takes 64 (or the LiDAR's 64 ranges)");
        let mut bits = vec![0.0; 8];
        bits[2] = f32::NAN;
        let e =
            add_lidar(Some((input(Sensor::SectorLidar, 8, 1, 0.5), false)), &bits, &mut obs).unwrap_err().to_string();
        assert!(e.contains("value 2 is NaN"), "{e}");
    }
}
