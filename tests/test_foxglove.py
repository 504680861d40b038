"""Foxglove outputs (torchrow.apps.foxglove): MCAP recordings of ``video``/``detect`` read back
with the ``mcap`` reader, the live view of ``video --serve`` read by a WebSocket client, and
the one-line refusals."""

from __future__ import annotations

import base64
import json
import os
import shutil
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("foxglove")
pytest.importorskip("mcap")
pytest.importorskip("google.protobuf")

from bags import encode

from torchrow.apps.annotate import HORIZON, VALID, row_top
from torchrow.apps.cli import main
from torchrow.apps.foxglove import POLYLINE_POINTS, read_mcap, topic_prefixes
from torchrow.core.results import ImageResult
from torchrow.evaluation.synthetic import FieldSpec, sequence

T0 = 1_700_000_000_123_456_789
REPO = Path(__file__).resolve().parents[1]
_CLASSES: dict[tuple[str, bytes], type] = {}


def _decode(schema: str, schema_data: bytes, data: bytes):
    """A protobuf message of a well-known Foxglove schema, from the schema's descriptor set."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    key = (schema, schema_data)
    if key not in _CLASSES:
        pool = descriptor_pool.DescriptorPool()
        for fd in descriptor_pb2.FileDescriptorSet.FromString(schema_data).file:
            pool.Add(fd)
        _CLASSES[key] = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema))
    return _CLASSES[key].FromString(data)


def _read(path: Path) -> tuple[dict, dict[str, list]]:
    """``({topic: schema name}, {topic: [(log_time, decoded message)]})`` of a whole MCAP."""
    from mcap.reader import make_reader

    schemas: dict[str, str] = {}
    msgs: dict[str, list] = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.chunk_count >= 1
        for schema, channel, msg in reader.iter_messages():
            schemas[channel.topic] = schema.name
            value = (json.loads(msg.data) if schema.encoding == "jsonschema"
                     else _decode(schema.name, schema.data, msg.data))
            msgs.setdefault(channel.topic, []).append((msg.log_time, value))
    return schemas, msgs


def _records(path: Path) -> list[dict]:
    return [json.loads(s) for s in path.read_text().splitlines()]


def _check_annotations(ann, rec: dict, image_size: tuple[int, int]) -> None:
    """Every polyline is the record's row sampled at the stated working rows, scaled by the
    stated factors into the published image's pixels (corner origin: ``(x + 0.5) * s``)."""
    meta = {kv.key: kv.value for kv in ann.metadata}
    sx, sy = float(meta["scale_x"]), float(meta["scale_y"])
    w, h = rec["width"], rec["height"]
    assert (sx, sy) == (image_size[0] / w, image_size[1] / h)
    res = ImageResult.from_record(rec)
    assert float(meta["y_top"]) == row_top(res, h) and float(meta["y_bottom"]) == h - 1
    ys = np.linspace(float(meta["y_top"]), float(meta["y_bottom"]), int(meta["samples"]))
    assert ys.size == POLYLINE_POINTS
    rows = [r for r in res.rows if np.isfinite(r.a) and np.isfinite(r.b)]
    lines = list(ann.points)
    assert len(lines) == len(rows) + (res.sky > 0)
    for row, line in zip(rows, lines):
        got = np.array([[p.x, p.y] for p in line.points])
        want = np.stack([(np.asarray(row.x_at(ys)) + 0.5) * sx, (ys + 0.5) * sy], 1)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
        if row.valid:
            c = line.outline_color
            assert (round(c.r * 255), round(c.g * 255), round(c.b * 255)) == VALID
    if res.sky > 0:
        c = lines[-1].outline_color
        assert (round(c.r * 255), round(c.g * 255), round(c.b * 255)) == HORIZON
        assert {p.y for p in lines[-1].points} == {res.sky * sy}
    if res.vp is not None:
        (circle,) = ann.circles
        assert (circle.position.x, circle.position.y) == ((res.vp[0] + 0.5) * sx, (res.vp[1] + 0.5) * sy)


def _check_recording(mcap: Path, recs: list[dict], prefix: str, images: list[bytes | None]) -> None:
    """One message per frame per topic, log times = the records' ``stamp_ns``, JPEG frames
    passed through byte for byte (``None``: an encoded working image), polylines as stated."""
    schemas, msgs = _read(mcap)
    assert {t: schemas[t] for t in schemas if t.startswith(prefix + "/")} == {
        f"{prefix}/image": "foxglove.CompressedImage", f"{prefix}/annotations": "foxglove.ImageAnnotations",
        f"{prefix}/signals": "torchrow.RowSignals"}
    stamps = [r["stamp_ns"] for r in recs]
    for topic in ("image", "annotations", "signals"):
        assert [t for t, _ in msgs[f"{prefix}/{topic}"]] == stamps
    for rec, (_, img), (_, ann), (_, sig), want in zip(recs, msgs[f"{prefix}/image"], msgs[f"{prefix}/annotations"],
                                                       msgs[f"{prefix}/signals"], images):
        assert img.format == "jpeg" and img.timestamp.seconds * 10**9 + img.timestamp.nanos == rec["stamp_ns"]
        import cv2

        pic = cv2.imdecode(np.frombuffer(img.data, np.uint8), cv2.IMREAD_COLOR)
        if want is not None:
            assert img.data == want
        else:
            assert pic.shape[:2] == (rec["height"], rec["width"])
        _check_annotations(ann, rec, (pic.shape[1], pic.shape[0]))
        assert sig["status"] == rec["status"] and sig["timestamp"] == {"sec": rec["stamp_ns"] // 10**9,
                                                                        "nsec": rec["stamp_ns"] % 10**9}
        for key in ("lateral_px", "heading_px", "confidence", "heading_rad"):
            assert sig[key] == rec.get(key)
        assert sig["lateral_m"] is None and sig["state"] is None  # not in these records


@pytest.mark.data
def test_video_mcap_of_caterra_frames(data_dir: Path, tmp_path: Path) -> None:
    files = sorted((data_dir / "caterra_video").glob("rgb*.jpg"))[:5]
    if len(files) < 5:
        pytest.skip("caterra_video not found")
    folder = tmp_path / "frames"
    folder.mkdir()
    for f in files:
        shutil.copy(f, folder / f.name)
    out, mcap = tmp_path / "v.jsonl", tmp_path / "v.mcap"
    # working size 250x140 of 1280x720 frames: rows scaled by 5.12 across and 720/140 down
    assert main(["video", str(folder), "--out", str(out), "--mcap", str(mcap), "--plot", "none", "-q",
                 "--param", "video_width=250"]) == 0
    recs = _records(out)
    # a folder has no frame rate: 10 fps, the annotated video's default
    assert [r["stamp_ns"] for r in recs] == [t * 100_000_000 for t in range(5)]
    assert [list(r)[:3] for r in recs] == [["source", "frame", "stamp_ns"]] * 5
    _check_recording(mcap, recs, "/torchrow", [f.read_bytes() for f in files])
    recording = read_mcap(mcap)
    assert recording.whole and len(recording.messages) == 15


def test_video_and_detect_mcap_of_a_ros2_bag(tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    from bags import write_bag

    frames = [f.image for f in sequence(FieldSpec(seed=4, width=320, height=240), 4, drift_px_per_frame=2.0)]
    jpegs = [encode(im, ".jpg") for im in frames]
    stamps = [T0 + t * 33_333_333 for t in range(len(frames))]
    bag = write_bag(tmp_path / "bag", {"/camera/image/compressed": [(s, "jpeg", j) for s, j in zip(stamps, jpegs)]},
                    "sqlite3")
    out, mcap = tmp_path / "v.jsonl", tmp_path / "v.mcap"
    assert main(["video", str(bag), "--out", str(out), "--mcap", str(mcap), "--plot", "none", "-q",
                 "--param", "video_width=160"]) == 0
    recs = _records(out)
    assert [r["stamp_ns"] for r in recs] == stamps  # the bag's header stamps
    assert sum(len(r["rows"]) for r in recs) > 0
    _check_recording(mcap, recs, "/torchrow", jpegs)  # 320x240 JPEGs over 160x120 rows: scale 2

    # detect: the image files (PNG: encoded once, working size) and the bag are two sequences
    folder = tmp_path / "pngs"
    folder.mkdir()
    for t, im in enumerate(frames[:2]):
        (folder / f"{t}.png").write_bytes(encode(im, ".png"))
    out, mcap = tmp_path / "d.jsonl", tmp_path / "d.mcap"
    # (the reference: the recording does not depend on the implementation, and it starts faster)
    assert main(["detect", str(folder), str(bag), "--out", str(out), "--mcap", str(mcap), "-q",
                 "--impl", "reference"]) == 0
    recs = _records(out)
    files, frames_of_bag = recs[:2], recs[2:]
    assert [list(r)[:2] for r in files] == [["name", "stamp_ns"]] * 2
    assert [r["stamp_ns"] for r in files] == [0, 100_000_000]
    assert [r["stamp_ns"] for r in frames_of_bag] == stamps
    p_files, p_bag = topic_prefixes(["images", "bag"])
    _check_recording(mcap, files, p_files, [None, None])
    _check_recording(mcap, frames_of_bag, p_bag, jpegs)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_serve_streams_every_frame_to_a_websocket_client(tmp_path: Path) -> None:
    from websockets.sync.client import connect

    folder = tmp_path / "seq"
    folder.mkdir()
    for t, f in enumerate(sequence(FieldSpec(seed=2, width=160, height=120), 3, drift_px_per_frame=1.0)):
        (folder / f"{t}.png").write_bytes(encode(f.image, ".png"))
    out, port = tmp_path / "s.jsonl", _free_port()
    rc: list[int] = []
    run = threading.Thread(target=lambda: rc.append(main(
        ["video", str(folder), "--out", str(out), "--serve", f"127.0.0.1:{port}", "--serve-wait", "20",
         "--fps", "20", "--plot", "none", "-q", "--param", "video_width=160"])), daemon=True)
    run.start()
    deadline = time.monotonic() + 30
    while True:
        try:
            ws = connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],
                         open_timeout=5)
            break
        except OSError:
            assert time.monotonic() < deadline and run.is_alive(), "the server did not start"
            time.sleep(0.1)
    got: dict[str, list[tuple[int, bytes]]] = {}
    with ws:
        channels: dict[int, dict] = {}
        while len(channels) < 3:
            msg = ws.recv(timeout=10)
            if isinstance(msg, str) and json.loads(msg)["op"] == "advertise":
                channels.update({c["id"]: c for c in json.loads(msg)["channels"]})
        ids = sorted(channels)
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": k, "channelId": c} for k, c in enumerate(ids)]}))
        while sum(len(v) for v in got.values()) < 9:
            msg = ws.recv(timeout=10)
            if isinstance(msg, bytes) and msg[0] == 1:  # message data: subscription, log time, payload
                sub, log_time = struct.unpack_from("<IQ", msg, 1)
                got.setdefault(channels[ids[sub]]["topic"], []).append((log_time, msg[13:]))
    run.join(30)
    assert rc == [0]
    recs = _records(out)
    stamps = [r["stamp_ns"] for r in recs]
    assert stamps == [0, 50_000_000, 100_000_000]  # --fps 20
    assert {t: [lt for lt, _ in v] for t, v in got.items()} == {
        f"/torchrow/{k}": stamps for k in ("image", "annotations", "signals")}
    ann_ch = next(c for c in channels.values() if c["topic"] == "/torchrow/annotations")
    assert ann_ch["schemaName"] == "foxglove.ImageAnnotations"
    for rec, (_, payload) in zip(recs, got["/torchrow/annotations"]):
        ann = _decode(ann_ch["schemaName"], base64.b64decode(ann_ch["schema"]), payload)
        _check_annotations(ann, rec, (rec["width"], rec["height"]))  # encoded working image: scale 1


def test_missing_sdk_and_refusals(tmp_path: Path, capsys, monkeypatch) -> None:
    folder = tmp_path / "seq"
    folder.mkdir()
    (folder / "0.png").write_bytes(encode(np.zeros((8, 8, 3), np.uint8), ".png"))
    out = str(tmp_path / "o.jsonl")
    cases = [
        (["video", str(folder), "--out", out, "--mcap", str(folder / "x.mcap")], "inside the input folder"),
        (["video", str(folder), "--out", out, "--mcap", str(tmp_path / "m.mcap"), "--resume"], "--resume cannot"),
        (["video", str(folder), "--out", out, "--mcap", out], "--out and --mcap are the same file"),
        (["video", str(folder), "--out", out, "--serve", "localhost:http"], "--serve expects [HOST:]PORT"),
        (["video", str(folder), "--out", out, "--serve", "9999", "--serve-wait", "-1"], "--serve-wait must be >= 0"),
        (["detect", str(folder), "--out", out, "--mcap", str(tmp_path / "no" / "m.mcap")], "folder of --mcap"),
    ]
    for argv, what in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and err.startswith("torchrow: error:") and what in err, err
    assert not (tmp_path / "m.mcap").exists()
    monkeypatch.setitem(sys.modules, "foxglove", None)  # import foxglove raises ImportError
    for argv in (["video", str(folder), "--out", out, "--mcap", str(tmp_path / "m.mcap")],
                 ["detect", str(folder), "--out", out, "--mcap", str(tmp_path / "m.mcap")],
                 ["video", str(folder), "--out", out, "--serve", "8765"]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and err.endswith("pip install 'torchrow[foxglove]'"), err


_KILLED = """
import os, signal, sys
from pathlib import Path
from torchrow.apps.foxglove import Recorder
rec = {"name": "x", "status": "no_vp", "width": 8, "height": 6, "rows": [], "vp": None}
r = Recorder(["a"], [10.0], mcap=Path(sys.argv[1]))
for j in range(int(sys.argv[3])):
    r.frame(0, j, dict(rec), None, Path(sys.argv[2]))
os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_killed_recording_keeps_its_whole_chunks(tmp_path: Path) -> None:
    import cv2

    noise = np.random.default_rng(0).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    jpeg = tmp_path / "noise.jpg"
    cv2.imwrite(str(jpeg), noise, [cv2.IMWRITE_JPEG_QUALITY, 95])  # about 0.3 MB: a chunk per 3-4 frames
    mcap = tmp_path / "k.mcap"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", _KILLED, str(mcap), str(jpeg), "10"], env=env, timeout=60,
                          capture_output=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()
    recording = read_mcap(mcap)
    assert not recording.whole
    frames = [m for m in recording.messages if m.topic == "/torchrow/image"]
    assert 1 <= len(frames) < 10 and all(jpeg.read_bytes() in m.data for m in frames)
    assert [m.log_time for m in frames] == [j * 100_000_000 for j in range(len(frames))]


def test_layout_shows_the_published_topics() -> None:
    layout = json.loads((REPO / "docs" / "foxglove_layout.json").read_text())
    panels = layout["configById"]
    image = next(v for k, v in panels.items() if k.startswith("Image!"))
    assert image["imageMode"]["imageTopic"] == "/torchrow/image"
    assert image["imageMode"]["annotations"] == {"/torchrow/annotations": {"visible": True}}
    from torchrow.apps.foxglove import SIGNALS_SCHEMA

    plotted = [p["value"] for k, v in panels.items() if k.startswith("Plot!") for p in v["paths"]]
    assert {"/torchrow/signals.lateral_px", "/torchrow/signals.heading_px"} <= set(plotted)
    assert all(p.split(".", 1)[1] in SIGNALS_SCHEMA["properties"] for p in plotted)
