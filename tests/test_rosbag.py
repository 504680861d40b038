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
