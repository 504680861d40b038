"""Progress of long runs on stderr: a live bar on a terminal, a few plain lines otherwise.

A redirected stderr (a log file, CI, ``2> run.log``) gets no carriage-return redraws: it gets
one line when the run starts, one at every tenth of it or every ``interval`` seconds
(whichever comes later), and one at the end.
"""

from __future__ import annotations

import sys
import time
from typing import IO, Any

__all__ = ["progress", "PlainProgress"]


class PlainProgress:
    """tqdm's ``update``/``close``/context-manager interface, writing whole lines."""

    def __init__(self, total: int | None, desc: str, unit: str, file: IO[str], interval: float = 30.0) -> None:
        self.total, self.desc, self.unit, self.file, self.interval = total, desc, unit, file, interval
        self.n = 0
        self._t0 = self._last_t = time.monotonic()
        self._last_n = 0
        self._closed = False
        self._write(f"{desc}: started" + (f", {total} {unit}(s)" if total else ""))

    def _write(self, text: str) -> None:
        print(text, file=self.file, flush=True)

    def _line(self) -> str:
        elapsed = time.monotonic() - self._t0
        rate = f", {self.n / elapsed:.1f} {self.unit}/s" if elapsed > 0 and self.n else ""
        of = f"/{self.total}" if self.total else ""
        return f"{self.desc}: {self.n}{of} {self.unit}(s), {elapsed:.0f} s{rate}"

    def update(self, n: int = 1) -> None:
        self.n += n
        now = time.monotonic()
        step = max(1, (self.total or 0) // 10)
        if (self.n - self._last_n >= step and now - self._last_t >= min(self.interval, 5.0)) \
                or now - self._last_t >= self.interval:
            self._write(self._line())
            self._last_n, self._last_t = self.n, now

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._write(self._line() + " (done)")

    def __enter__(self) -> PlainProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Silent:
    n = 0

    def update(self, n: int = 1) -> None:
        self.n += n

    def close(self) -> None:
        pass

    def __enter__(self) -> _Silent:
        return self

    def __exit__(self, *exc: object) -> None:
        pass


def progress(total: int | None, desc: str, enabled: bool = True, unit: str = "item", file: IO[str] | None = None) -> Any:
    """A progress reporter with ``update(n)``/``close()``: tqdm on a terminal, plain lines
    (:class:`PlainProgress`) when ``file`` (default stderr) is not one, nothing when not ``enabled``."""
    out = file if file is not None else sys.stderr
    if not enabled:
        return _Silent()
    isatty = getattr(out, "isatty", None)
    if isatty is not None and isatty():
        from tqdm.auto import tqdm

        return tqdm(total=total, desc=desc, file=out, unit=unit)
    return PlainProgress(total, desc, unit, out)
