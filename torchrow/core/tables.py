"""Tables shared bit for bit by the reference and the tensor path.

ALGORITHM.md requires that both implementations see the same bits wherever a float decides a
discrete output. Three quantities are therefore computed exactly once, here:

* the CIE LAB value of every 8-bit sRGB colour (section 2): a ``(2**24, 3)`` float64 table
  built from :func:`kornia.color.rgb_to_lab` in float64. It is a table and not a direct call
  because kornia's float64 result for one colour depends on where that colour sits in the
  input tensor (SIMD tails and BLAS blocking; measured: 6 of ~90k random colours differ by
  1 ulp between layouts), so two calls on differently shaped inputs would not agree. The
  table is built in canonical slabs (one ``(1, 3, 256, 256)`` call per red value), cached on
  disk (about 400 MB, ``TORCHROW_CACHE`` or ``~/.cache/torchrow``), verified by a CRC-32
  recorded beside it, and memory-mapped;
* the Hough angle cosines and sines ``numpy.cos/sin(numpy.deg2rad(j))`` (section 5);
* the RANSAC hypothesis table ``numpy.random.default_rng(seed).random((trials, 2))``
  (section 7).
"""

from __future__ import annotations

import functools
import json
import os
import sys
import tempfile
import warnings
import zlib
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import torch

from torchrow.core.params import Params

__all__ = [
    "CacheWarning",
    "write_atomic",
    "lab_table",
    "lab_table_torch",
    "rgb_to_lab",
    "pack_rgb",
    "rgb_code",
    "hough_trig",
    "near_horizontal",
    "near_angle",
    "hough_pickable",
    "rho_offset",
    "rho_index_table",
    "hypothesis_table",
    "subsample_key",
    "cache_dir",
]

_N_COLORS = 1 << 24


def cache_dir() -> Path:
    """The folder of the shared caches (the LAB table, onnxruntime's optimised models):
    ``TORCHROW_CACHE``, else ``~/.cache/torchrow``."""
    env = os.environ.get("TORCHROW_CACHE")
    if env:
        return Path(env)
    return Path.home() / ".cache" / "torchrow"


def _table_name() -> str:
    import kornia
    import torch

    tv = torch.__version__.split("+")[0]
    return f"lab_f64_torch{tv}_kornia{kornia.__version__}.npy"


def _build_lab_table(out: np.ndarray) -> None:
    """Fill ``out`` (2**24, 3) float64 slab by slab: one kornia call per red value."""
    import kornia
    import torch
    from tqdm.auto import tqdm

    gb = torch.arange(256, dtype=torch.float64)
    g = gb.view(256, 1).expand(256, 256)
    b = gb.view(1, 256).expand(256, 256)
    with torch.no_grad():
        for r in tqdm(range(256), desc="torchrow: building LAB table (once)", file=sys.stderr,
                      leave=False, disable=None):
            rgb = torch.stack([torch.full((256, 256), float(r), dtype=torch.float64), g, b])
            lab = kornia.color.rgb_to_lab((rgb / 255.0).unsqueeze(0))[0]  # (3, 256, 256)
            out[r << 16:(r + 1) << 16] = lab.reshape(3, -1).T.numpy()


class CacheWarning(UserWarning):
    """The on-disk LAB table was damaged (and is rebuilt) or cannot be written (built in memory)."""


def _check_path(path: Path) -> Path:
    """The verification record beside the table: ``<table>.check`` (JSON)."""
    return path.with_name(path.name + ".check")


def _crc32(path: Path) -> int:
    """CRC-32 of a whole file, read in 16 MiB blocks (bounded memory, ~0.4 s for the table)."""
    crc = 0
    with open(path, "rb") as fh:
        while block := fh.read(1 << 24):
            crc = zlib.crc32(block, crc)
    return crc


def _stamp(path: Path) -> dict:
    """What says that a file is the one last verified. ``ctime_ns`` (inode change time) is set
    by the kernel on every write and on every ``utime``, so a table changed in place with its
    modification time put back is caught too; a check record without it (older torchrow)
    means one full verification."""
    st = path.stat()
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "ctime_ns": st.st_ctime_ns, "inode": st.st_ino}


def write_atomic(path: Path, write) -> None:
    """``write(file)`` into a temporary file beside ``path``, then rename it over ``path``
    (mode 0644: the cache is meant to be shared). The temporary file never outlives a failure."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _record_check(path: Path, crc: int) -> None:
    record = {"crc32": crc, **_stamp(path)}
    write_atomic(_check_path(path), lambda fh: fh.write(json.dumps(record).encode()))


def _damage(path: Path) -> str | None:
    """Why the cached table at ``path`` cannot be used (``None``: it is sound).

    Cheap when nothing changed: the size, modification and inode change times and inode
    recorded beside the table at its last verification are compared with the file's
    (:func:`_stamp`). Otherwise the file's CRC-32 is recomputed (0.4 s) and compared with the
    recorded one, and the new stamp is recorded.
    """
    try:
        record = json.loads(_check_path(path).read_text())
        crc, size = int(record["crc32"]), int(record["size"])
    except FileNotFoundError:
        return f"no verification record {_check_path(path).name} beside it"
    except (OSError, ValueError, KeyError, TypeError):
        return f"its verification record {_check_path(path).name} is unreadable"
    stamp = _stamp(path)
    if stamp["size"] != size:
        return f"it has {stamp['size']} bytes, {size} expected"
    if stamp == {k: record.get(k) for k in stamp}:
        return None
    if _crc32(path) != crc:
        return "its checksum does not match"
    try:
        _record_check(path, crc)  # verified: the next load is cheap again
    except OSError:
        pass
    return None


def _open_cached(path: Path) -> tuple[np.ndarray | None, str | None]:
    """The verified memory-mapped table, or ``(None, why it is unusable)`` (``why`` is
    ``None`` when there is no file at all)."""
    if not path.exists():
        return None, None
    try:
        why = _damage(path)
        if why is None:
            table = np.load(path, mmap_mode="r")
            if table.shape == (_N_COLORS, 3) and table.dtype == np.float64:
                return table, None
            why = f"it holds {table.dtype} {table.shape}, float64 ({_N_COLORS}, 3) expected"
    except Exception as exc:  # empty or truncated file, bad header: all mean "rebuild"
        why = f"{type(exc).__name__}: {exc}"
    return None, why


@functools.lru_cache(maxsize=1)
def lab_table() -> np.ndarray:
    """LAB of every 8-bit sRGB colour, ``(2**24, 3)`` float64, index ``(R<<16)|(G<<8)|B``.

    Read-only memory map of the on-disk cache (``TORCHROW_CACHE`` or ``~/.cache/torchrow``),
    verified against the CRC-32 recorded beside it (:func:`_damage`). A missing or damaged
    table is built (~10 s on 2 cores; one line on stderr says so and where) and written
    atomically with mode 0644; a damaged one is reported by a one-line :class:`CacheWarning`.
    If the folder cannot be written, one :class:`CacheWarning` says so and the table lives
    in memory for this process (400 MB).
    """
    path = cache_dir() / _table_name()
    table, why = _open_cached(path)
    if table is not None:
        return table
    if why is not None:
        warnings.warn(f"torchrow: the cached LAB table {path} cannot be used ({why}); rebuilding it",
                      CacheWarning, stacklevel=2)
    print(f"torchrow: building the shared LAB table (once, about 10 s): {path}", file=sys.stderr)
    table = np.empty((_N_COLORS, 3), dtype=np.float64)
    _build_lab_table(table)
    table.setflags(write=False)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, lambda fh: np.save(fh, table))
        _record_check(path, _crc32(path))
    except OSError as exc:
        warnings.warn(f"torchrow: cannot write the LAB table to {path.parent} ({exc}); it is kept in memory "
                      "for this process only (set TORCHROW_CACHE to a writable folder)", CacheWarning, stacklevel=2)
        return table
    mapped, _ = _open_cached(path)
    return mapped if mapped is not None else table


_TORCH_TABLES: dict = {}


def lab_table_torch(device: str | torch.device = "cpu"):
    """The LAB table as a torch ``(2**24, 3)`` float64 tensor on ``device`` (cached per device).

    On the CPU it shares memory with the memory map (no copy); elsewhere it is copied once.
    """
    import torch

    dev = torch.device(device)
    key = str(dev)
    t = _TORCH_TABLES.get(key)
    if t is None or torch.compiler.is_exporting():  # never cache a tensor traced by torch.export
        base = _TORCH_TABLES.get("cpu")
        if base is None:
            table = lab_table()  # outside the filter below: its CacheWarning must be seen
            with warnings.catch_warnings():  # read-only memory map: torch never writes to it
                warnings.filterwarnings("ignore", message="The given NumPy array is not writable",
                                        category=UserWarning)
                base = torch.from_numpy(table)
            if not torch.compiler.is_exporting():
                _TORCH_TABLES["cpu"] = base
        t = base if dev.type == "cpu" else base.to(dev)
        if not torch.compiler.is_exporting():
            _TORCH_TABLES[key] = t
    return t


def rgb_code(r: Any, g: Any, b: Any) -> Any:
    """The 24-bit colour code ``(R<<16)|(G<<8)|B`` (the row of the LAB table) of channels ``r``,
    ``g``, ``b`` in ``0..255``: NumPy arrays, tensors or numbers of an integer type that holds
    ``2**24`` (widen ``uint8`` first), broadcast together.

    Written as products and sums, equal for such values: ONNX's ``BitShift`` takes unsigned
    types only, and the exported graphs compute the code with this function too."""
    return r * 65536 + g * 256 + b


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """``(..., 3)`` uint8 RGB -> ``(...)`` int64 colour code (:func:`rgb_code`)."""
    rgb = np.asarray(rgb).astype(np.int64)
    return rgb_code(rgb[..., 0], rgb[..., 1], rgb[..., 2])


def rgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """The shared LAB function: ``(..., 3)`` uint8 sRGB -> ``(..., 3)`` float64 L*a*b* (D65).

    Equals ``kornia.color.rgb_to_lab`` in float64 on the colour's canonical slab and agrees
    with ``skimage.color.rgb2lab`` to about 3e-13.
    """
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim < 1 or rgb.shape[-1] != 3:
        raise ValueError(f"rgb_to_lab expects uint8 (..., 3); got {rgb.dtype} {rgb.shape}")
    return lab_table()[pack_rgb(rgb)]


def rho_offset(height: int, width: int) -> int:
    """``D = ceil(sqrt(H^2 + W^2))``: the accumulator row of ``rho`` is ``rho + D`` (section 5)."""
    import math

    return math.ceil(math.sqrt(height * height + width * width))


@functools.lru_cache(maxsize=8)
def hough_trig(theta_step: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``(cos, sin)`` of the Hough angles ``j * theta_step`` degrees, each ``(180/step,)`` float64."""
    theta = np.deg2rad(np.arange(0, 180, theta_step, dtype=np.float64))
    c, s = np.cos(theta), np.sin(theta)
    c.setflags(write=False)
    s.setflags(write=False)
    return c, s


def near_horizontal(deg: Any, horizontal_excl: int) -> Any:
    """Step 5.1's fixed rule: Hough angles ``deg`` (degrees: a number, a NumPy array or a
    tensor) with ``|deg - 90| < horizontal_excl`` are never picked (a bool of ``deg``'s kind).

    One rule for the reference, the eager and the static voters (which vote only the other
    angles, :func:`hough_pickable`)."""
    return abs(deg - 90) < horizontal_excl


def near_angle(deg: Any, held_deg: Any, angle_excl: int) -> Any:
    """Step 5.1's rule around a held line: angles ``deg`` with ``|deg - held_deg| < angle_excl``
    (degrees, on the integer grid, no wrap-around at 0/180) are not picked while it is held."""
    return abs(deg - held_deg) < angle_excl


@functools.lru_cache(maxsize=8)
def hough_pickable(theta_step: int, horizontal_excl: int) -> np.ndarray:
    """Indices ``j`` of the Hough angles ``j * theta_step`` that are not :func:`near_horizontal`,
    int64 ``(A,)``: the only angles step 5.1 ever lets be a peak (read-only)."""
    deg = np.arange(180 // theta_step, dtype=np.int64) * theta_step
    out = np.flatnonzero(~near_horizontal(deg, horizontal_excl)).astype(np.int64)
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=4)
def rho_index_table(height: int, width: int, theta_step: int = 1) -> np.ndarray:
    """Accumulator row of every pixel for every angle: ``rint(x*c_j + y*s_j) + D``.

    ``(n_theta, H*W)`` int16 (int32 if the accumulator is taller than int16 allows), raster
    pixel order. Computed with NumPy exactly as the reference votes (float64, products then
    sum, round half to even). 28 MB at 320x240; 442 MB at 1280x960.
    """
    c, s = hough_trig(theta_step)
    d = rho_offset(height, width)
    ys, xs = np.divmod(np.arange(height * width, dtype=np.int64), width)
    dtype = np.int16 if 2 * d + 1 < 2**15 else np.int32
    out = np.empty((len(c), height * width), dtype)
    for j in range(len(c)):  # row by row: bounded float64 temporaries
        out[j] = np.rint(xs * c[j] + ys * s[j]).astype(np.int64) + d
    out.setflags(write=False)
    return out


def hough_theta(params: Params) -> np.ndarray:
    """Hough angles in radians, ``(n_theta,)`` float64 (``numpy.deg2rad(j * step)``)."""
    return np.deg2rad(np.arange(0, 180, params.theta_step, dtype=np.float64))


@functools.lru_cache(maxsize=8)
def hypothesis_table(seed: int = 0, trials: int = 1000) -> np.ndarray:
    """RANSAC hypothesis table ``U``, ``(trials, 2)`` float64 in [0, 1), shared by all rows."""
    u = np.random.default_rng(seed).random((trials, 2))
    u.setflags(write=False)
    return u


def subsample_key(x: np.ndarray, y: np.ndarray, width: int, mult: int = 2654435761) -> np.ndarray:
    """Subsampling key ``((y*W + x) * mult) mod 2**32`` as int64 (section 7.2)."""
    lin = y.astype(np.int64) * width + x.astype(np.int64)
    return (lin * mult) & 0xFFFFFFFF
