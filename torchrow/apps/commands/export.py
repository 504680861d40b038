"""``torchrow export onnx``: the image-mode detector or the video tracker step as a
static-shape ONNX graph (README: ONNX export)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from torchrow.apps.commands.shared import CLIError, add_common, add_mode, parse_params, replace_params, with_mode

__all__ = ["add_parser", "run"]


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser("export", help="export the image-mode detector or the tracker step "
                                             "(see README: ONNX export)")
    esub = p.add_subparsers(dest="format", required=True)
    p = esub.add_parser("onnx", help="static-shape ONNX graph (torch dynamo exporter)")
    p.add_argument("--out", required=True, help="output .onnx file")
    p.add_argument("--tracker", action="store_true",
                   help="export the video tracker step (frame + state -> rows + new state) instead of the detector; "
                        "with --mode improved, the lattice tracker step (ALGORITHM.md 11.7)")
    p.add_argument("--no-control-flow", action="store_true",
                   help="no ONNX Loop or If: every line-search step to the static bound (and, tracker, both "
                        "branches) runs, masks choose (slower, same results)")
    p.add_argument("--scatter-free", action="store_true",
                   help="vote without ScatterElements(reduction=add), for runtimes that lack it (TensorRT); "
                        "slower on a CPU, same results")
    p.add_argument("--height", type=int, default=None,
                   help="working height (detector default 240; required with --tracker)")
    p.add_argument("--width", type=int, default=None,
                   help="working width (detector default 320; tracker default video_width, 500)")
    p.add_argument("--batch", type=int, default=1, help="static batch size (default 1)")
    p.add_argument("--opset", type=int, default=18, help="ONNX opset, >= 18 (default 18)")
    add_common(p)
    add_mode(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        import onnx  # noqa: F401
        import onnxscript  # noqa: F401
    except ImportError:
        raise CLIError("export needs onnx and onnxscript: pip install 'torchrow[onnx]'") from None
    from torchrow.onnx.export import to_onnx
    from torchrow.onnx.metadata import model_info

    params = with_mode(parse_params(args.param), args)
    improved = params.mode == "improved"
    if improved and not args.tracker:
        raise CLIError("--mode improved exports the lattice tracker step only: add --tracker")
    if improved and args.scatter_free:
        raise CLIError("--scatter-free: the improved mode's tracker step has no scatter-free form")
    if args.tracker:
        width = args.width if args.width is not None else params.video_width
        if args.height is None:
            raise CLIError("--tracker needs --height: the frames' working height at width "
                           f"{width} (e.g. 281 for 1280x720 video at the default video_width 500)")
        height = args.height
        if width != params.video_width:
            params = replace_params(params, "--width", video_width=width)
    else:
        width = args.width if args.width is not None else 320
        height = args.height if args.height is not None else 240
        if width != params.image_width:
            params = replace_params(params, "--width", image_width=width)
    out = Path(args.out)
    if not out.parent.is_dir():
        raise CLIError(f"output folder does not exist: {out.parent}")
    t0 = time.perf_counter()

    def phase(name: str) -> None:  # an export takes minutes: say which phase runs
        if not args.quiet:
            print(f"torchrow: export: {name} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)

    try:
        to_onnx(out, height=height, width=width, batch=args.batch, params=params, opset=args.opset,
                tracker=args.tracker, control_flow=not args.no_control_flow, scatter_free=args.scatter_free,
                progress=phase)
    except ValueError as exc:
        raise CLIError(str(exc)) from None
    info = model_info(out)
    ops = ", ".join(f"{k} {v}" for k, v in sorted(info["ops"].items()))
    what = ("lattice tracker step: frames + active + state" if improved else
            "tracker step: frames + k_table + active + state" if args.tracker else "images + veg_lab")
    print(f"torchrow: exported {out} in {time.perf_counter() - t0:.0f} s: {info['size'] / 2**20:.1f} MiB, "
          f"{what}, uint8 frames ({args.batch}, 3, {height}, {width}), "
          f"opset {info['opset']}, {sum(info['ops'].values())} nodes")
    print(f"ops: {ops}")
    return 0
