"""Write small ROS bags with ``rosbags`` itself for the tests (no bag files are committed)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np


def _store(ros1: bool):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)


def image_msg(ts, rgb: np.ndarray, encoding: str, stamp_ns: int, ros1: bool = False, pad: int = 0,
              bigendian: bool = False):
    """``sensor_msgs/Image`` of an RGB (or grey/16-bit for mono*) array in ``encoding``."""
    a = rgb
    if encoding == "bgr8":
        a = rgb[:, :, ::-1]
    elif encoding == "rgba8":
        a = np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 7, np.uint8)], axis=2)
    elif encoding == "bgra8":
        a = np.concatenate([rgb[:, :, ::-1], np.full(rgb.shape[:2] + (1,), 7, np.uint8)], axis=2)
    elif encoding in ("mono8", "mono16"):
        a = rgb if rgb.ndim == 2 else rgb[:, :, 1]
        if encoding == "mono16":
            a = a.astype(">u2" if bigendian else "<u2")
    h, w = a.shape[:2]
    rows = np.ascontiguousarray(a).view(np.uint8).reshape(h, -1)
    if pad:
        rows = np.concatenate([rows, np.zeros((h, pad), np.uint8)], axis=1)
    return ts.types["sensor_msgs/msg/Image"](
        header=_header(ts, stamp_ns, ros1), height=h, width=w, encoding=encoding, is_bigendian=int(bigendian),
        step=rows.shape[1], data=np.ascontiguousarray(rows).reshape(-1))


def compressed_msg(ts, data: bytes, fmt: str, stamp_ns: int, ros1: bool = False):
    return ts.types["sensor_msgs/msg/CompressedImage"](
        header=_header(ts, stamp_ns, ros1), format=fmt, data=np.frombuffer(data, np.uint8).copy())


def _header(ts, stamp_ns: int, ros1: bool):
    stamp = ts.types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    if ros1:
        return ts.types["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id="cam")
    return ts.types["std_msgs/msg/Header"](stamp=stamp, frame_id="cam")


def write_bag(path: Path, topics: dict[str, Sequence[tuple[int, str, object]]], storage: str = "sqlite3") -> Path:
    """Write a bag: ``topics`` maps a topic to ``(stamp_ns, kind, payload)`` messages, where
    ``kind`` is an Image encoding (payload an RGB array), ``"jpeg"``/``"png"`` (payload the
    encoded bytes), or ``"string"`` (a std_msgs/String, payload text). ``storage``:
    ``sqlite3`` or ``mcap`` (rosbag2 folder ``path``), ``ros1`` (``path`` a ``.bag`` file)."""
    ros1 = storage == "ros1"
    ts = _store(ros1)
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer = Writer(path, version=9, storage_plugin=plugin)
    with writer:
        for topic, msgs in topics.items():
            kinds = {k for _, k, _ in msgs}
            msgtype = ("std_msgs/msg/String" if kinds == {"string"} else
                       "sensor_msgs/msg/CompressedImage" if kinds <= {"jpeg", "png"} else "sensor_msgs/msg/Image")
            conn = writer.add_connection(topic, msgtype, typestore=ts)
            for t, (stamp, kind, payload) in enumerate(msgs):
                if kind == "string":
                    msg = ts.types["std_msgs/msg/String"](data=str(payload))
                elif kind in ("jpeg", "png"):
                    msg = compressed_msg(ts, payload, kind, stamp, ros1)  # type: ignore[arg-type]
                else:
                    msg = image_msg(ts, payload, kind, stamp, ros1)  # type: ignore[arg-type]
                raw = ts.serialize_ros1(msg, msgtype) if ros1 else ts.serialize_cdr(msg, msgtype)
                # log time = stamp + a small offset: the bag's order is the stamps' order
                writer.write(conn, stamp + 1000 + t, raw)
    return path


def encode(rgb: np.ndarray, ext: str = ".png") -> bytes:
    ok, buf = cv2.imencode(ext, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert ok
    return buf.tobytes()
