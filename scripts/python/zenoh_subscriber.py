"""A Zenoh peer that is not Texel's: reads the cameras' models the way any Zenoh
program would (eclipse-zenoh), from the keys docs/daemon.md documents, and prints
what it received as JSON: per camera, each listed scan's id, and from the scan's own
data (a ScanAdded wire frame, docs/wire-protocol.md) its id, timestamp and vertex
count, plus the live samples it saw while subscribed.

    python zenoh_subscriber.py --connect tcp/127.0.0.1:7447 --site test [--camera '*']
"""

import argparse
import json
import struct
import sys
import time

import zenoh

SCAN_LISTED = 0x14
SCAN_ADDED = 0x12


def frames(payload: bytes):
    """Splits a payload of wire frames (u32 body length, kind, fields)."""
    out, at = [], 0
    while at < len(payload):
        (body_len,) = struct.unpack_from("<I", payload, at)
        if body_len == 0 or at + 4 + body_len > len(payload):
            raise ValueError(f"a frame at byte {at} runs past the payload")
        out.append(payload[at + 4 : at + 4 + body_len])
        at += 4 + body_len
    return out


def scan_added(body: bytes):
    """id, timestamp and vertex count of a ScanAdded body (kind byte first)."""
    assert body[0] == SCAN_ADDED, f"kind {body[0]:#x}"
    at = 1
    (scan_id,) = struct.unpack_from("<Q", body, at)
    at += 8 + 56  # id, world_from_scan
    (timestamp_ns,) = struct.unpack_from("<Q", body, at)
    at += 8 + 4 + 8 + 56 + 24 + 16  # timestamp, seq, grid, scan_from_lidar, cop, noise
    (vertex_count,) = struct.unpack_from("<I", body, at)
    return {"id": scan_id, "timestamp_ns": timestamp_ns, "vertex_count": vertex_count}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--connect", action="append", default=[])
    ap.add_argument("--site", default="*")
    ap.add_argument("--camera", default="*")
    ap.add_argument("--listen-s", type=float, default=1.0)
    args = ap.parse_args()

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", json.dumps(args.connect))
    conf.insert_json5("scouting/multicast/enabled", "false")
    prefix = f"texel/{args.site}/{args.camera}"
    live = []
    with zenoh.open(conf) as session:
        sub = session.declare_subscriber(
            f"{prefix}/**", lambda s: live.append(str(s.key_expr))
        )
        time.sleep(0.5)  # let the links come up
        cameras = {}
        for reply in session.get(f"{prefix}/model", timeout=10.0):
            if reply.ok is None:
                continue
            key = str(reply.ok.key_expr)
            camera = key.rsplit("/", 1)[0]
            listed = []
            for body in frames(reply.ok.payload.to_bytes()):
                if body[0] == SCAN_LISTED:
                    listed.append(struct.unpack_from("<Q", body, 1)[0])
            scans = []
            for scan_id in listed:
                for r in session.get(f"{camera}/scan/{scan_id}", timeout=10.0):
                    if r.ok is not None:
                        scans.append(scan_added(frames(r.ok.payload.to_bytes())[0]))
            cameras[camera] = {"listed": listed, "scans": scans}
        time.sleep(args.listen_s)
        sub.undeclare()
    json.dump({"cameras": cameras, "live_keys": sorted(set(live))}, sys.stdout)
    print()


if __name__ == "__main__":
    main()
