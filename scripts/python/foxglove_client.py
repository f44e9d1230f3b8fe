#!/usr/bin/env python3
"""A Foxglove WebSocket client that is not Texel's: it speaks the published Foxglove
WebSocket protocol (https://github.com/foxglove/ws-protocol, docs/spec.md) with the
`websockets` package, subscribes to the topics it is given, decodes their messages
with `foxglove_schemas_protobuf` (or as JSON), loads every scan model of a
`foxglove.SceneUpdate` with trimesh (a real glTF reader), and prints one JSON line
per event on stdout:

  {"event": "connected", "subprotocol": ...}
  {"event": "advertise", "channels": [{"id", "topic", "encoding", "schemaName", "schemaEncoding"}]}
  {"event": "subscribed", "topics": [...]}
  {"event": "message", "topic": ..., "schema": ..., ...decoded fields...}
  {"event": "done"}

The protocol: the client offers a subprotocol (the foxglove crate's server takes
`foxglove.sdk.v1`, the ws-protocol spec names `foxglove.websocket.v1`; both are
offered, and the chosen one is reported), reads `serverInfo` and `advertise`
(JSON text messages), sends `subscribe` ({"op": "subscribe", "subscriptions":
[{"id", "channelId"}]}), and reads binary `messageData`: opcode 0x01, the
subscription id (u32 LE), the log time (u64 LE ns), the message.

Scan models are reported as a viewer in Foxglove would place them: the glTF scene
graph applied, then Foxglove's turn from glTF's +Y up to its +Z up (+90 degrees
about x), in the entity's frame before the primitive's pose.

usage: foxglove_client.py URL [--subscribe TOPIC ...] [--until-deleted ENTITY_ID]
                              [--timeout SECONDS]
"""

import argparse
import asyncio
import io
import json
import struct
import sys
import time

import numpy as np
import trimesh
import websockets
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
MESSAGE_DATA = 0x01


def emit(record):
    sys.stdout.write(json.dumps(record) + "\n")
    sys.stdout.flush()


def nanos(stamp):
    return stamp.seconds * 1_000_000_000 + stamp.nanos


def model_summary(primitive):
    """Loads a model primitive's glTF with trimesh and says what it holds."""
    scene = trimesh.load(io.BytesIO(primitive.data), file_type="glb", process=False)
    meshes = scene.dump(concatenate=False) if hasattr(scene, "dump") else [scene]
    vertices = np.concatenate([m.vertices for m in meshes])
    # Foxglove turns a glTF from +Y up to +Z up: (x, y, z) -> (x, -z, y).
    shown = np.stack([vertices[:, 0], -vertices[:, 2], vertices[:, 1]], axis=1)
    textures = []
    for m in meshes:
        material = getattr(m.visual, "material", None)
        image = getattr(material, "baseColorTexture", None) or getattr(material, "image", None)
        textures.append(list(image.size) if image is not None else None)
    p, q = primitive.pose.position, primitive.pose.orientation
    return {
        "media_type": primitive.media_type,
        "glb_bytes": len(primitive.data),
        "meshes": len(meshes),
        "vertices": int(len(vertices)),
        "faces": int(sum(len(m.faces) for m in meshes)),
        "textures": textures,
        "min": shown.min(axis=0).tolist(),
        "max": shown.max(axis=0).tolist(),
        "pose": {"position": [p.x, p.y, p.z], "orientation": [q.x, q.y, q.z, q.w]},
        "scale": [primitive.scale.x, primitive.scale.y, primitive.scale.z],
    }


def decode(schema, encoding, payload):
    if encoding == "json":
        return {"json": json.loads(payload)}
    if schema == "foxglove.CameraCalibration":
        m = CameraCalibration.FromString(payload)
        return {"frame_id": m.frame_id, "timestamp_ns": nanos(m.timestamp), "width": m.width,
                "height": m.height, "distortion_model": m.distortion_model, "D": list(m.D),
                "K": list(m.K), "R": list(m.R), "P": list(m.P)}
    if schema == "foxglove.FrameTransform":
        m = FrameTransform.FromString(payload)
        return {"parent": m.parent_frame_id, "child": m.child_frame_id,
                "timestamp_ns": nanos(m.timestamp),
                "translation": [m.translation.x, m.translation.y, m.translation.z],
                "rotation": [m.rotation.x, m.rotation.y, m.rotation.z, m.rotation.w]}
    if schema == "foxglove.RawImage":
        m = RawImage.FromString(payload)
        return {"frame_id": m.frame_id, "timestamp_ns": nanos(m.timestamp), "width": m.width,
                "height": m.height, "encoding": m.encoding, "step": m.step, "bytes": len(m.data)}
    if schema == "foxglove.SceneUpdate":
        m = SceneUpdate.FromString(payload)
        entities = []
        for e in m.entities:
            entities.append({
                "id": e.id, "frame_id": e.frame_id, "timestamp_ns": nanos(e.timestamp),
                "metadata": {kv.key: kv.value for kv in e.metadata},
                "models": [model_summary(p) for p in e.models],
            })
        return {"entities": entities,
                "deleted": [d.id for d in m.deletions],
                "deletion_types": [d.type for d in m.deletions]}
    return {"bytes": len(payload)}


async def connect(url, deadline):
    """Connects, retrying while the server is not up yet."""
    while True:
        try:
            return await websockets.connect(url, subprotocols=SUBPROTOCOLS, max_size=None,
                                            open_timeout=5)
        except (OSError, websockets.exceptions.InvalidHandshake):
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.05)


async def run(args):
    deadline = time.monotonic() + args.timeout
    ws = await connect(args.url, deadline)
    async with ws:
        emit({"event": "connected", "subprotocol": ws.subprotocol})
        channels = {}
        subscriptions = {}
        wanted = set(args.subscribe)
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"no end condition within {args.timeout} s")
            message = await asyncio.wait_for(ws.recv(), remaining)
            if isinstance(message, str):
                op = json.loads(message)
                if op.get("op") == "serverInfo":
                    emit({"event": "serverInfo", "name": op.get("name"),
                          "capabilities": op.get("capabilities")})
                elif op.get("op") == "advertise":
                    new = []
                    for c in op["channels"]:
                        channels[c["id"]] = c
                        new.append({k: c.get(k) for k in
                                    ("id", "topic", "encoding", "schemaName", "schemaEncoding")})
                    emit({"event": "advertise", "channels": new})
                    subscribe = [c for c in op["channels"] if c["topic"] in wanted
                                 and c["id"] not in subscriptions.values()]
                    if subscribe:
                        for c in subscribe:
                            subscriptions[c["id"]] = c["id"]
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": c["id"], "channelId": c["id"]} for c in subscribe]}))
                        emit({"event": "subscribed", "topics": [c["topic"] for c in subscribe]})
                elif op.get("op") == "status":
                    emit({"event": "status", "level": op.get("level"), "message": op.get("message")})
                continue
            if len(message) < 13 or message[0] != MESSAGE_DATA:
                continue
            subscription, log_time = struct.unpack_from("<IQ", message, 1)
            channel = channels.get(subscriptions.get(subscription))
            if channel is None:
                continue
            record = {"event": "message", "topic": channel["topic"],
                      "schema": channel.get("schemaName"), "log_time_ns": log_time}
            record.update(decode(channel.get("schemaName"), channel["encoding"],
                                 message[13:]))
            emit(record)
            if args.until_deleted is not None and args.until_deleted in record.get("deleted", []):
                emit({"event": "done"})
                return


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("url")
    parser.add_argument("--subscribe", nargs="*", default=[])
    parser.add_argument("--until-deleted", default=None,
                        help="exit after a SceneUpdate deletes this entity id")
    parser.add_argument("--timeout", type=float, default=60.0)
    args = parser.parse_args()
    try:
        asyncio.run(run(args))
    except Exception as e:  # noqa: BLE001 - the test reads the reason on stderr
        sys.stderr.write(f"foxglove_client: {type(e).__name__}: {e}\n")
        sys.exit(1)


if __name__ == "__main__":
    main()
