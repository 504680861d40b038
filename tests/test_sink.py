"""Streaming output: the record sink (flush, torn lines, resume, Parquet), the runner's
bounded ordering window, and a run killed with SIGKILL then resumed (subprocess)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import pytest

from torchrow.apps.cli import main
from torchrow.apps.sink import RecordSink, SinkError, frame_key, journal_path, read_records
from torchrow.engines.runner import run
from torchrow.evaluation.synthetic import FieldSpec, render, sequence


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines()


# -- the sink ----------------------------------------------------------------------------

def test_each_record_is_on_disk_when_write_returns(tmp_path: Path) -> None:
    out = tmp_path / "r.jsonl"
    sink = RecordSink(out)
    for i in range(3):
        sink.write({"name": f"im{i}", "status": "ok"})
        # another reader sees the record at once (flushed to the OS, not buffered)
        assert [json.loads(s)["name"] for s in _lines(out)] == [f"im{j}" for j in range(i + 1)]
    sink.close()


def test_resume_cuts_a_torn_last_line_and_appends(tmp_path: Path) -> None:
    out = tmp_path / "r.jsonl"
    with RecordSink(out) as sink:
        sink.write({"name": "a", "status": "ok"})
        sink.write({"name": "b", "status": "ok"})
    with open(out, "ab") as fh:
        fh.write(b'{"name": "c", "stat')  # a write cut short by a kill
    sink = RecordSink(out, resume=True)
    assert sink.done == {"a", "b"} and "c" not in sink
    sink.write({"name": "c", "status": "ok"})
    sink.close()
    assert [json.loads(s)["name"] for s in _lines(out)] == ["a", "b", "c"]


def test_resume_cuts_a_last_line_that_is_not_json_even_with_newline(tmp_path: Path) -> None:
    out = tmp_path / "r.jsonl"
    out.write_bytes(b'{"name": "a"}\n{"name": "b", \n')
    assert RecordSink(out, resume=True).done == {"a"}
    assert out.read_bytes() == b'{"name": "a"}\n'


def test_resume_refuses_a_corrupt_line_before_the_end(tmp_path: Path) -> None:
    out = tmp_path / "r.jsonl"
    out.write_bytes(b'{"name": "a"}\nGARBAGE\n{"name": "b"}\n')
    with pytest.raises(SinkError, match="line 2"):
        RecordSink(out, resume=True)
    assert out.read_bytes() == b'{"name": "a"}\nGARBAGE\n{"name": "b"}\n'  # untouched


def test_without_resume_the_file_is_replaced(tmp_path: Path) -> None:
    out = tmp_path / "r.jsonl"
    out.write_text('{"name": "old"}\n')
    with RecordSink(out) as sink:
        sink.write({"name": "new"})
    assert _lines(out) == ['{"name": "new"}']


def test_video_keys_are_source_and_frame(tmp_path: Path) -> None:
    out = tmp_path / "v.jsonl"
    with RecordSink(out, key=frame_key) as sink:
        sink.write({"source": "s", "frame": 0})
        sink.write({"source": "t", "frame": 0})
    assert RecordSink(out, key=frame_key, resume=True).done == {("s", 0), ("t", 0)}


def _cli_records(folder: Path, out: Path, *extra: str) -> None:
    assert main(["detect", str(folder), "--out", str(out), "-q", "--batch-size", "2", *extra]) == 0


@pytest.fixture(scope="module")
def field_folder(tmp_path_factory) -> Path:
    """Three synthetic fields (one of another size, sorted first) and one unreadable file."""
    d = tmp_path_factory.mktemp("fields")
    cv2.imwrite(str(d / "a_wide.png"), cv2.cvtColor(render(FieldSpec(seed=9, width=640, height=360)).image,
                                                    cv2.COLOR_RGB2BGR))
    for i in range(2):
        cv2.imwrite(str(d / f"f{i}.png"), cv2.cvtColor(render(FieldSpec(seed=i)).image, cv2.COLOR_RGB2BGR))
    (d / "z_bad.jpg").write_bytes(b"not an image")
    return d


def test_parquet_output_holds_the_jsonl_records(field_folder: Path, tmp_path: Path) -> None:
    pytest.importorskip("pyarrow")
    _cli_records(field_folder, tmp_path / "r.jsonl")
    _cli_records(field_folder, tmp_path / "r.parquet")
    want = [json.loads(s) for s in _lines(tmp_path / "r.jsonl")]
    assert list(read_records(tmp_path / "r.parquet")) == want
    assert not journal_path(tmp_path / "r.parquet").exists()
    # resuming a finished Parquet run keeps every record once
    _cli_records(field_folder, tmp_path / "r.parquet", "--resume")
    assert list(read_records(tmp_path / "r.parquet")) == want


def test_parquet_holds_improved_records_with_their_nulls(field_folder: Path, tmp_path: Path) -> None:
    # the improved mode's records null sections 2-6's fields and add lattice_rows: the schema,
    # fixed before the first row, types them (not JSON strings) and they come back as written
    pytest.importorskip("pyarrow")
    import pyarrow.parquet as pq

    _cli_records(field_folder, tmp_path / "r.jsonl", "--mode", "improved")
    _cli_records(field_folder, tmp_path / "r.parquet", "--mode", "improved")
    want = [json.loads(s) for s in _lines(tmp_path / "r.jsonl")]
    ok = [r for r in want if r["status"] != "error"]
    assert ok and all(r["veg_color"] is None and r["hough"] is None and r["vp"] is None and r["lattice_rows"]
                      for r in ok)
    assert list(read_records(tmp_path / "r.parquet")) == want
    schema = pq.read_schema(tmp_path / "r.parquet")
    assert str(schema.field("lattice_rows").type).startswith("list<") and str(schema.field("k").type) == "int32"


# -- the runner's ordering window --------------------------------------------------------

_SMALL = [render(FieldSpec(seed=s, width=64, height=48)).image for s in range(3)]
_ODD = render(FieldSpec(seed=7, width=64, height=40)).image


def _small_items(n: int, odd_first: bool, pulled: list[int]):
    imgs = [_SMALL[i % 3] for i in range(n)]
    if odd_first:
        imgs[0] = _ODD
    for i, im in enumerate(imgs):
        pulled.append(i)
        yield f"im{i}", (lambda im=im: im)


def test_odd_sized_first_image_does_not_hold_the_output_back() -> None:
    """Before the window, the odd image's record (and so every record) came out only after
    the last input was read; now it comes out once ``window`` inputs are read ahead."""
    pulled: list[int] = []
    gen = run(_small_items(20, True, pulled), batch_size=4, window=8, progress=False)
    i, _, res, _ = next(gen)
    assert i == 0 and res.name == "im0" and res.height == 40
    assert len(pulled) <= 8
    rest = list(gen)
    assert [r[0] for r in rest] == list(range(1, 20))


def test_window_changes_no_record() -> None:
    a = [r.to_record() for _, _, r, _ in run(_small_items(13, True, []), batch_size=4, window=4, progress=False)]
    b = [r.to_record() for _, _, r, _ in run(_small_items(13, True, []), batch_size=64, window=1000,
                                             progress=False)]
    assert a == b


def test_window_smaller_than_batch_is_refused() -> None:
    with pytest.raises(ValueError, match="window"):
        list(run([], batch_size=8, window=4, progress=False))


# -- kill -9 and --resume ----------------------------------------------------------------

def _spawn_detect(folder: Path, out: Path, *extra: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    return subprocess.Popen([sys.executable, "-m", "torchrow", "detect", str(folder), "--out", str(out),
                             "--batch-size", "1", "-q", *extra], env=env, stderr=subprocess.PIPE)


@pytest.fixture(scope="module")
def many_fields(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("many")
    for i in range(10):
        img = render(FieldSpec(seed=100 + i, width=320, height=160)).image
        cv2.imwrite(str(d / f"im{i:02d}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    (d / "im99_bad.png").write_bytes(b"")
    return d


def test_killed_run_resumed_equals_a_clean_run(many_fields: Path, tmp_path: Path) -> None:
    clean = tmp_path / "clean.jsonl"
    _cli_records(many_fields, clean)
    out = tmp_path / "killed.jsonl"
    proc = _spawn_detect(many_fields, out)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        if out.exists() and len(out.read_bytes().splitlines()) >= 3:
            break
        time.sleep(0.01)
    assert proc.poll() is None, proc.stderr.read().decode() if proc.stderr else ""  # still running
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    n_before = len(out.read_bytes().splitlines())
    assert 3 <= n_before < 11, n_before  # streamed, not held back to the end
    with open(out, "ab") as fh:
        fh.write(b'{"name": "im2')  # and a torn line, as a kill during a write leaves
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    res = subprocess.run([sys.executable, "-m", "torchrow", "detect", str(many_fields), "--out", str(out),
                          "--batch-size", "2", "-q", "--resume"], env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert "kept from the earlier run" in res.stderr
    got = _lines(out)
    names = [json.loads(s)["name"] for s in got]
    assert len(names) == len(set(names)) == 11
    assert got == _lines(clean)  # records in input order: the same file as a clean run


def test_video_resume_after_a_cut_equals_a_clean_run(tmp_path: Path) -> None:
    srcs = []
    for k in range(2):
        d = tmp_path / f"seq{k}"
        d.mkdir()
        for t, f in enumerate(sequence(FieldSpec(seed=k, width=200, height=120), 6 + 2 * k)):
            cv2.imwrite(str(d / f"{t:03d}.png"), cv2.cvtColor(f.image, cv2.COLOR_RGB2BGR))
        srcs.append(str(d))
    clean, cut = tmp_path / "clean.jsonl", tmp_path / "cut.jsonl"
    base = ["video", *srcs, "-q", "--plot", "none", "--param", "video_width=200"]
    assert main([*base, "--out", str(clean)]) == 0
    lines = clean.read_bytes().splitlines(keepends=True)
    assert len(lines) == 14
    cut.write_bytes(b"".join(lines[:5]) + lines[5][:30])  # sequence 1 cut short, torn line
    Path(f"{cut}.run.json").write_bytes(Path(f"{clean}.run.json").read_bytes())  # the run that wrote it
    assert main([*base, "--out", str(cut), "--resume"]) == 0
    assert sorted(_lines(cut)) == sorted(_lines(clean))
    assert len(_lines(cut)) == 14


# -- issue 26: run header, lock, Parquet that cannot fail at the end, journal paths -------

def _one_line_error(capsys, *words: str) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("torchrow: error: ") and "\n" not in err, err
    for w in words:
        assert w in err, err
    return err


@pytest.fixture(scope="module")
def two_small(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("two")
    for i in range(2):
        img = render(FieldSpec(seed=40 + i, width=96, height=64)).image
        cv2.imwrite(str(d / f"s{i}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    return d


def test_resume_refuses_an_output_of_another_run(two_small: Path, tmp_path: Path, capsys) -> None:
    """Reproducer 5: --resume mixed n_rows 5 and 2, faithful and improved, detect and video records."""
    out = tmp_path / "r.jsonl"
    _cli_records(two_small, out)
    data = out.read_bytes()
    capsys.readouterr()
    for extra, words in ((["--param", "n_rows=2"], "params.n_rows 5 there, 2 now"),
                         (["--mode", "improved"], "params.mode 'faithful' there, 'improved' now")):
        assert main(["detect", str(two_small), "--out", str(out), "-q", "--resume", *extra]) == 2
        _one_line_error(capsys, "cannot --resume", words)
    assert main(["detect", str(two_small / "s0.png"), "--out", str(out), "-q", "--resume"]) == 2
    _one_line_error(capsys, "sources")
    assert main(["video", str(two_small), "--out", str(out), "-q", "--resume", "--plot", "none"]) == 2
    _one_line_error(capsys, "command 'detect' there, 'video' now")
    assert out.read_bytes() == data
    # the same run, inputs spelled otherwise: resumed (nothing left to do)
    assert main(["detect", str(two_small / "."), "--out", str(out), "-q", "--resume"]) == 0
    assert out.read_bytes() == data
    capsys.readouterr()
    # records that no header describes (an older torchrow, or by hand) are not resumed by the CLI
    header = out.with_name(out.name + ".run.json")
    header.unlink()
    assert main(["detect", str(two_small), "--out", str(out), "-q", "--resume"]) == 2
    _one_line_error(capsys, "no run header")


def test_video_resume_with_the_source_spelled_otherwise(tmp_path: Path, monkeypatch) -> None:
    """Reproducer 5: `cat20` then `/abs/cat20` gave 8 duplicate records under a second name."""
    d = tmp_path / "seq"
    d.mkdir()
    for i, spec in enumerate(sequence(FieldSpec(seed=5, width=160, height=96), 3)):
        cv2.imwrite(str(d / f"f{i}.png"), cv2.cvtColor(spec.image, cv2.COLOR_RGB2BGR))
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "v.jsonl"
    small = ["--param", "video_width=160", "--plot", "none", "-q"]
    assert main(["video", "seq", "--out", str(out), *small]) == 0
    lines = _lines(out)
    (out.parent / "cut.jsonl").write_text("\n".join(lines[:1]) + "\n")
    os.replace(out.parent / "cut.jsonl", out)
    assert main(["video", str(d), "--out", str(out), "--resume", *small]) == 0
    assert _lines(out) == lines  # one name, every frame once


def test_a_second_writer_of_the_same_output_fails_at_once(two_small: Path, tmp_path: Path, capsys) -> None:
    """Reproducer 6: two runs on one .jsonl both exited 0 (84 records for 59 inputs, a garbled
    line); on one .parquet the second deleted the first one's journal."""
    for name in ("r.jsonl", "r.parquet"):
        out = tmp_path / name
        with RecordSink(out) as first:
            first.write({"name": "kept", "status": "ok"})
            for resume in ([], ["--resume"]):
                assert main(["detect", str(two_small), "--out", str(out), "-q", *resume]) == 2
                _one_line_error(capsys, "being written by another torchrow run")
            first.write({"name": "kept2", "status": "ok"})
        if name.endswith(".parquet") and not _has_pyarrow():
            continue
        assert [r["name"] for r in read_records(out)] == ["kept", "kept2"]
    with pytest.raises(SinkError, match="locked"):
        with RecordSink(tmp_path / "x.jsonl"), RecordSink(tmp_path / "x.jsonl", resume=True):
            pass


def _has_pyarrow() -> bool:
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        return False
    return True


def test_parquet_schema_is_fixed_up_front_and_names_are_bytes_safe(tmp_path: Path) -> None:
    """Reproducer 7: > 4096 image records then bag frames (keys first seen late), and a file
    name that is not UTF-8, ended in tracebacks with no .parquet and a stray .parquet.tmp."""
    pytest.importorskip("pyarrow")
    out = tmp_path / "x.parquet"
    odd = os.fsdecode(b"caf\xe9.jpg")  # as Python lists a non-UTF-8 file name
    with RecordSink(out) as sink:
        for i in range(4100):
            sink.write({"name": f"im{i}", "status": "ok", "n_rows": 5})
        sink.write({"name": odd, "status": "error", "error": f"cannot read /d/{odd}"})
        sink.write({"name": "b.bag#000000", "source": "/d/b.bag", "frame": 0, "stamp_ns": 7, "status": "ok"})
    assert not journal_path(out).exists() and not out.with_name("x.parquet.tmp").exists()
    recs = list(read_records(out))
    assert len(recs) == 4102 and recs[4100]["name"] == "caf\\xe9.jpg" and recs[4100]["error"] == "cannot read /d/caf\\xe9.jpg"
    assert recs[4101]["source"] == "/d/b.bag" and recs[4101]["frame"] == 0 and "source" not in recs[0]
    # the JSONL holds the same escaped text, and a resume finds the name in either spelling
    sink = RecordSink(out, resume=True)
    assert odd in sink and "caf\\xe9.jpg" in sink and len(sink.done) == 4102
    sink.close()


def test_a_failed_parquet_conversion_keeps_the_journal_and_no_tmp(tmp_path: Path, monkeypatch) -> None:
    pytest.importorskip("pyarrow")
    out = tmp_path / "x.parquet"
    with RecordSink(out) as sink:
        sink.write({"name": "a", "status": "ok"})
    monkeypatch.setattr("torchrow.apps.sink.records_to_parquet",
                        lambda recs, path, **kw: (Path(path).write_bytes(b"half"), 1 / 0))
    with pytest.raises(SinkError, match="kept in"):
        with RecordSink(out, resume=True) as sink:
            sink.write({"name": "b", "status": "ok"})
    assert not out.with_name("x.parquet.tmp").exists()
    assert [json.loads(s)["name"] for s in _lines(journal_path(out))] == ["a", "b"]
    monkeypatch.undo()
    RecordSink(out, resume=True).close()
    assert [r["name"] for r in read_records(out)] == ["a", "b"]


def test_journal_and_temporary_paths_are_never_over_an_input(two_small: Path, tmp_path: Path, capsys) -> None:
    """Reproducer 8: `detect o/r.parquet.partial.jsonl o/r.parquet.tmp --out o/r.parquet` deleted both inputs."""
    o = tmp_path / "o"
    o.mkdir()
    for name in ("r.parquet.partial.jsonl", "r.parquet.tmp", "r.jsonl.run.json"):
        img = o / name
        img.write_bytes((two_small / "s0.png").read_bytes())
        out = o / name.split(".")[0]
        out = out.with_suffix(".parquet" if "parquet" in name else ".jsonl")
        assert main(["detect", str(img), "--out", str(out), "-q"]) == 2
        _one_line_error(capsys, "is an input")
        assert img.read_bytes() == (two_small / "s0.png").read_bytes()
