"""Independent check of a duv log written as a ROS 2 bag (`[log] format = "ros2"`).

Opens the log folder with the `rosbags` package as a rosbag2 bag (metadata.yaml, MCAP storage
with the `ros2` profile), registers the message types the bag carries in its `ros2msg` schemas
(the duv_msgs ones are not in any ROS distribution; for standard ones the bag's definition must
agree field by field with the typestore's own), deserialises every message from CDR and prints
a JSON summary: counts per topic, the type of each topic, and a few decoded fields.

usage: check_ros2_bag.py LOG_DIR
"""

import json
import math
import sys
from pathlib import Path

from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore, get_types_from_msg


def field_names(fielddefs, name):
    return [f[0] for f in fielddefs[name][1]]


def main():
    bag = Path(sys.argv[1])
    store = get_typestore(Stores.ROS2_HUMBLE)
    out = {"counts": {}, "types": {}, "fields": {}, "mismatched_definitions": [], "errors": []}
    with Reader(bag) as reader:
        out["message_count"] = reader.message_count
        out["duration_ns"] = reader.duration
        new_types = {}
        for conn in reader.connections:
            out["types"][conn.topic] = conn.msgtype
            if conn.msgdef.format.name != "MSG":
                out["errors"].append(f"{conn.topic}: schema is {conn.msgdef.format.name}, not ros2msg")
                continue
            types = get_types_from_msg(conn.msgdef.data, conn.msgtype)
            for name, definition in types.items():
                if name in store.fielddefs:
                    theirs = field_names(store.fielddefs, name)
                    ours = [f[0] for f in definition[1]]
                    if theirs != ours:
                        out["mismatched_definitions"].append(f"{name}: bag {ours}, typestore {theirs}")
                else:
                    new_types[name] = definition
        store.register(new_types)
        first = {}
        for conn, t_ns, raw in reader.messages():
            try:
                msg = store.deserialize_cdr(raw, conn.msgtype)
            except Exception as e:  # noqa: BLE001 - report every failure, not just the first
                out["errors"].append(f"{conn.topic} at {t_ns}: {e}")
                continue
            out["counts"][conn.topic] = out["counts"].get(conn.topic, 0) + 1
            first.setdefault(conn.topic, msg)
            if conn.topic in ("/camera/image", "/keyframe/image", "/keyframe/inv_depth", "/keyframe/variance") and conn.msgtype == "sensor_msgs/msg/Image":
                if msg.step * msg.height != len(msg.data):
                    out["errors"].append(f"{conn.topic}: {len(msg.data)} bytes for step {msg.step} x {msg.height}")
            if conn.msgtype == "sensor_msgs/msg/CompressedImage":
                data = bytes(msg.data)
                if not (data.startswith(b"\xff\xd8") and data.endswith(b"\xff\xd9")):
                    out["errors"].append(f"{conn.topic}: not a whole JPEG stream")
                out["fields"]["jpeg_streams"] = out["fields"].get("jpeg_streams", 0) + 1
            if conn.msgtype == "sensor_msgs/msg/PointCloud2" and msg.point_step * msg.width != len(msg.data):
                out["errors"].append(f"{conn.topic}: {len(msg.data)} bytes for {msg.width} points")
            if conn.msgtype == "duv_msgs/msg/Health":
                json.loads(msg.json)
        f = out["fields"]
        if (m := first.get("/camera/image")) is not None:
            f["image"] = {"format": getattr(m, "format", None), "encoding": getattr(m, "encoding", None), "width": getattr(m, "width", None), "height": getattr(m, "height", None), "frame_id": m.header.frame_id, "stamp_ns": m.header.stamp.sec * 10**9 + m.header.stamp.nanosec}
        if (m := first.get("/camera/camera_info")) is not None:
            f["camera_info"] = {"width": m.width, "height": m.height, "k": [float(x) for x in m.k], "p": [float(x) for x in m.p]}
        if (m := first.get("/slam/pose")) is not None:
            p = m.pose
            f["pose"] = {"frame_id": m.header.frame_id, "position": [p.position.x, p.position.y, p.position.z], "orientation": [p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]}
        if (m := first.get("/tf")) is not None:
            t = m.transforms[0]
            f["tf"] = {"parent": t.header.frame_id, "child": t.child_frame_id, "translation": [t.transform.translation.x, t.transform.translation.y, t.transform.translation.z]}
        if (m := first.get("/slam/state")) is not None:
            f["state"] = {"seq": m.seq, "state": m.state, "tracked": bool(m.tracked), "has_keyframe": bool(m.has_keyframe), "keyframe": m.keyframe, "segment": m.segment, "why": m.why, "value_is_nan": math.isnan(m.value)}
        if (m := first.get("/map/gaussians")) is not None:
            f["cloud"] = {"width": m.width, "point_step": m.point_step, "fields": [(x.name, x.offset, x.datatype, x.count) for x in m.fields], "frame_id": m.header.frame_id}
        if (m := first.get("/keyframe/inv_depth")) is not None:
            f["inv_depth"] = {"encoding": m.encoding, "width": m.width, "height": m.height}
        if (m := first.get("/map/checkpoint")) is not None:
            f["checkpoint_bytes"] = len(m.data)
        if (m := first.get("/slam/window")) is not None:
            f["window_magic"] = bytes(m.data[:4]).decode("latin-1")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
