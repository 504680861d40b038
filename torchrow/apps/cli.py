"""Command line: ``torchrow detect | eval | score | video | export | demo`` (also ``python -m torchrow``).

Each command is a module of :mod:`torchrow.apps.commands` (its arguments and its run); this
module builds the parser from them and runs the one asked. Errors in arguments or paths print
one line (``torchrow: error: ...``) and exit with 2; a file that cannot be read inside a run
gets an ``error`` record and the run goes on.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from torchrow import __version__
from torchrow.apps.commands import demo, detect, evaluate, export, score, video
from torchrow.apps.commands.shared import ERROR_STATUS, CLIError, print_error

__all__ = ["main", "build_parser", "COMMANDS"]

COMMANDS = (detect, evaluate, score, video, export, demo)
"""The command modules, in the order ``torchrow --help`` lists them."""


def build_parser() -> argparse.ArgumentParser:
    """The ``torchrow`` parser: one subcommand per module of :data:`COMMANDS`, each setting
    ``func`` (its ``run``)."""
    ap = argparse.ArgumentParser(prog="torchrow", description="Crop-row detection (ALGORITHM.md), "
                                 "reference and batched tensor implementations.")
    ap.add_argument("--version", action="version", version=f"torchrow {__version__}")
    sub = ap.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``torchrow`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status: 0,
    2 for a user error (one line on stderr), 130 when interrupted."""
    ap = build_parser()
    args = ap.parse_args(argv)
    if getattr(args, "every", 1) < 1 or getattr(args, "limit", 0) < 0 or getattr(args, "batch_size", 1) < 1:
        ap.exit(ERROR_STATUS, "torchrow: error: --every and --batch-size must be >= 1, --limit >= 0\n")
    try:
        return int(args.func(args) or 0)
    except CLIError as exc:
        return print_error(exc)
    except ValueError as exc:  # a Parquet output that cannot be written (torchrow.apps.sink.SinkError)
        from torchrow.apps.sink import SinkError

        if not isinstance(exc, SinkError):
            raise
        return print_error(exc)
    except KeyboardInterrupt:
        print("torchrow: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:
        return print_error(exc)


if __name__ == "__main__":
    sys.exit(main())
