//! The DeepRacer car's own ROS 2 messages, as they travel over Zenoh.
//!
//! zenoh-bridge-ros2dds (and rmw_zenoh) carry a ROS 2 message as its CDR serialisation: a
//! 4-byte encapsulation header (`00 01 00 00` little-endian, `00 00 00 00` big-endian), then
//! the fields in order, each aligned to its size relative to the end of that header. The
//! encoding is `cdr-encoding`'s (serde); the layouts here are those of the stock DeepRacer
//! interfaces package (`deepracer_interfaces_pkg/msg/*.msg`) and `sensor_msgs`:
//!
//! | message | community stack (Jazzy, larsll's interfaces) | original AWS release |
//! |---|---|---|
//! | `EvoSensorMsg` | `CompressedImage[] images; float32[] lidar_data; Imu imu_data` | `Image[] images; float32[] lidar_data` |
//! | `ServoCtrlMsg` | `Header header; Header correlation; float32 angle; float32 throttle` | `float32 angle; float32 throttle` |
//!
//! A bridge maps the ROS name `/sensor_fusion_pkg/sensor_msg` to the Zenoh key
//! `sensor_fusion_pkg/sensor_msg`, with the bridge's namespace in front (`car7/…`): [`CarKeys`].

use byteorder::{BigEndian, LittleEndian};
use serde::{Deserialize, Serialize};
use serde_bytes::ByteBuf;

/// Which release of the interfaces package the car runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Layout {
    /// aws-deepracer-community/deepracer-custom-car (ROS 2 Jazzy): JPEG frames, IMU, headed
    /// servo messages.
    Community,
    /// The original AWS car software: raw `sensor_msgs/Image` frames, bare servo messages.
    Aws,
}

/// `builtin_interfaces/Time`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Time {
    /// Seconds.
    pub sec: i32,
    /// Nanoseconds.
    pub nanosec: u32,
}

impl Time {
    /// A time from seconds since the epoch.
    pub fn from_secs_f64(s: f64) -> Time {
        Time { sec: s.floor() as i32, nanosec: ((s - s.floor()) * 1e9) as u32 }
    }
}

/// `std_msgs/Header`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// Stamp.
    pub stamp: Time,
    /// Frame id.
    pub frame_id: String,
}

/// `sensor_msgs/CompressedImage`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CompressedImage {
    /// Header.
    pub header: Header,
    /// "jpeg", "png", …
    pub format: String,
    /// The compressed bytes.
    pub data: ByteBuf,
}

/// `sensor_msgs/Image`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Image {
    /// Header.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// "bgr8", "rgb8", "mono8", …
    pub encoding: String,
    /// 1 when the data are big-endian (multi-byte encodings only).
    pub is_bigendian: u8,
    /// Bytes per row.
    pub step: u32,
    /// Pixels.
    pub data: ByteBuf,
}

/// `geometry_msgs/Quaternion`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w.
    pub w: f64,
}

/// `geometry_msgs/Vector3`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

/// `sensor_msgs/Imu`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Imu {
    /// Header.
    pub header: Header,
    /// Orientation.
    pub orientation: Quaternion,
    /// Its covariance (row-major 3×3).
    pub orientation_covariance: [f64; 9],
    /// Angular velocity.
    pub angular_velocity: Vector3,
    /// Its covariance.
    pub angular_velocity_covariance: [f64; 9],
    /// Linear acceleration.
    pub linear_acceleration: Vector3,
    /// Its covariance.
    pub linear_acceleration_covariance: [f64; 9],
}

/// `deepracer_interfaces_pkg/EvoSensorMsg`, community layout.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EvoSensorCommunity {
    /// Camera frames (JPEG).
    pub images: Vec<CompressedImage>,
    /// LiDAR ranges.
    pub lidar_data: Vec<f32>,
    /// IMU.
    pub imu_data: Imu,
}

/// `deepracer_interfaces_pkg/EvoSensorMsg`, original AWS layout.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EvoSensorAws {
    /// Camera frames (raw).
    pub images: Vec<Image>,
    /// LiDAR ranges.
    pub lidar_data: Vec<f32>,
}

/// `deepracer_interfaces_pkg/ServoCtrlMsg`, community layout.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ServoCommunity {
    /// When the command was made.
    pub header: Header,
    /// The header of the frame it answers.
    pub correlation: Header,
    /// Steering ratio in [-1, 1] (+ = left).
    pub angle: f32,
    /// Throttle ratio in [-1, 1].
    pub throttle: f32,
}

/// `deepracer_interfaces_pkg/ServoCtrlMsg`, original AWS layout.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ServoAws {
    /// Steering ratio in [-1, 1].
    pub angle: f32,
    /// Throttle ratio in [-1, 1].
    pub throttle: f32,
}

/// Why a CDR payload could not be read.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CdrError {
    /// Shorter than the encapsulation header.
    #[error("{0} bytes: too short for a CDR message")]
    Short(usize),
    /// An encapsulation other than plain CDR.
    #[error("encapsulation {0:02x} {1:02x} is not plain CDR (00 00 big-endian, 00 01 little-endian)")]
    Encapsulation(u8, u8),
    /// The fields do not decode as the expected message.
    #[error("not a {what}: {msg}")]
    Fields {
        /// The message type.
        what: &'static str,
        /// The decoder's words.
        msg: String,
    },
}

/// Serialise with the little-endian encapsulation header, as ROS 2 does.
pub fn to_cdr<T: Serialize>(m: &T) -> Vec<u8> {
    let body = cdr_encoding::to_vec::<T, LittleEndian>(m).expect("these messages serialise");
    let mut out = Vec::with_capacity(body.len() + 4);
    out.extend_from_slice(&[0x00, 0x01, 0x00, 0x00]);
    out.extend_from_slice(&body);
    out
}

/// Deserialise a CDR payload (either byte order). Never panics.
pub fn from_cdr<T: for<'de> Deserialize<'de>>(bytes: &[u8], what: &'static str) -> Result<T, CdrError> {
    if bytes.len() < 4 {
        return Err(CdrError::Short(bytes.len()));
    }
    let fields = |e: cdr_encoding::Error| CdrError::Fields { what, msg: e.to_string() };
    match (bytes[0], bytes[1]) {
        (0x00, 0x01) => cdr_encoding::from_bytes::<T, LittleEndian>(&bytes[4..]).map(|(m, _)| m).map_err(fields),
        (0x00, 0x00) => cdr_encoding::from_bytes::<T, BigEndian>(&bytes[4..]).map(|(m, _)| m).map_err(fields),
        (a, b) => Err(CdrError::Encapsulation(a, b)),
    }
}

/// A camera frame as it came from the car, before decoding.
#[derive(Clone, Debug, PartialEq)]
pub enum RawFrame {
    /// JPEG (or another compressed format the `format` names).
    Compressed(CompressedImage),
    /// Raw pixels.
    Raw(Image),
}

impl RawFrame {
    /// The frame's header.
    pub fn header(&self) -> &Header {
        match self {
            RawFrame::Compressed(c) => &c.header,
            RawFrame::Raw(i) => &i.header,
        }
    }
}

/// What one `EvoSensorMsg` carries for a model: its camera frames and its `lidar_data`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SensorFrames {
    /// The camera images (one, or the stereo pair).
    pub frames: Vec<RawFrame>,
    /// The LiDAR's values as the sensor-fusion node sends them (empty without a LiDAR).
    pub lidar: Vec<f32>,
}

/// Decode one `EvoSensorMsg` in `layout`.
pub fn decode_sensor(bytes: &[u8], layout: Layout) -> Result<SensorFrames, CdrError> {
    Ok(match layout {
        Layout::Community => {
            let m = from_cdr::<EvoSensorCommunity>(bytes, "EvoSensorMsg (community layout)")?;
            SensorFrames { frames: m.images.into_iter().map(RawFrame::Compressed).collect(), lidar: m.lidar_data }
        }
        Layout::Aws => {
            let m = from_cdr::<EvoSensorAws>(bytes, "EvoSensorMsg (AWS layout)")?;
            SensorFrames { frames: m.images.into_iter().map(RawFrame::Raw).collect(), lidar: m.lidar_data }
        }
    })
}

/// Encode one `EvoSensorMsg` in `layout` from frames of the matching kind and LiDAR values
/// (the simulated car).
pub fn encode_sensor(frames: Vec<RawFrame>, lidar: &[f32], layout: Layout) -> Vec<u8> {
    match layout {
        Layout::Community => to_cdr(&EvoSensorCommunity {
            images: frames
                .into_iter()
                .filter_map(|f| if let RawFrame::Compressed(c) = f { Some(c) } else { None })
                .collect(),
            lidar_data: lidar.to_vec(),
            imu_data: Imu::default(),
        }),
        Layout::Aws => to_cdr(&EvoSensorAws {
            images: frames.into_iter().filter_map(|f| if let RawFrame::Raw(i) = f { Some(i) } else { None }).collect(),
            lidar_data: lidar.to_vec(),
        }),
    }
}

/// A servo command, whatever the layout.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Servo {
    /// Steering ratio in [-1, 1].
    pub angle: f32,
    /// Throttle ratio in [-1, 1].
    pub throttle: f32,
}

/// Encode a command in `layout`; `stamp` and `frame` fill the community layout's headers
/// (`correlation` is the answered frame's header).
pub fn encode_servo(s: Servo, layout: Layout, stamp: Time, frame_id: u64, correlation: &Header) -> Vec<u8> {
    match layout {
        Layout::Community => to_cdr(&ServoCommunity {
            header: Header { stamp, frame_id: frame_id.to_string() },
            correlation: correlation.clone(),
            angle: s.angle,
            throttle: s.throttle,
        }),
        Layout::Aws => to_cdr(&ServoAws { angle: s.angle, throttle: s.throttle }),
    }
}

/// Decode a command in `layout` (with the answered frame's header, community layout only).
pub fn decode_servo(bytes: &[u8], layout: Layout) -> Result<(Servo, Option<Header>), CdrError> {
    match layout {
        Layout::Community => {
            let m = from_cdr::<ServoCommunity>(bytes, "ServoCtrlMsg (community layout)")?;
            Ok((Servo { angle: m.angle, throttle: m.throttle }, Some(m.correlation)))
        }
        Layout::Aws => {
            let m = from_cdr::<ServoAws>(bytes, "ServoCtrlMsg (AWS layout)")?;
            Ok((Servo { angle: m.angle, throttle: m.throttle }, None))
        }
    }
}

/// The car's Zenoh keys, as zenoh-bridge-ros2dds names its ROS topics.
#[derive(Clone, Debug, PartialEq)]
pub struct CarKeys {
    /// Camera frames in: `{namespace}/sensor_fusion_pkg/sensor_msg`.
    pub sensor: String,
    /// Commands out: `{namespace}/deepracer_navigation_pkg/auto_drive`.
    pub servo: String,
}

impl CarKeys {
    /// The keys under a bridge namespace (`""`, `car7` or `/car7`).
    pub fn new(namespace: &str) -> CarKeys {
        let ns = namespace.trim_matches('/');
        let key = |topic: &str| if ns.is_empty() { topic.to_string() } else { format!("{ns}/{topic}") };
        CarKeys { sensor: key("sensor_fusion_pkg/sensor_msg"), servo: key("deepracer_navigation_pkg/auto_drive") }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn servo_layouts_are_byte_exact() {
        // AWS: two float32 after the header, nothing else.
        let b = encode_servo(Servo { angle: 0.5, throttle: -1.0 }, Layout::Aws, Time::default(), 0, &Header::default());
        assert_eq!(b, [0, 1, 0, 0, 0, 0, 0, 0x3f, 0, 0, 0x80, 0xbf]);
        // Community: header (sec, nanosec, frame_id "7\0"), correlation, then the floats aligned to 4.
        let corr = Header { stamp: Time { sec: 1, nanosec: 2 }, frame_id: String::new() };
        let b =
            encode_servo(Servo { angle: 1.0, throttle: 0.0 }, Layout::Community, Time { sec: 3, nanosec: 4 }, 7, &corr);
        #[rustfmt::skip]
        let want: Vec<u8> = vec![
            0, 1, 0, 0,
            3, 0, 0, 0, 4, 0, 0, 0, 2, 0, 0, 0, b'7', 0, 0, 0,   // header (string length 2 with NUL, padded)
            1, 0, 0, 0, 2, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0,      // correlation (empty string = length 1, NUL)
            0, 0, 0x80, 0x3f, 0, 0, 0, 0,
        ];
        assert_eq!(b, want);
        let (s, c) = decode_servo(&b, Layout::Community).unwrap();
        assert_eq!((s.angle, s.throttle, c), (1.0, 0.0, Some(corr)));
    }

    #[test]
    fn sensor_messages_round_trip_and_garbage_is_an_error() {
        let img = Image {
            header: Header { stamp: Time { sec: 5, nanosec: 6 }, frame_id: "camera".into() },
            height: 2,
            width: 3,
            encoding: "bgr8".into(),
            is_bigendian: 0,
            step: 9,
            data: ByteBuf::from((0..18u8).collect::<Vec<_>>()),
        };
        let b = encode_sensor(vec![RawFrame::Raw(img.clone())], &[0.25, 1.0], Layout::Aws);
        let d = decode_sensor(&b, Layout::Aws).unwrap();
        assert_eq!((d.frames, d.lidar), (vec![RawFrame::Raw(img)], vec![0.25, 1.0]));
        let jpeg =
            CompressedImage { header: Header::default(), format: "jpeg".into(), data: ByteBuf::from(vec![1, 2, 3]) };
        let b = encode_sensor(vec![RawFrame::Compressed(jpeg.clone())], &[], Layout::Community);
        assert_eq!(decode_sensor(&b, Layout::Community).unwrap().frames, vec![RawFrame::Compressed(jpeg)]);
        for bad in [&b"\x00\x01"[..], b"\x00\x01\x00\x00\xff\xff\xff\xff", b"\x01\x02\x00\x00abcd"] {
            assert!(decode_sensor(bad, Layout::Community).is_err());
            assert!(decode_servo(bad, Layout::Aws).is_err());
        }
        // Every truncation of a good message is an error, never a panic.
        for n in 0..b.len() {
            assert!(decode_sensor(&b[..n], Layout::Community).is_err(), "{n}");
        }
    }

    #[test]
    fn keys_follow_the_bridge_namespace() {
        assert_eq!(CarKeys::new("").sensor, "sensor_fusion_pkg/sensor_msg");
        assert_eq!(CarKeys::new("/car7").servo, "car7/deepracer_navigation_pkg/auto_drive");
    }
}
