#!/usr/bin/env python3
"""Reads a texel capture with the PyPI `mcap` reader, decodes every message with the
Foxglove protobuf classes (`mcap-protobuf-support`'s decoder) or as JSON, and prints
what it found as JSON, so the capture's writer can be checked by an independent reader.

usage: read_capture.py CAPTURE.mcap
"""

import json
import math
import struct
import sys

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory


def stamp_ns(msg):
    return msg.timestamp.seconds * 1_000_000_000 + msg.timestamp.nanos


def main():
    out = {"topics": {}, "calibrations": {}, "range": [], "intensity": [], "eo": [],
           "poses": {}, "schemas": {}}
    with open(sys.argv[1], "rb") as f:
        reader = make_reader(f)
        factory = DecoderFactory()
        header = reader.get_header()
        out["profile"] = header.profile
        for schema, channel, message in reader.iter_messages():
            topic = channel.topic
            out["topics"][topic] = out["topics"].get(topic, 0) + 1
            out["schemas"][topic] = [schema.name if schema else "", schema.encoding if schema else "",
                                     channel.message_encoding]
            if topic == "/texel/sensor":
                out["sensor"] = json.loads(message.data)
                continue
            if topic == "/eo/exposure":
                exposure = json.loads(message.data)
                exposure["log_time"] = message.log_time
                out.setdefault("exposures", []).append(exposure)
                continue
            if topic == "/texel/anchor":
                anchor = json.loads(message.data)
                anchor["log_time"] = message.log_time
                out.setdefault("anchors", []).append(anchor)
                continue
            if channel.message_encoding != "protobuf":
                continue
            decoded = factory.decoder_for(channel.message_encoding, schema)(message.data)
            if message.log_time != message.publish_time:
                raise SystemExit(f"{topic}: log time {message.log_time} != publish time")
            if topic.endswith("/calibration"):
                out["calibrations"][topic] = {
                    "width": decoded.width, "height": decoded.height, "K": list(decoded.K),
                    "D": list(decoded.D), "model": decoded.distortion_model,
                    "frame_id": decoded.frame_id}
            elif topic == "/tf_static" or topic.endswith("/pose"):
                item = {"t_ns": stamp_ns(decoded), "log_time": message.log_time,
                        "parent": decoded.parent_frame_id, "child": decoded.child_frame_id,
                        "t": [decoded.translation.x, decoded.translation.y, decoded.translation.z],
                        "q": [decoded.rotation.x, decoded.rotation.y, decoded.rotation.z, decoded.rotation.w]}
                out["poses"].setdefault(topic, []).append(item)
            elif topic in ("/lidar/range", "/lidar/intensity"):
                fmt = {"32FC1": "<f", "16UC1": "<H", "mono16": "<H"}[decoded.encoding]
                size = struct.calcsize(fmt)
                values = []
                for v in range(decoded.height):
                    row = decoded.data[v * decoded.step: v * decoded.step + decoded.width * size]
                    for (x,) in struct.iter_unpack(fmt, row):
                        values.append(None if isinstance(x, float) and math.isnan(x) else x)
                out["range" if topic == "/lidar/range" else "intensity"].append({
                    "t_ns": stamp_ns(decoded), "log_time": message.log_time,
                    "encoding": decoded.encoding, "width": decoded.width, "height": decoded.height,
                    "frame_id": decoded.frame_id, "values": values})
            elif topic == "/eo/image":
                out["eo"].append({"t_ns": stamp_ns(decoded), "log_time": message.log_time,
                                  "encoding": decoded.encoding, "width": decoded.width,
                                  "height": decoded.height, "step": decoded.step,
                                  "frame_id": decoded.frame_id, "data": list(decoded.data)})
    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
