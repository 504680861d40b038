"""ROS bags as sources: rosbag2 (sqlite3, MCAP) and ROS 1 bags written here with rosbags itself;
Image encodings and CompressedImage; topic choice; records equal the folder run's."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")

from bags import encode, write_bag

from torchrow.apps.cli import main
from torchrow.apps.commands.shared import annotation_names
from torchrow.core.rosbag import BagError, is_bag, open_bag
from torchrow.evaluation.synthetic import FieldSpec, render, sequence

STORAGES = ("sqlite3", "mcap", "ros1")
T0 = 1_700_000_000_123_456_789


def _bag_path(tmp_path: Path, storage: str, stem: str = "b") -> Path:
    return tmp_path / (f"{stem}.bag" if storage == "ros1" else f"{stem}_{storage}")


def _records(path: Path) -> list[dict]:
    return [json.loads(s) for s in path.read_text().splitlines()]


@pytest.mark.parametrize("storage", STORAGES)
def test_image_encodings_decode_to_the_same_rgb(tmp_path: Path, storage: str) -> None:
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (7, 9, 3), dtype=np.uint8)
    grey16 = (rgb[:, :, 1].astype(np.uint16) * 257 + rng.integers(-128, 128, rgb.shape[:2])).astype(np.uint16)
    msgs = [(T0 + i, enc, rgb) for i, enc in enumerate(("rgb8", "bgr8", "rgba8", "bgra8", "mono8"))]
    msgs.append((T0 + 5, "mono16", grey16))
    path = write_bag(_bag_path(tmp_path, storage), {"/cam": msgs, "/log": [(T0, "string", "hi")]}, storage)
    assert is_bag(path)
    src = open_bag(path)  # the only image topic
    assert src.topic == "/cam" and src.length == 6
    frames = list(src)
    assert [n for n, _ in frames] == [f"{i:06d}" for i in range(6)]
    assert [f.stamp_ns for _, f in frames] == [T0 + i for i in range(6)]
    for _, f in frames[:4]:
        np.testing.assert_array_equal(f(), rgb)
    np.testing.assert_array_equal(frames[4][1](), np.repeat(rgb[:, :, 1:2], 3, axis=2))
    want16 = ((grey16.astype(np.uint32) + 128) // 257).astype(np.uint8)  # the README's 16-bit rule
    np.testing.assert_array_equal(frames[5][1](), np.repeat(want16[:, :, None], 3, axis=2))


def test_padded_rows_big_endian_and_bad_encodings(tmp_path: Path) -> None:
    from bags import image_msg
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    rgb = np.arange(5 * 4 * 3, dtype=np.uint8).reshape(5, 4, 3)
    g16 = (np.arange(20, dtype=np.uint16).reshape(5, 4) * 3000).astype(np.uint16)
    msgs = [image_msg(ts, rgb, "rgb8", 1, pad=5), image_msg(ts, g16, "mono16", 2, bigendian=True),
            image_msg(ts, rgb, "rgb8", 3), image_msg(ts, rgb, "rgb8", 4)]
    msgs[2].encoding = "bayer_rggb8"
    msgs[3].data = msgs[3].data[:10]  # shorter than height * step
    path = tmp_path / "odd"
    with Writer(path, version=9) as w:
        conn = w.add_connection("/cam", "sensor_msgs/msg/Image", typestore=ts)
        for k, m in enumerate(msgs):
            w.write(conn, k + 1, ts.serialize_cdr(m, "sensor_msgs/msg/Image"))
    frames = [f for _, f in open_bag(path)]
    np.testing.assert_array_equal(frames[0](), rgb)
    np.testing.assert_array_equal(frames[1]()[:, :, 0], ((g16.astype(np.uint32) + 128) // 257).astype(np.uint8))
    with pytest.raises(BagError.__mro__[1], match="unsupported Image encoding 'bayer_rggb8'"):
        frames[2]()
    with pytest.raises(BagError.__mro__[1], match="needs"):
        frames[3]()


def test_topic_choice_and_one_line_errors(tmp_path: Path, capsys) -> None:
    img = render(FieldSpec(seed=1, width=64, height=48)).image
    two = write_bag(tmp_path / "two", {"/a": [(1, "png", encode(img))], "/b": [(1, "rgb8", img)]})
    none = write_bag(tmp_path / "none", {"/log": [(1, "string", "x")]})
    out = tmp_path / "r.jsonl"
    for argv, msg in (
            (["video", str(two)], "several image topics; choose one with --topic"),
            (["video", str(none)], "no image topic"),
            (["video", str(two), "--topic", "/c"], "topic '/c' is not an image topic"),
            (["detect", str(two)], "several image topics"),
            (["detect", str(tmp_path), "--topic", "/a"], "--topic applies to ROS bag inputs only")):
        capsys.readouterr()
        assert main([*argv, "--out", str(out), "-q"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("torchrow: error: ") and "\n" not in err and msg in err, err
    capsys.readouterr()
    assert main(["video", str(two), "--out", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert "/a (CompressedImage, 1 messages), /b (Image, 1 messages)" in err


@pytest.mark.parametrize("storage", STORAGES)
def test_detect_on_a_bag_equals_detect_on_the_folder(tmp_path: Path, storage: str) -> None:
    folder = tmp_path / "imgs"
    folder.mkdir()
    imgs = [render(FieldSpec(seed=s)).image for s in range(3)]
    msgs = []
    for k, im in enumerate(imgs):
        data = encode(im, ".png")
        (folder / f"{k}.png").write_bytes(data)
        msgs.append((T0 + k * 10**8, "png" if k != 1 else "rgb8", data if k != 1 else im))
    msgs.append((T0 + 10**9, "jpeg", b"garbage, not a jpeg"))  # a frame that does not decode
    if storage != "ros1":
        # a bag with one message type per topic: raw frames go to their own topic
        raw = [m for m in msgs if m[1] == "rgb8"]
        comp = [m for m in msgs if m[1] != "rgb8"]
        bag = write_bag(_bag_path(tmp_path, storage), {"/c": comp, "/r": raw}, storage)
        topic_runs = [("/c", [0, 2, None]), ("/r", [1])]
    else:
        bag = write_bag(_bag_path(tmp_path, storage), {"/c": [m for m in msgs if m[1] != "rgb8"]}, storage)
        topic_runs = [("/c", [0, 2, None])]
    want = _detect(folder, tmp_path / "folder.jsonl")
    for topic, which in topic_runs:
        got = _detect(bag, tmp_path / "bag.jsonl", "--topic", topic)
        assert len(got) == len(which)
        for j, (rec, k) in enumerate(zip(got, which)):
            assert rec["name"] == f"{bag.name}#{j:06d}" and rec["frame"] == j and rec["source"] == str(bag)
            stamp = [m[0] for m in msgs if (m[1] == "rgb8") == (topic == "/r")][j]
            assert rec["stamp_ns"] == stamp
            if k is None:
                assert rec["status"] == "error" and "cannot decode image" in rec["error"]
                continue
            strip = {key: v for key, v in rec.items() if key not in ("name", "source", "frame", "stamp_ns")}
            assert strip == {key: v for key, v in want[k].items() if key != "name"}


def _detect(inp: Path, out: Path, *extra: str) -> list[dict]:
    assert main(["detect", str(inp), "--out", str(out), "-q", *extra]) == 0
    return _records(out)


def _video(inp: Path, out: Path, *extra: str) -> list[dict]:
    assert main(["video", str(inp), "--out", str(out), "-q", "--plot", "none", *extra]) == 0
    return _records(out)


def _same_frames(bag_recs: list[dict], folder_recs: list[dict], stamps: list[int], bag: Path) -> None:
    assert len(bag_recs) == len(folder_recs) == len(stamps)
    for t, (b, f) in enumerate(zip(bag_recs, folder_recs)):
        assert list(b)[:3] == ["source", "frame", "stamp_ns"]  # stamp_ns beside frame
        assert b["source"] == str(bag) and b["frame"] == t and b["stamp_ns"] == stamps[t]
        assert b["name"] == f"{t:06d}"
        drop = ("source", "stamp_ns", "name")
        assert {k: v for k, v in b.items() if k not in drop} == {k: v for k, v in f.items() if k not in drop}


def test_video_on_synthetic_bags_equals_the_folder(tmp_path: Path) -> None:
    frames = [f.image for f in sequence(FieldSpec(seed=4, width=200, height=120), 7, drift_px_per_frame=1.5)]
    folder = tmp_path / "seq"
    folder.mkdir()
    stamps = [T0 + t * 33_333_333 for t in range(len(frames))]
    for t, im in enumerate(frames):
        (folder / f"{t:03d}.png").write_bytes(encode(im, ".png"))
    # the same implementation on both sides: records equal exactly (tensor vs reference agree
    # only to 1e-6 px, test_tracker.py)
    want = {impl: _video(folder, tmp_path / "f.jsonl", "--param", "video_width=200", "--impl", impl)
            for impl in ("tensor", "reference")}
    for storage, kind in (("mcap", "rgb8"), ("ros1", "bgr8"), ("sqlite3", "png")):
        msgs = [(s, kind, encode(im, ".png") if kind == "png" else im) for s, im in zip(stamps, frames)]
        bag = write_bag(_bag_path(tmp_path, storage), {"/camera/image": msgs}, storage)
        for impl in ("tensor", "reference"):
            got = _video(bag, tmp_path / "b.jsonl", "--param", "video_width=200", "--impl", impl)
            _same_frames(got, want[impl], stamps, bag)


@pytest.mark.data
@pytest.mark.parametrize(("storage", "n"), [("sqlite3", 20), ("mcap", 20),
                                       pytest.param("mcap", 100, marks=pytest.mark.heavy)])
def test_caterra_compressed_bag_equals_the_folder_frame_by_frame(data_dir: Path, tmp_path: Path,
                                                                  storage: str, n: int) -> None:
    """All 100 frames (-m heavy, about 2 min here) were run once: identical."""
    src = data_dir / "caterra_video"
    files = sorted(src.glob("rgb*.jpg"))
    if not files:
        pytest.skip(f"caterra_video not found under {data_dir}")
    files = files[:n]
    folder = tmp_path / "frames"
    folder.mkdir()
    for f in files:
        shutil.copy(f, folder / f.name)
    stamps = [T0 + t * 66_666_667 for t in range(len(files))]
    bag = write_bag(_bag_path(tmp_path, storage, "caterra"),
                    {"/camera/color/image_raw/compressed": [(s, "jpeg", f.read_bytes()) for s, f in zip(stamps, files)]},
                    storage)
    want = _video(folder, tmp_path / "folder.jsonl")
    got = _video(bag, tmp_path / "bag.jsonl")
    _same_frames(got, want, stamps, bag)
    assert sum(r["hough_ran"] for r in got) >= 4


# --- hostile bags: bounds, names, damage, odd first frames, stated counts, mixed topics --------

SMALL = ["--param", "image_width=64", "-q"]


def _flat(n: int, seed: int = 0, size: tuple[int, int] = (48, 64)) -> list[np.ndarray]:
    """``n`` one-colour images, each of its own colour (cheap to detect on, distinct bytes)."""
    return [np.full((*size, 3), (40 * seed + 10 * k + 5) % 256, np.uint8) for k in range(n)]


def test_bag_frames_get_the_max_pixels_bound_before_decoding(tmp_path: Path, monkeypatch) -> None:
    """Issue 26.1: a 1x5000 mono8 Image was resized to 320x1,600,000 (4.9 GB) and a 2x8000 PNG
    decoded and resized (4.0 GB); as files the same pixels were an error record at once."""
    from torchrow.core.rosbag import BagFrame

    ok = _flat(1)[0]
    msgs = [(T0, "rgb8", ok), (T0 + 1, "mono8", np.zeros((400, 4), np.uint8)), (T0 + 2, "rgb8", ok)]
    raw = write_bag(tmp_path / "raw", {"/cam": msgs})
    comp = write_bag(tmp_path / "comp", {"/cam": [(T0, "png", encode(ok)), (T0 + 1, "png", encode(_flat(1, 1, (800, 2))[0])),
                                                  (T0 + 2, "png", encode(ok))]})
    for bag in (raw, comp):
        recs = _detect(bag, tmp_path / f"{bag.name}.jsonl", *SMALL, "--param", "max_pixels=100000")
        assert [r["frame"] for r in recs] == [0, 1, 2]
        assert recs[0]["status"] != "error" and recs[2]["status"] != "error"
        assert recs[1]["status"] == "error" and "working size 64x" in recs[1]["error"] and "max_pixels" in recs[1]["error"]
    # the bound holds on the message's own sizes, before anything is decoded or resized: an
    # Image's fields (nothing of 320 x 320,000,000 is allocated), a CompressedImage's header
    tall = BagFrame(T0, 0, "tall", False, bytes(10**6), "mono8", 10**6, 1, 1, width=320, max_pixels=2**19)
    with pytest.raises(BagError.__mro__[1], match="working size 320x320000000"):
        tall()
    flat = BagFrame(T0, 0, "flat", True, encode(_flat(1, size=(8000, 2))[0]), width=320, max_pixels=2**19)
    monkeypatch.setattr("cv2.imdecode", lambda *a: pytest.fail("decoded before the bound was checked"))
    with pytest.raises(BagError.__mro__[1], match="working size 320x1280000"):
        flat()


def test_bags_of_one_file_name_in_two_folders_keep_apart(tmp_path: Path) -> None:
    """Issue 26.2: dayA/cam.bag and dayB/cam.bag got the same record names; --resume after the
    first bag lost dayB and --annotate wrote 4 pictures for 8 records; a bag named twice gave
    every frame twice."""
    for d in ("dayA", "dayB"):
        (tmp_path / d).mkdir()
    bags = [write_bag(tmp_path / d / "cam.bag", {"/cam": [(T0 + k, "png", encode(im)) for k, im in enumerate(_flat(2, s))]},
                      "ros1") for s, d in enumerate(("dayA", "dayB"))]
    out, ann = tmp_path / "r.jsonl", tmp_path / "ann"
    argv = ["detect", str(bags[0]), str(bags[1]), str(tmp_path / "dayA" / ".." / "dayA" / "cam.bag"),
            "--out", str(out), *SMALL]
    assert main([*argv, "--annotate", str(ann)]) == 0
    recs = _records(out)
    assert [r["name"] for r in recs] == ["dayA/cam.bag#000000", "dayA/cam.bag#000001",
                                         "dayB/cam.bag#000000", "dayB/cam.bag#000001"]
    assert sorted(p.relative_to(ann).as_posix() for p in ann.rglob("*.png")) == [
        "dayA/cam.bag_000000.png", "dayA/cam.bag_000001.png", "dayB/cam.bag_000000.png", "dayB/cam.bag_000001.png"]
    lines = out.read_text().splitlines(keepends=True)
    out.write_text("".join(lines[:2]))  # a run stopped after the first bag
    assert main([*argv, "--resume"]) == 0
    assert _records(out) == recs
    one = _detect(bags[0], tmp_path / "one.jsonl", *SMALL)  # one bag: named by its file name, as before
    assert [r["name"] for r in one] == ["cam.bag#000000", "cam.bag#000001"]
    # an image file whose picture would be a bag frame's keeps its whole name
    assert annotation_names(["cam.bag_000001.jpg", "x.jpg"], ["cam.bag"]) == ["cam.bag_000001.jpg.png", "x.png"]


def _damage(bag: Path, storage: str, payload: bytes, log_time: int) -> None:
    """Damage one message of a bag so that its reader fails on it (sqlite3: an overflow page's
    pointer; ROS 1: the record header) or skips it without a word (MCAP: the record's opcode)."""
    f = bag if storage == "ros1" else next(bag.glob("*.db3" if storage == "sqlite3" else "*.mcap"))
    b = bytearray(f.read_bytes())
    if storage == "mcap":
        pos = b.index(log_time.to_bytes(8, "little") * 2) - 15  # opcode, length, channel, sequence
        assert b[pos] == 0x05
        b[pos] = 0x7F
    elif storage == "ros1":
        pos = b.index(payload)
        b[pos - 60:pos] = b"\xa5" * 60
    else:
        pos = b.index(payload[len(payload) // 2:len(payload) // 2 + 32])
        page = int.from_bytes(b[16:18], "big")
        b[pos - pos % page:pos - pos % page + 4] = b"\xff" * 4
    f.write_bytes(bytes(b))


@pytest.mark.parametrize("storage", STORAGES)
def test_damage_in_the_middle_of_a_bag_loses_only_the_damaged_message(tmp_path: Path, storage: str) -> None:
    """Issue 26.3: sqlite3 and ROS 1 ended in a traceback with 0 records; MCAP skipped the
    damaged message without a word and renumbered the later frames."""
    imgs = _flat(5, size=(60, 80))  # raw Images: each message spans several sqlite3 pages
    bag = write_bag(_bag_path(tmp_path, storage), {"/cam": [(T0 + k, "rgb8", im) for k, im in enumerate(imgs)]}, storage)
    _damage(bag, storage, imgs[2].tobytes(), T0 + 2 + 1000 + 2)  # write_bag's log time of message 2
    recs = _detect(bag, tmp_path / "r.jsonl", *SMALL)
    assert [r["frame"] for r in recs] == [0, 1, 2, 3, 4]
    assert [r["stamp_ns"] for r in recs] == [T0, T0 + 1, None, T0 + 3, T0 + 4]
    assert [r["status"] == "error" for r in recs] == [False, False, True, False, False]
    assert f"{bag.name}:/cam#2" in recs[2]["error"]


def test_odd_first_frame_of_a_bag_follows_the_majority_rule(tmp_path: Path) -> None:
    """Issue 26.4: 10 of 11 frames were errors; from a folder, 1 error and 10 records."""
    frames = [f.image for f in sequence(FieldSpec(seed=4, width=120, height=72), 3)]
    odd = render(FieldSpec(seed=5, width=96, height=72)).image
    bag = write_bag(tmp_path / "odd", {"/cam": [(T0 + t, "rgb8", im) for t, im in enumerate([odd, *frames])]})
    assert open_bag(bag).working_size(120) == (72, 120)
    recs = _video(bag, tmp_path / "v.jsonl", "--param", "video_width=120", "-q")
    assert [r["status"] == "error" for r in recs] == [True, False, False, False]
    assert "working size 120x90" in recs[0]["error"]


def test_resume_does_not_trust_the_stated_message_count(tmp_path: Path) -> None:
    """Issue 26.12: `video --resume` built set(range(message_count)) from metadata.yaml and, the
    count inflated, died with MemoryError."""
    import re

    bag = write_bag(tmp_path / "big", {"/cam": [(T0 + t, "rgb8", im) for t, im in enumerate(_flat(2))]})
    out = tmp_path / "v.jsonl"
    recs = _video(bag, out, "--param", "video_width=64")
    meta = bag / "metadata.yaml"
    meta.write_text(re.sub(r"message_count: \d+", "message_count: 1000000000000", meta.read_text()))
    assert open_bag(bag).length == 2  # the count by the bag's index
    assert _video(bag, out, "--param", "video_width=64", "--resume") == recs


@pytest.mark.parametrize("storage", STORAGES)
def test_a_topic_of_image_and_compressed_image_messages(tmp_path: Path, storage: str) -> None:
    """Issue 26.18: a topic carrying both types was reported as "no image topic"."""
    from bags import _store, compressed_msg, image_msg

    rgb = _flat(1, size=(6, 8))[0]
    ros1 = storage == "ros1"
    ts = _store(ros1)
    path = _bag_path(tmp_path, storage)
    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        writer = Writer1(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3)
    kinds = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
    with writer:
        conns = [writer.add_connection("/cam", k, typestore=ts) for k in kinds]
        for t in range(4):
            msg = compressed_msg(ts, encode(rgb), "png", T0 + t, ros1) if t % 2 else image_msg(ts, rgb, "rgb8", T0 + t, ros1)
            raw = ts.serialize_ros1(msg, kinds[t % 2]) if ros1 else ts.serialize_cdr(msg, kinds[t % 2])
            writer.write(conns[t % 2], T0 + t, raw)
    src = open_bag(path)
    frames = [f for _, f in src]
    assert src.length == 4 and [f.compressed for f in frames] == [False, True, False, True]
    for f in frames:
        np.testing.assert_array_equal(f(), rgb)
