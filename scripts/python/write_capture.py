#!/usr/bin/env python3
"""Writes a small texel capture with the PyPI `mcap`, `mcap-protobuf-support` and
`foxglove-schemas-protobuf` packages, exercising every encoding the capture format
lists, and a JSON file with the values the capture holds, so a reader can be checked
against them.

usage: write_capture.py OUT.mcap EXPECTED.json [--compression zstd|lz4|none]
"""

import argparse
import io
import json
import math
import struct

from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set
from PIL import Image

LIDAR_W, LIDAR_H = 16, 12
EO_W, EO_H = 32, 24
T0 = 1_700_000_000_000_000_000  # ns
PERIOD = 100_000_000  # 10 Hz


def stamp(msg, t):
    msg.timestamp.seconds = t // 1_000_000_000
    msg.timestamp.nanos = t % 1_000_000_000


def ranges(frame):
    """Radial ranges in metres with no-returns sprinkled in (0 = NaN in JSON)."""
    out = []
    for v in range(LIDAR_H):
        for u in range(LIDAR_W):
            if (u + v + frame) % 7 == 0:
                out.append(None)
            else:
                out.append(round(1.0 + 0.125 * u + 0.25 * v + 0.5 * frame, 3))
    return out


def eo_rgb(frame):
    return [((u * 8 + frame * 3) % 256, (v * 10) % 256, (u * v + frame) % 256)
            for v in range(EO_H) for u in range(EO_W)]


def ycbcr(p):
    r, g, b = p
    return (0.299 * r + 0.587 * g + 0.114 * b,
            128 - 0.168736 * r - 0.331264 * g + 0.5 * b,
            128 + 0.5 * r - 0.418688 * g - 0.081312 * b)


def clamp8(x):
    return max(0, min(255, int(round(x))))


def to_rgb(y, cb, cr):
    cb -= 128
    cr -= 128
    return (clamp8(y + 1.402 * cr), clamp8(y - 0.344136 * cb - 0.714136 * cr), clamp8(y + 1.772 * cb))


def encode_eo(rgb, encoding):
    """Returns (step, bytes, the RGB a reader must decode)."""
    if encoding == "rgb8":
        return EO_W * 3, bytes(c for p in rgb for c in p), rgb
    if encoding == "bgr8":
        return EO_W * 3, bytes(c for p in rgb for c in reversed(p)), rgb
    if encoding == "rgba8":
        return EO_W * 4, bytes(c for p in rgb for c in (*p, 255)), rgb
    if encoding == "mono8":
        grey = [clamp8(0.299 * r + 0.587 * g + 0.114 * b) for r, g, b in rgb]
        return EO_W, bytes(grey), [(g, g, g) for g in grey]
    if encoding == "yuyv":
        data, decoded = bytearray(), []
        for i in range(0, len(rgb), 2):
            a, b = ycbcr(rgb[i]), ycbcr(rgb[i + 1])
            y0, y1 = clamp8(a[0]), clamp8(b[0])
            cb, cr = clamp8((a[1] + b[1]) / 2), clamp8((a[2] + b[2]) / 2)
            data += bytes([y0, cb, y1, cr])
            decoded += [to_rgb(y0, cb, cr), to_rgb(y1, cb, cr)]
        return EO_W * 2, bytes(data), decoded
    raise ValueError(encoding)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("expected")
    ap.add_argument("--compression", default="zstd", choices=["zstd", "lz4", "none"])
    args = ap.parse_args()
    compression = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                   "none": CompressionType.NONE}[args.compression]

    expected = {"frames": [], "poses": []}
    with open(args.out, "wb") as f:
        writer = Writer(f, compression=compression, chunk_size=4096)
        writer.start(profile="", library="texel interop test (python mcap)")
        schemas, channels = {}, {}

        def channel(topic, cls):
            name = cls.DESCRIPTOR.full_name
            if name not in schemas:
                schemas[name] = writer.register_schema(
                    name=name, encoding="protobuf",
                    data=build_file_descriptor_set(cls).SerializeToString())
            if topic not in channels:
                channels[topic] = writer.register_channel(
                    topic=topic, message_encoding="protobuf", schema_id=schemas[name])
            return channels[topic]

        def write(topic, msg, t):
            writer.add_message(channel(topic, type(msg)), log_time=t, publish_time=t,
                               data=msg.SerializeToString())

        # Calibrations, extrinsic and sensor JSON before the first frame.
        lidar_k = [20.0, 0.0, 7.5, 0.0, 20.5, 5.5, 0.0, 0.0, 1.0]
        eo_k = [40.0, 0.0, 15.5, 0.0, 40.0, 11.5, 0.0, 0.0, 1.0]
        eo_d = [-0.12, 0.03, 0.001, -0.002, 0.0]
        for topic, frame, w, h, k, model, d in [
            ("/lidar/calibration", "lidar", LIDAR_W, LIDAR_H, lidar_k, "", []),
            ("/eo/calibration", "eo", EO_W, EO_H, eo_k, "plumb_bob", eo_d),
        ]:
            cal = CameraCalibration(frame_id=frame, width=w, height=h,
                                    distortion_model=model, D=d, K=k)
            stamp(cal, T0)
            write(topic, cal, T0)
        expected["lidar_k"], expected["eo_k"], expected["eo_d"] = lidar_k, eo_k, eo_d

        tf = FrameTransform(parent_frame_id="eo", child_frame_id="lidar")
        tf.translation.x, tf.translation.y, tf.translation.z = 0.031, -0.002, 0.0105
        half = math.radians(0.4) / 2
        tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = 0.0, math.sin(half), 0.0, math.cos(half)
        stamp(tf, T0)
        write("/tf_static", tf, T0)
        expected["eo_from_lidar"] = {"t": [0.031, -0.002, 0.0105],
                                     "q": [0.0, math.sin(half), 0.0, math.cos(half)]}

        sensor = {"version": 1, "range_noise_sigma_m": 0.004, "range_noise_sigma_per_m": 0.001,
                  "min_range_m": 0.5, "max_range_m": 40.0, "name": "python interop",
                  "vendor_extra": "ignored by readers"}
        sensor_schema = writer.register_schema(name="texel.Sensor", encoding="jsonschema",
                                               data=b'{"type":"object"}')
        sensor_channel = writer.register_channel(topic="/texel/sensor", message_encoding="json",
                                                 schema_id=sensor_schema)
        writer.add_message(sensor_channel, log_time=T0, publish_time=T0,
                           data=json.dumps(sensor).encode())
        expected["sensor"] = sensor

        eo_encodings = ["rgb8", "bgr8", "rgba8", "mono8", "yuyv", "png", "jpeg"]
        for i, eo_encoding in enumerate(eo_encodings):
            t = T0 + (i + 1) * PERIOD
            r = ranges(i)
            range_encoding = "32FC1" if i % 2 == 0 else "16UC1"
            if range_encoding == "32FC1":
                data = b"".join(struct.pack("<f", math.nan if x is None else x) for x in r)
                step = LIDAR_W * 4
                decoded_r = [None if x is None else struct.unpack("<f", struct.pack("<f", x))[0] for x in r]
            else:
                data = b"".join(struct.pack("<H", 0 if x is None else int(round(x * 1000))) for x in r)
                step = LIDAR_W * 2
                decoded_r = [None if x is None else int(round(x * 1000)) / 1000 for x in r]
            img = RawImage(frame_id="lidar", width=LIDAR_W, height=LIDAR_H, encoding=range_encoding,
                           step=step, data=data)
            stamp(img, t)
            write("/lidar/range", img, t)

            intensity = [(u * 100 + v * 7 + i) % 65536 for v in range(LIDAR_H) for u in range(LIDAR_W)]
            img = RawImage(frame_id="lidar", width=LIDAR_W, height=LIDAR_H, encoding="mono16",
                           step=LIDAR_W * 2, data=b"".join(struct.pack("<H", x) for x in intensity))
            stamp(img, t)
            write("/lidar/intensity", img, t)

            rgb = eo_rgb(i)
            # Odd frames say how they were exposed (/eo/exposure, before the image);
            # even ones do not, as captures made before the topic existed.
            exposure = None
            if i % 2 == 1:
                exposure = {"exposure_time_s": 1.0 / (100.0 * (i + 1)), "gain": 1.5 * i}
                if "exposure" not in channels:
                    schema = writer.register_schema(name="texel.EoExposure",
                                                    encoding="jsonschema",
                                                    data=b'{"type":"object"}')
                    channels["exposure"] = writer.register_channel(
                        topic="/eo/exposure", message_encoding="json", schema_id=schema)
                body = dict(exposure, timestamp={"sec": t // 10**9, "nsec": t % 10**9})
                writer.add_message(channels["exposure"], log_time=t, publish_time=t,
                                   data=json.dumps(body).encode())
            if eo_encoding in ("png", "jpeg"):
                im = Image.new("RGB", (EO_W, EO_H))
                im.putdata(rgb)
                buf = io.BytesIO()
                im.save(buf, format="PNG" if eo_encoding == "png" else "JPEG", quality=95)
                msg = CompressedImage(frame_id="eo", format=eo_encoding, data=buf.getvalue())
                stamp(msg, t)
                write("/eo/image/compressed", msg, t)
                decoded_rgb = rgb if eo_encoding == "png" else None
            else:
                step, data, decoded_rgb = encode_eo(rgb, eo_encoding)
                msg = RawImage(frame_id="eo", width=EO_W, height=EO_H, encoding=eo_encoding,
                               step=step, data=data)
                stamp(msg, t)
                write("/eo/image", msg, t)

            pose = FrameTransform(parent_frame_id="world", child_frame_id="eo")
            pose.translation.x, pose.translation.y, pose.translation.z = 0.1 * i, 2.0, 1.5
            pose.rotation.w = 1.0
            stamp(pose, t)
            write("/truth/pose", pose, t)
            expected["poses"].append({"t_ns": t, "translation": [0.1 * i, 2.0, 1.5]})

            expected["frames"].append({
                "t_ns": t, "range_encoding": range_encoding, "ranges_m": decoded_r,
                "intensity": intensity, "eo_encoding": eo_encoding, "exposure": exposure,
                "rgb": None if decoded_rgb is None else [c for p in decoded_rgb for c in p],
            })

        # A topic the format does not know: readers skip it.
        other = writer.register_channel(topic="/vendor/debug", message_encoding="json", schema_id=0)
        writer.add_message(other, log_time=T0, publish_time=T0, data=b"{}")
        writer.finish()

    with open(args.expected, "w") as f:
        json.dump(expected, f)


if __name__ == "__main__":
    main()
