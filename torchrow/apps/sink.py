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
  The Parquet schema is fixed before the first row is written (one pass over the journal
  collects every key), so the conversion cannot fail half-way on a key that appears late;
  if it fails anyway, no ``.parquet.tmp`` is left and the journal is kept for ``--resume``;
* one writer at a time: the JSONL (the journal for Parquet) is held under an exclusive
  ``flock`` while the sink is open (Parquet: until the conversion is done); a second sink on
  the same file raises :class:`SinkError` at once, before it changes anything;
* the run header ``<out>.run.json`` (:func:`header_path`; a sidecar, so that the JSONL stays
  a stream of records for every reader) records what wrote the file: a dict given by the
  caller (the CLI: command, parameters, sources as resolved paths) and its ``"info"`` (not
  compared). ``resume=True`` with another header raises :class:`SinkError` naming what
  differs; records without a header (written by an older torchrow, or by hand) are refused
  as well when a header is given, since nothing says what wrote them;
* text is bytes-safe: a string that is not valid Unicode (a file name that is not UTF-8,
  decoded by Python with ``surrogateescape``) is stored with each undecodable byte as the
  four characters ``\\xNN`` (:func:`bytes_safe`), the same in JSONL and Parquet; the keys
  of :attr:`RecordSink.done` use that form too.

Memory: one record at a time, plus the set of keys when resuming.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Hashable, Iterable, Iterator
from pathlib import Path
from typing import Any

from torchrow.core.tables import write_atomic

__all__ = ["RecordSink", "SinkError", "image_key", "frame_key", "read_records", "PARQUET_ROW_GROUP",
           "journal_path", "header_path", "output_paths", "bytes_safe", "records_to_parquet",
           "read_parquet_records"]

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


def header_path(path: Path) -> Path:
    """The run header beside an output (module docstring)."""
    return path.with_name(path.name + ".run.json")


def _tmp_path(path: Path) -> Path:
    return path.with_name(path.name + ".tmp")


def output_paths(path: str | Path) -> list[Path]:
    """Every path a sink on ``path`` writes: the output, its run header and, for Parquet, the
    journal and the temporary file of the conversion (for "never write over an input")."""
    path = Path(path)
    extra = [journal_path(path), _tmp_path(path)] if _is_parquet(path) else []
    return [path, header_path(path), *extra]


def bytes_safe(text: str) -> str:
    """``text`` itself if it is valid Unicode; else each byte that ``surrogateescape`` kept
    (a file name that is not UTF-8) as ``\\xNN`` and any other lone surrogate as ``\\uXXXX``."""
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        pass
    try:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    except UnicodeEncodeError:
        return text.encode("utf-8", "backslashreplace").decode("utf-8")


def _safe(value: object) -> object:
    """``value`` with every string in it :func:`bytes_safe` (records are small: dicts, lists)."""
    if isinstance(value, str):
        return bytes_safe(value)
    if isinstance(value, dict):
        return {_safe(k): _safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_safe(v) for v in value)
    return value


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
    header : dict, optional
        What this run is (JSON-able; its ``"info"`` entry is kept but not compared): written
        to :func:`header_path`; with ``resume``, the header already there must be equal
        (module docstring). ``None``: no header is read or written.

    Raises
    ------
    SinkError
        Another sink holds the file; ``resume`` on a file that is not a torchrow output, or
        that another run (another header) wrote. Nothing is changed then.

    Use as a context manager: on a normal exit the file is closed (and a Parquet output
    written); on an exception the JSONL (journal) is only closed, ready for ``resume``.
    """

    def __init__(self, path: str | Path, key: Key = image_key, resume: bool = False,
                 header: dict | None = None) -> None:
        self.path = Path(path)
        self.key = key
        self.parquet = _is_parquet(self.path)
        self.stream = journal_path(self.path) if self.parquet else self.path
        self.done: set[Hashable] = set()
        self.written = 0
        #: the header found beside ``path`` when resuming (``None``: none)
        self.previous_header: dict | None = None
        self._fh = _open_locked(self.stream)
        try:
            if resume:
                self._load_done(header)
            else:
                self._fh.truncate(0)
            if header is not None:
                _write_header(header_path(self.path), header)
        except BaseException:
            self._fh.close()
            raise
        self._fh.seek(0, os.SEEK_END)

    def _load_done(self, header: dict | None) -> None:
        fh = self._fh
        if self.parquet and os.fstat(fh.fileno()).st_size == 0 and self.path.exists():
            # a finished Parquet run being extended: its records go back into the journal
            for rec in read_parquet_records(self.path):
                fh.write(_line(rec))
            fh.flush()
        good = _scan(self.stream)
        if header is not None and good:
            self.previous_header = _check_header(self.path, header)
        for rec in _records(self.stream, good):
            self.done.add(_safe(self.key(rec)))
        if good != os.fstat(fh.fileno()).st_size:
            fh.truncate(good)

    def __contains__(self, key: Hashable) -> bool:
        return _safe(key) in self.done

    def write(self, rec: dict[str, Any]) -> None:
        """Append one record and flush it to the operating system."""
        self._fh.write(_line(rec))
        self._fh.flush()
        self.written += 1

    def close(self, complete: bool = True) -> None:
        """Close; with ``complete`` and a Parquet target, write it and drop the journal.

        The lock is held until the Parquet file is in place. A conversion that fails leaves
        the journal (for ``resume``) and no temporary file, and raises :class:`SinkError`."""
        if self._fh.closed:
            return
        try:
            self._fh.flush()
            os.fsync(self._fh.fileno())
            if complete and self.parquet:
                tmp = _tmp_path(self.path)
                try:
                    keys: dict[str, None] = {}  # every key, in order of first appearance: the schema
                    for rec in read_records(self.stream):
                        keys.update(dict.fromkeys(rec))
                    records_to_parquet(read_records(self.stream), tmp, keys=list(keys))
                    os.replace(tmp, self.path)
                except Exception as exc:
                    tmp.unlink(missing_ok=True)
                    raise SinkError(f"cannot write {self.path} ({type(exc).__name__}: {exc}); its records are "
                                    f"kept in {self.stream} (--resume continues)") from None
                self.stream.unlink()
        finally:
            self._fh.close()

    def __enter__(self) -> RecordSink:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(complete=exc_type is None)


def _open_locked(path: Path):
    """``path`` opened for reading and writing (created if missing, nothing truncated) under
    an exclusive ``flock``; :class:`SinkError` at once if another process holds it."""
    try:
        import fcntl
    except ImportError:  # no flock (Windows): no lock
        return open(path, "a+b")
    for _ in range(3):
        fh = open(path, "a+b")
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.close()
            raise SinkError(f"{path} is being written by another torchrow run (locked); wait for it to end "
                            "or write elsewhere") from None
        try:
            same = os.fstat(fh.fileno()).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:  # not a file that the holder removed (a finished Parquet journal) meanwhile
            return fh
        fh.close()
    raise SinkError(f"{path} keeps being replaced by another torchrow run; write elsewhere")


def _write_header(path: Path, header: dict) -> None:
    """The run header, written atomically (:func:`torchrow.core.tables.write_atomic`)."""
    text = json.dumps(_safe({"torchrow_run": 1, **header}), indent=1) + "\n"
    write_atomic(path, lambda fh: fh.write(text.encode()))


def _check_header(path: Path, header: dict) -> dict:
    """The header beside ``path``, checked against this run's (:class:`SinkError` naming the
    first entries that differ)."""
    hp = header_path(path)
    try:
        old = json.loads(hp.read_text())
        if not isinstance(old, dict) or old.get("torchrow_run") != 1:
            raise ValueError("not a torchrow run header")
    except FileNotFoundError:
        raise SinkError(f"{path} has records but no run header {hp.name} (written by an older torchrow or "
                        "another tool): what wrote them is unknown; run without --resume") from None
    except (OSError, ValueError) as exc:
        raise SinkError(f"cannot read the run header {hp} ({exc})") from None
    new = json.loads(json.dumps(_safe(header)))  # the form it has once written (tuples -> lists)
    diffs = []
    for k in sorted((set(new) | set(old)) - {"torchrow_run", "info"}):
        a, b = old.get(k), new.get(k)
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            diffs += [f"{k}.{f} {a.get(f)!r} there, {b.get(f)!r} now" for f in sorted(set(a) | set(b))
                      if a.get(f) != b.get(f)]
        else:
            diffs.append(f"{k} {a!r} there, {b!r} now")
    if diffs:
        more = f" (and {len(diffs) - 3} more)" if len(diffs) > 3 else ""
        raise SinkError(f"{path} was written by another run: {'; '.join(diffs[:3])}{more}; run without --resume "
                        "or write elsewhere")
    return old


def _line(rec: dict) -> bytes:
    line = json.dumps(rec)
    if "\\ud" in line:  # a lone surrogate (or a pair): bytes_safe decides, the same as Parquet
        line = json.dumps(_safe(rec))
    return (line + "\n").encode()


# ----------------------------------------------------------------------------------------
# Parquet
# ----------------------------------------------------------------------------------------

def _arrow_types():
    import pyarrow as pa

    f64, i32, i64, s = pa.float64(), pa.int32(), pa.int64(), pa.string()
    row = pa.struct([("a", f64), ("b", f64), ("c", f64), ("e", f64), ("valid", pa.bool_()), ("reason", s),
                     ("confidence", f64)])
    lattice_row = pa.struct([("k", i32), ("a", f64), ("b", f64), ("c", f64), ("e", f64), ("confidence", f64)])
    return {
        "source": s, "frame": i64, "stamp_ns": i64, "name": s, "status": s, "width": i32, "height": i32,
        "sky": i32, "veg_color": pa.list_(i32), "k": i32, "bushy": pa.bool_(), "n_rows": i32,
        # [theta_rad, rho_px, votes]: one float64 list (rho and votes are exact in float64)
        "hough": pa.list_(pa.list_(f64)), "outliers": pa.list_(pa.list_(f64)), "vp": pa.list_(f64),
        "rows": pa.list_(row), "error": s, "hough_ran": pa.bool_(), "hough_redo": pa.bool_(),
        "image_confidence": f64, "lattice_rows": pa.list_(lattice_row),
        "confidence": f64, "heading_px": f64, "heading_rad": f64, "lateral_px": f64, "lateral_frac": f64,
        "lateral_m": f64, "spacing_m": f64,
        # the lattice tracker's (ALGORITHM.md 11.7)
        "state": s, "row_change": i32, "row_end_y": i32, "row_end_m": f64,
    }


def records_to_parquet(records: Iterable[dict], path: str | Path, row_group: int = PARQUET_ROW_GROUP,
                       keys: Iterable[str] | None = None) -> int:
    """Write records (dicts with the README's keys) to a Parquet file; returns their count.

    Known keys get typed columns (Hough triples as float64 lists); any other key becomes a
    JSON string column. The columns are ``keys`` (every key of the records, so that the
    schema is fixed before the first row group: :meth:`RecordSink.close` collects them in a
    first pass) or, without it, the keys of the first row group; plus the optional ``error``
    and ``stamp_ns`` (null where absent). Strings are :func:`bytes_safe`. Memory: one row group.
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
        chunk = [_safe(rec) for rec in chunk]  # type: ignore[misc]
        if schema is None:
            names: list[str] = list(keys) if keys is not None else []
            for rec in chunk:
                names.extend(k for k in rec if k not in names)
            names.extend(k for k in ("error", "stamp_ns") if k not in names)
            schema = pa.schema([(k, types.get(k, pa.string())) for k in names])
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
            # optional keys (and a bag frame's keys among image records): absent, as in the JSONL, where null
            for k in ("error", "stamp_ns", "source", "frame"):
                if k in rec and rec[k] is None:
                    del rec[k]
            yield rec
