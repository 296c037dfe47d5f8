"""The car's side of `deploy`, written with clients nobody in Paddock wrote.

rosbags (from PyPI) encodes the camera messages and decodes the servo commands in CDR from
the interfaces package's .msg definitions; eclipse-zenoh (from PyPI) carries them, as
zenoh-bridge-ros2dds would on a car. Usage:

    car_peer.py ENDPOINT LAYOUT NAMESPACE FRAMES_DIR OUT_JSON

FRAMES_DIR holds frame_<i>.bin: JPEG bytes (community layout) or 160x120 bgr8 pixels (aws).
For every frame it writes the encoded message to FRAMES_DIR/msg_<i>.cdr and records the
command that answered it.
"""
import json
import os
import pathlib
import sys
import threading
import time

import numpy as np
import zenoh
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

EVO = {
    "community": "sensor_msgs/CompressedImage[] images\nfloat32[] lidar_data\nsensor_msgs/Imu imu_data\n",
    "aws": "sensor_msgs/Image[] images\nfloat32[] lidar_data\n",
}
SERVO = {
    "community": "std_msgs/Header header\nstd_msgs/Header correlation\nfloat32 angle\nfloat32 throttle\n",
    "aws": "float32 angle\nfloat32 throttle\n",
}


def main():
    endpoint, layout, ns, frames_dir, out = sys.argv[1:6]
    frames_dir = pathlib.Path(frames_dir)
    ts = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    types.update(get_types_from_msg(EVO[layout], "deepracer_interfaces_pkg/msg/EvoSensorMsg"))
    types.update(get_types_from_msg(SERVO[layout], "deepracer_interfaces_pkg/msg/ServoCtrlMsg"))
    ts.register(types)
    T = ts.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]

    def frame_msg(i):
        raw = (frames_dir / f"frame_{i}.bin").read_bytes()
        header = Header(stamp=Time(sec=1000 + i, nanosec=i), frame_id=f"f{i}")
        if layout == "community":
            img = T["sensor_msgs/msg/CompressedImage"](header=header, format="jpeg", data=np.frombuffer(raw, np.uint8))
            imu = T["sensor_msgs/msg/Imu"](
                header=header,
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.zeros(9),
                angular_velocity=T["geometry_msgs/msg/Vector3"](x=0.1, y=0.2, z=0.3),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=9.8),
                linear_acceleration_covariance=np.zeros(9),
            )
            msg = T["deepracer_interfaces_pkg/msg/EvoSensorMsg"](
                images=[img], lidar_data=np.array([0.5, 1.5], np.float32), imu_data=imu
            )
        else:
            img = T["sensor_msgs/msg/Image"](
                header=header, height=120, width=160, encoding="bgr8", is_bigendian=0, step=480,
                data=np.frombuffer(raw, np.uint8),
            )
            msg = T["deepracer_interfaces_pkg/msg/EvoSensorMsg"](images=[img], lidar_data=np.array([], np.float32))
        return bytes(ts.serialize_cdr(msg, "deepracer_interfaces_pkg/msg/EvoSensorMsg"))

    n = len(list(frames_dir.glob("frame_*.bin")))
    got = []
    cond = threading.Condition()

    def on_servo(sample):
        m = ts.deserialize_cdr(bytes(sample.payload.to_bytes()), "deepracer_interfaces_pkg/msg/ServoCtrlMsg")
        rec = {"angle": float(m.angle), "throttle": float(m.throttle)}
        if layout == "community":
            rec["correlation"] = m.correlation.frame_id
            rec["correlation_sec"] = m.correlation.stamp.sec
        with cond:
            got.append(rec)
            cond.notify_all()

    conf = zenoh.Config()
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    prefix = ns.strip("/") + "/" if ns.strip("/") else ""
    sub = session.declare_subscriber(prefix + "deepracer_navigation_pkg/auto_drive", on_servo)
    pub = session.declare_publisher(prefix + "sensor_fusion_pkg/sensor_msg")
    answers = []
    deadline = time.time() + 60
    for i in range(n):
        payload = frame_msg(i)
        (frames_dir / f"msg_{i}.cdr").write_bytes(payload)
        while True:
            with cond:
                got.clear()
            pub.put(payload)
            with cond:
                cond.wait_for(lambda: len(got) > 0, timeout=0.5)
                hit = [g for g in got if layout != "community" or g["correlation"] == f"f{i}"]
            if hit:
                answers.append(hit[0])
                break
            if time.time() > deadline:
                raise SystemExit(f"no command answered frame {i}")
    sub.undeclare()
    pub.undeclare()
    session.close()
    pathlib.Path(out).write_text(json.dumps(answers))


if __name__ == "__main__":
    # Exit at once either way: zenoh's threads can hold up an interpreter's shutdown.
    try:
        main()
    except BaseException:
        import traceback
        traceback.print_exc()
        sys.stderr.flush()
        os._exit(1)
    sys.stdout.flush()
    os._exit(0)
