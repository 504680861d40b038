"""Nothing lost, nothing overwritten (issue 11, reproducers 1-3 and 11): output targets that are
inputs, annotated and record names, video files with a corrupt frame, odd first frames,
``--plot`` formats, ``score`` without results."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from torchrow.apps.cli import main
from torchrow.apps.commands.shared import annotation_names, record_names
from torchrow.apps.sink import bytes_safe
from torchrow.evaluation.synthetic import FieldSpec, render

SMALL = ["--param", "video_width=160"]


def _write(path: Path, seed: int = 1, size: tuple[int, int] = (320, 240)) -> bytes:
    img = render(FieldSpec(seed=seed, width=size[0], height=size[1])).image
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    return path.read_bytes()


def _records(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _one_line_error(capsys, *words: str) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("torchrow: error: ") and "\n" not in err, err
    for w in words:
        assert w in err, err
    return err


def test_out_that_is_the_input_is_refused(tmp_path: Path, capsys) -> None:
    """Reproducer 1: `detect a.jpg --out a.jpg` replaced the image by a JSON line."""
    a = tmp_path / "a.jpg"
    data = _write(a)
    assert main(["detect", str(a), "--out", str(a), "-q"]) == 2
    _one_line_error(capsys, "--out", "is an input")
    assert a.read_bytes() == data
    # another spelling, and a hard link, of the same file
    assert main(["detect", str(a), "--out", str(tmp_path / "." / "a.jpg"), "-q"]) == 2
    os.link(a, tmp_path / "link.jpg")
    assert main(["detect", str(a), "--out", str(tmp_path / "link.jpg"), "-q"]) == 2
    assert a.read_bytes() == data


def test_annotate_into_the_input_folder_is_refused(tmp_path: Path, capsys) -> None:
    """Reproducer 2: `detect imgs/b.png --out r.jsonl --annotate imgs` overwrote b.png."""
    b = tmp_path / "imgs" / "b.png"
    data = _write(b)
    out = tmp_path / "r.jsonl"
    assert main(["detect", str(b), "--out", str(out), "--annotate", str(b.parent), "-q"]) == 2
    _one_line_error(capsys, "--annotate", "is an input")
    assert b.read_bytes() == data and not out.exists()
    # a folder input: nothing may be written inside it (a second run would read it back)
    assert main(["detect", str(b.parent), "--out", str(out), "--annotate", str(b.parent / "ann"), "-q"]) == 2
    _one_line_error(capsys, "inside the input folder")
    assert main(["detect", str(b.parent), "--out", str(b.parent / "r.jsonl"), "-q"]) == 2
    assert sorted(p.name for p in b.parent.iterdir()) == ["b.png"]


def test_names_and_pictures_are_unique_per_input(tmp_path: Path) -> None:
    """Reproducer 2: s1/x.jpg, s1/x.png and s2/x.jpg gave one picture and three records `x.jpg`."""
    _write(tmp_path / "s1" / "x.jpg", 1)
    _write(tmp_path / "s1" / "x.png", 2)
    _write(tmp_path / "s2" / "x.jpg", 3)
    out, ann = tmp_path / "r.jsonl", tmp_path / "ann"
    assert main(["detect", str(tmp_path / "s1"), str(tmp_path / "s2"), "--out", str(out),
                 "--annotate", str(ann), "-q"]) == 0
    names = [r["name"] for r in _records(out)]
    assert names == ["s1/x.jpg", "s1/x.png", "s2/x.jpg"]
    pictures = sorted(p.relative_to(ann).as_posix() for p in ann.rglob("*.png"))
    assert pictures == ["s1/x.jpg.png", "s1/x.png.png", "s2/x.png"]
    # one folder, or one file: names are the file names, as before
    assert record_names([Path("d/a.jpg"), Path("d/b.jpg")]) == ["a.jpg", "b.jpg"]
    assert record_names([Path("d/a.jpg")]) == ["a.jpg"]
    assert annotation_names(["a.jpg", "b.JPG"]) == ["a.png", "b.png"]


def test_the_same_file_twice_is_one_input(tmp_path: Path) -> None:
    a = tmp_path / "d" / "a.jpg"
    _write(a)
    out = tmp_path / "r.jsonl"
    assert main(["detect", str(a.parent), str(a), "--out", str(out), "-q", "--impl", "reference"]) == 0
    assert [r["name"] for r in _records(out)] == ["a.jpg"]


def _corrupt_avi(path: Path, n: int = 12, bad: int = 6) -> None:
    """An MJPG .avi of ``n`` frames whose frame ``bad`` (0-based) has its JPEG data zeroed."""
    img = render(FieldSpec(seed=4, width=160, height=120)).image
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (160, 120))
    assert vw.isOpened()
    for i in range(n):
        vw.write(cv2.cvtColor(np.roll(img, 2 * i, axis=1), cv2.COLOR_RGB2BGR))
    vw.release()
    data = bytearray(path.read_bytes())
    soi = [i for i in range(len(data) - 1) if data[i] == 0xFF and data[i + 1] == 0xD8]
    assert len(soi) == n
    data[soi[bad]:soi[bad] + 600] = bytes(600)
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("impl", ["tensor", "reference"])
def test_video_with_a_corrupt_frame_is_read_to_its_end(tmp_path: Path, impl: str, capsys) -> None:
    """Reproducer 3: frame 7 of 12 corrupt gave "6 frame(s) (ok 6)": frames 8-12 were lost."""
    video = tmp_path / "v.avi"
    _corrupt_avi(video)
    cap = cv2.VideoCapture(str(video))
    reads = [cap.read()[0] for _ in range(12)]
    cap.release()
    assert reads == [True] * 6 + [False] + [True] * 5  # OpenCV goes on after the bad frame
    out = tmp_path / "r.jsonl"
    assert main(["video", str(video), "--out", str(out), "-q", "--impl", impl, *SMALL]) == 0
    recs = _records(out)
    assert [r["frame"] for r in recs] == list(range(12))
    assert recs[6]["status"] == "error" and "frame 6" in recs[6]["error"]
    assert all(r["status"] != "error" for i, r in enumerate(recs) if i != 6)
    assert "12 frame(s)" in capsys.readouterr().err


@pytest.mark.parametrize("impl", ["tensor", "reference"])
def test_odd_size_first_frame_does_not_spoil_the_sequence(tmp_path: Path, impl: str) -> None:
    """Reproducer 11: one odd-size first frame made every later frame an error."""
    d = tmp_path / "frames"
    _write(d / "f000.png", 1, (320, 320))  # square: another working size
    for i in range(1, 5):
        _write(d / f"f{i:03d}.png", i, (320, 180))
    out = tmp_path / "r.jsonl"
    assert main(["video", str(d), "--out", str(out), "-q", "--impl", impl, *SMALL]) == 0
    recs = _records(out)
    assert recs[0]["status"] == "error" and "working size 160x160" in recs[0]["error"]
    assert all(r["status"] != "error" for r in recs[1:])
    assert recs[1]["hough_ran"] and (recs[1]["width"], recs[1]["height"]) == (160, 90)


def test_video_targets_and_plot_format_checked_before_the_run(tmp_path: Path, capsys) -> None:
    """Reproducer 11: `video --plot p.txt` printed a traceback after the JSONL was written."""
    d = tmp_path / "frames"
    for i in range(2):
        _write(d / f"f{i}.png", i, (320, 180))
    out = tmp_path / "r.jsonl"
    assert main(["video", str(d), "--out", str(out), "--plot", str(tmp_path / "p.txt"), "-q", *SMALL]) == 2
    _one_line_error(capsys, "--plot", ".txt")
    assert not out.exists()
    assert main(["video", str(d), "--out", str(d / "r.jsonl"), "-q", *SMALL]) == 2
    _one_line_error(capsys, "inside the input folder")
    assert main(["video", str(d), "--out", str(out), "--annotate", str(d), "-q", *SMALL]) == 2
    _one_line_error(capsys, "--annotate")
    assert main(["video", str(d), "--out", str(tmp_path / "r.png"), "-q", *SMALL]) == 2  # plot = out
    _one_line_error(capsys, "same file")
    video = tmp_path / "v.avi"
    _corrupt_avi(video, 3, 1)
    assert main(["video", str(video), "--out", str(out), "--annotate", str(video), "-q", *SMALL]) == 2
    _one_line_error(capsys, "is an input")
    assert sorted(p.name for p in d.iterdir()) == ["f0.png", "f1.png"]


def test_score_without_result_files_is_an_error(crbd_dir: Path, tmp_path: Path, capsys) -> None:
    """Reproducer 11: an empty results folder exited 0 with CRDA 0.000 for 281 images."""
    empty = tmp_path / "results"
    empty.mkdir()
    assert main(["score", "--data", str(crbd_dir), "--results", str(empty), "-q"]) == 2
    _one_line_error(capsys, "no result files", ".tmg")


def test_eval_out_inside_the_data_is_refused(crbd_dir: Path, capsys) -> None:
    assert main(["eval", "--data", str(crbd_dir), "--out", str(crbd_dir / "Images"), "--limit", "1", "-q"]) == 2
    _one_line_error(capsys, "inside the input folder")


def test_file_names_that_are_not_utf8(tmp_path: Path) -> None:
    """Issue 26.9: with --annotate, cv2.imwrite crashed the process (rc 139) on such a name in
    `detect` (both impls) and `video --annotate DIR`; video's default plot raised after the
    records. OpenCV now never sees such a name (pictures are written by Python, videos are
    opened through a link)."""
    base = os.fsencode(tmp_path)
    try:
        os.mkdir(base + b"/imgs\xff")
    except OSError:
        pytest.skip("this file system takes UTF-8 names only")
    folder = Path(os.fsdecode(base + b"/imgs\xff"))
    for i, name in enumerate((b"a\xfe.png", b"b.png")):
        _write(tmp_path / "x.png", i, (64, 48))  # (cv2.imwrite itself crashes on the name)
        os.rename(tmp_path / "x.png", folder / os.fsdecode(name))
    for impl in ("tensor", "reference"):
        out, ann = tmp_path / f"{impl}.jsonl", tmp_path / f"ann_{impl}"
        assert main(["detect", str(folder), "--out", str(out), "--annotate", str(ann), "-q", "--impl", impl,
                     "--param", "image_width=64"]) == 0
        # records keep an undecodable byte as the four characters \xNN (apps.sink.bytes_safe)
        assert [r["name"] for r in _records(out)] == ["a\\xfe.png", "b.png"]
        assert sorted(os.listdir(os.fsencode(ann))) == [b"a\xfe.png", b"b.png"]
    video = Path(os.fsdecode(base + b"/v\xff.avi"))
    _corrupt_avi(tmp_path / "v.avi", 2, 1)
    os.rename(tmp_path / "v.avi", video)
    for src in (folder, video):
        out = tmp_path / "v.jsonl"
        assert main(["video", str(src), "--out", str(out), "--annotate", str(tmp_path / "vann"), "-q",
                     "--param", "video_width=64"]) == 0
        assert [r["source"] for r in _records(out)] == [bytes_safe(str(src))] * 2 and out.with_suffix(".png").is_file()
    assert len(os.listdir(tmp_path / "vann")) == 4
