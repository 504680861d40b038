"""Streaming, crash-safe, resumable record output (JSONL, or Parquet at the end of a run).

Every command that writes records (``detect``, ``eval --out``, ``video``) writes them through
a :class:`RecordSink`:

* each record is one JSON line, written with one ``write`` and flushed to the operating
  system at once, so a process killed at any moment (``kill -9``, the kernel's OOM killer)
  leaves every record it had handed over, plus at most one torn last line;
* ``resume=True`` reads the file first, keeps the *keys* of the records in it
  (:attr:`RecordSink.done`: ``name`` for images, ``(source, frame)`` for video frames), cuts
  a torn last line off, and appends; the caller skips the inputs whose key is in ``done``.
  A line that is not JSON before the last one is an error (the file is not a torchrow
  output, or was edited): nothing is guessed;
* ``--out x.parquet``: records stream into the journal ``x.parquet.partial.jsonl`` exactly as
  above; when the run ends normally the journal is converted to ``x.parquet`` in row groups
  of :data:`PARQUET_ROW_GROUP` records (bounded memory) and removed. A killed run leaves the
  journal, which ``--resume`` continues. Parquet needs ``pyarrow`` (installed with ``ray``).

Memory: one record at a time, plus the set of keys when resuming.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Hashable, Iterable, Iterator
from pathlib import Path
from typing import Any

__all__ = ["RecordSink", "SinkError", "image_key", "frame_key", "read_records", "PARQUET_ROW_GROUP",
           "journal_path", "records_to_parquet", "read_parquet_records"]

#: Records per Parquet row group when a journal is converted (memory of the conversion).
PARQUET_ROW_GROUP = 4096

Key = Callable[[dict], Hashable]


class SinkError(ValueError):
    """An output file that cannot be resumed (not a torchrow JSONL, corrupt before its end)."""


def image_key(rec: dict) -> Hashable:
    """Key of an image record (``detect``, ``eval``): its ``name``."""
    return rec.get("name")


def frame_key(rec: dict) -> Hashable:
    """Key of a video frame record: ``(source, frame)``."""
    return (rec.get("source"), rec.get("frame"))


def journal_path(path: Path) -> Path:
    """Where records stream before the final Parquet file is written."""
    return path.with_name(path.name + ".partial.jsonl")


def _is_parquet(path: Path) -> bool:
    return path.suffix.lower() == ".parquet"


def _scan(path: Path) -> int:
    """Length in bytes of the intact part of a JSONL file.

    The intact part ends after the last newline-terminated line; a last line without a
    newline, or a last line that does not parse, is *torn* (a write cut short) and left out.
    A line that does not parse before the last one raises :class:`SinkError`.
    """
    good = 0
    with open(path, "rb") as fh:
        for lineno, raw in enumerate(fh, 1):
            if not raw.endswith(b"\n"):
                break
            try:
                rec = json.loads(raw)
            except json.JSONDecodeError:
                if fh.read(1) == b"":
                    break
                raise SinkError(f"{path}: line {lineno} is not JSON (not a torchrow output?)") from None
            if not isinstance(rec, dict):
                raise SinkError(f"{path}: line {lineno} is not a JSON object (not a torchrow output?)")
            good += len(raw)
    return good


def _records(path: Path, upto: int) -> Iterator[dict]:
    with open(path, "rb") as fh:
        pos = 0
        for raw in fh:
            pos += len(raw)
            if pos > upto:
                return
            yield json.loads(raw)


def read_records(path: str | Path) -> Iterator[dict]:
    """The records of a JSONL output (a torn last line left out) or of a Parquet output."""
    path = Path(path)
    if _is_parquet(path):
        yield from read_parquet_records(path)
        return
    yield from _records(path, _scan(path))


class RecordSink:
    """Write records one by one, flushed; optionally resume an earlier, interrupted run.

    Parameters
    ----------
    path : path
        ``.jsonl`` (any suffix but ``.parquet``) or ``.parquet`` (module docstring).
    key : callable
        Record -> key for :attr:`done` (:func:`image_key` or :func:`frame_key`).
    resume : bool
        Keep the records already in ``path`` (or in its journal) and append; without it the
        file is truncated.

    Use as a context manager: on a normal exit the file is closed (and a Parquet output
    written); on an exception the JSONL (journal) is only closed, ready for ``resume``.
    """

    def __init__(self, path: str | Path, key: Key = image_key, resume: bool = False) -> None:
        self.path = Path(path)
        self.key = key
        self.parquet = _is_parquet(self.path)
        self.stream = journal_path(self.path) if self.parquet else self.path
        self.done: set[Hashable] = set()
        self.written = 0
        if resume:
            self._load_done()
        elif self.parquet and self.stream.exists():
            self.stream.unlink()
        mode = "ab" if resume else "wb"
        self._fh = open(self.stream, mode)

    def _load_done(self) -> None:
        if self.parquet and not self.stream.exists() and self.path.exists():
            # a finished Parquet run being extended: its records go back into a journal
            with open(self.stream, "wb") as fh:
                for rec in read_parquet_records(self.path):
                    fh.write(_line(rec))
        if not self.stream.exists():
            return
        good = _scan(self.stream)
        for rec in _records(self.stream, good):
            self.done.add(self.key(rec))
        if good != self.stream.stat().st_size:
            with open(self.stream, "r+b") as fh:
                fh.truncate(good)

    def __contains__(self, key: Hashable) -> bool:
        return key in self.done

    def write(self, rec: dict[str, Any]) -> None:
        """Append one record and flush it to the operating system."""
        self._fh.write(_line(rec))
        self._fh.flush()
        self.written += 1

    def close(self, complete: bool = True) -> None:
        """Close; with ``complete`` and a Parquet target, write it and drop the journal."""
        if self._fh.closed:
            return
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self._fh.close()
        if complete and self.parquet:
            tmp = self.path.with_name(self.path.name + ".tmp")
            records_to_parquet(read_records(self.stream), tmp)
            os.replace(tmp, self.path)
            self.stream.unlink()

    def __enter__(self) -> RecordSink:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(complete=exc_type is None)


def _line(rec: dict) -> bytes:
    return (json.dumps(rec) + "\n").encode()


# ----------------------------------------------------------------------------------------
# Parquet
# ----------------------------------------------------------------------------------------

def _arrow_types():
    import pyarrow as pa

    f64, i32, i64, s = pa.float64(), pa.int32(), pa.int64(), pa.string()
    row = pa.struct([("a", f64), ("b", f64), ("c", f64), ("e", f64), ("valid", pa.bool_()), ("reason", s),
                     ("confidence", f64)])
    return {
        "source": s, "frame": i64, "stamp_ns": i64, "name": s, "status": s, "width": i32, "height": i32,
        "sky": i32, "veg_color": pa.list_(i32), "k": i32, "bushy": pa.bool_(), "n_rows": i32,
        # [theta_rad, rho_px, votes]: one float64 list (rho and votes are exact in float64)
        "hough": pa.list_(pa.list_(f64)), "outliers": pa.list_(pa.list_(f64)), "vp": pa.list_(f64),
        "rows": pa.list_(row), "error": s, "hough_ran": pa.bool_(), "hough_redo": pa.bool_(),
        "image_confidence": f64, "confidence": f64, "heading_px": f64, "heading_rad": f64, "lateral_px": f64, "lateral_frac": f64,
    }


def records_to_parquet(records: Iterable[dict], path: str | Path, row_group: int = PARQUET_ROW_GROUP) -> int:
    """Write records (dicts with the README's keys) to a Parquet file; returns their count.

    Known keys get typed columns (Hough triples as float64 lists); any other key becomes a
    JSON string column. The columns are the keys of the first row group, plus the optional
    ``error`` and ``stamp_ns`` (null where absent). Memory: one row group.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    types = _arrow_types()
    it = iter(records)
    writer = None
    schema = None
    n = 0
    while True:
        chunk = [rec for _, rec in zip(range(row_group), it)]
        if not chunk:
            break
        if schema is None:
            keys: list[str] = []
            for rec in chunk:
                keys.extend(k for k in rec if k not in keys)
            keys.extend(k for k in ("error", "stamp_ns") if k not in keys)
            schema = pa.schema([(k, types.get(k, pa.string())) for k in keys])
            writer = pq.ParquetWriter(str(path), schema)
        extra = {k for rec in chunk for k in rec} - set(schema.names)
        if extra:
            raise SinkError(f"record keys {sorted(extra)} first appear after record {n} (Parquet columns "
                            "are fixed by the first row group)")
        cols = {}
        for f in schema:
            vals = [rec.get(f.name) for rec in chunk]
            if f.name not in types:
                vals = [None if v is None else json.dumps(v) for v in vals]
            cols[f.name] = pa.array(vals, type=f.type)
        writer.write_table(pa.table(cols, schema=schema))  # type: ignore[union-attr]
        n += len(chunk)
    if writer is None:
        pq.write_table(pa.table({"name": pa.array([], pa.string())}), str(path))
    else:
        writer.close()
    return n


def read_parquet_records(path: str | Path) -> Iterator[dict]:
    """Records of a Parquet file written by :func:`records_to_parquet`, row group by row group."""
    import pyarrow.parquet as pq

    types = _arrow_types()
    pf = pq.ParquetFile(str(path))
    for i in range(pf.num_row_groups):
        for rec in pf.read_row_group(i).to_pylist():
            for k, v in rec.items():
                if k not in types and isinstance(v, str):
                    rec[k] = json.loads(v)
            for k in ("hough", "outliers"):  # back to [float, int, int], as in the JSONL
                if rec.get(k) is not None:
                    rec[k] = [[t, int(r), int(v)] for t, r, v in rec[k]]
            for k in ("error", "stamp_ns"):  # optional keys: absent, as in the JSONL, where null
                if k in rec and rec[k] is None:
                    del rec[k]
            yield rec
