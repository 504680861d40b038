"""Loaders for the Crop Row Benchmark Dataset (CRBD) and the Crop Row Detection Lincoln Dataset
(CRDLD), each in its authors' layout.

CRBD
----

Layout (the folder given, or its ``crbd/`` sub-folder)::

    Images/crop_row_NNN.JPG | .jpg      281 RGB images, 320 x 240 (extension case varies)
    Images/imageClassification.txt      name<TAB>set, 1 = straight rows, 2 = curved rows
    Images/imageClassificationTMGEM.txt name<TAB>set, 0 = TMGEM training, 1/2 = test
    GT data/crop_row_NNN.crp            c_v<TAB>d_v for image rows v0 .. H-1
    TMGEM results/crop_row_NNN.tmg      H lines x 3 columns: x of 3 adjacent rows (TMGEM)

Only ``Images/`` and ``GT data/`` are required. The classification files and the TMGEM
results are read on first use; when absent, only the methods that need them raise.

CRDLD (:class:`CRDLD`): a split folder holding ``image/N.jpg`` (RGB) and ``label/N.jpg``
(white polyline masks at any size), or a folder holding ``train/`` and ``test/`` split
folders, or a data folder holding ``crdld_dev/``.

The data location is never hard-coded: pass it, or set ``TORCHROW_DATA`` (see
:func:`resolve_data_root`).
"""

from __future__ import annotations

import operator
import os
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

import numpy as np

from torchrow.core.io import IMAGE_EXTENSIONS
from torchrow.core.params import Params

if TYPE_CHECKING:
    from torchrow.evaluation.crdld import CRDLDTruth

__all__ = ["ENV_VAR", "SUBSETS", "CRDLD_SPLITS", "resolve_data_root", "GroundTruth", "CRBDItem", "CRBD",
           "CRDLDItem", "CRDLD"]

#: Environment variable naming the data folder (or the CRBD folder itself).
ENV_VAR = "TORCHROW_DATA"

#: Subsets accepted by :meth:`CRBD.indices`.
SUBSETS = ("all", "straight", "curved", "train", "test")

_LAYOUT = ("Images/crop_row_NNN.JPG|jpg, GT data/crop_row_NNN.crp, "
           "TMGEM results/crop_row_NNN.tmg")
#: Splits of :class:`CRDLD`.
CRDLD_SPLITS = ("train", "test")
_CRDLD_LAYOUT = "image/N.jpg and label/N.jpg"
_CRDLD_DIR = "crdld_dev"
_IMAGE_RE = re.compile(r"^(crop_row_(\d+))\.jpe?g$", re.IGNORECASE)
_ROW_SET_FILE = "imageClassification.txt"
_TMGEM_SET_FILE = "imageClassificationTMGEM.txt"


def resolve_data_root(root: str | os.PathLike[str] | None = None) -> Path:
    """Data folder: ``root`` if given, else the ``TORCHROW_DATA`` environment variable.

    Parameters
    ----------
    root : str or path-like, optional
        Explicit location; wins over the environment.

    Returns
    -------
    pathlib.Path
        The location (``~`` expanded). Its existence is not checked here.

    Raises
    ------
    FileNotFoundError
        If neither ``root`` nor a non-empty ``TORCHROW_DATA`` is given.
    """
    if root is not None and str(root) != "":
        return Path(root).expanduser()
    env = os.environ.get(ENV_VAR, "")
    if env:
        return Path(env).expanduser()
    raise FileNotFoundError(
        f"no data location: pass the data folder (root=...) or set the {ENV_VAR} environment variable")


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """Ground-truth crop-row parameters of one CRBD image (one ``.crp`` file).

    Attributes
    ----------
    c : numpy.ndarray, shape (height - v0,), float64
        Offset (px) of the central crop row from the image centre ``W/2``, image rows
        ``v0 .. height-1``.
    d : numpy.ndarray, shape (height - v0,), float64
        Spacing (px) between adjacent crop rows, same image rows.
    v0 : int
        First image row (0-based) where crop rows are visible: ``height - len(c)``.
    height : int
        Image height in pixels (240 for CRBD).
    """

    c: np.ndarray
    d: np.ndarray
    v0: int
    height: int

    def __repr__(self) -> str:
        return f"GroundTruth(v0={self.v0}, height={self.height}, rows={len(self.c)})"

    def centre_x(self, shift: int = 0, width: int = 320) -> np.ndarray:
        """x (px, 0-based column) of ground-truth row ``shift`` for rows ``v0 .. height-1``.

        ``shift = 0`` is the central row, ``-1``/``+1`` its left/right neighbours.
        Returns shape ``(height - v0,)`` float64.
        """
        return self.c + shift * self.d + width / 2


@dataclass(frozen=True)
class CRBDItem:
    """One CRBD image: paths and small metadata (the image itself is not loaded).

    Attributes
    ----------
    name : str
        Image file name as on disk (``crop_row_004.jpg``).
    stem : str
        ``crop_row_NNN``.
    image_path : pathlib.Path
    ground_truth : GroundTruth
    row_set : int or None
        1 straight / 2 curved rows; None when the classification is not available.
    tmgem_set : int or None
        0 TMGEM training, 1 test straight, 2 test curved; None when not available.
    """

    name: str
    stem: str
    image_path: Path
    ground_truth: GroundTruth
    row_set: int | None
    tmgem_set: int | None


def _jpeg_size(path: Path) -> tuple[int, int] | None:
    """``(width, height)`` from a JPEG's SOF header, or None if it cannot be parsed."""
    try:
        with open(path, "rb") as f:
            if f.read(2) != b"\xff\xd8":
                return None
            while True:
                b = f.read(1)
                while b and b != b"\xff":
                    b = f.read(1)
                while b == b"\xff":
                    b = f.read(1)
                if not b:
                    return None
                marker = b[0]
                if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
                    continue
                seg = f.read(2)
                if len(seg) != 2:
                    return None
                (length,) = struct.unpack(">H", seg)
                if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                    data = f.read(5)
                    if len(data) != 5:
                        return None
                    h, w = struct.unpack(">HH", data[1:5])
                    return (w, h) if w > 0 and h > 0 else None
                f.seek(length - 2, 1)
    except OSError:
        return None


def _read_set_file(path: Path) -> dict[str, int]:
    """``name<TAB>set`` lines -> {lower-case stem: set}."""
    out: dict[str, int] = {}
    for k, line in enumerate(path.read_text().splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 2:
            raise ValueError(f"{path}:{k}: expected 'name<TAB>set', got {line!r}")
        out[Path(parts[0]).stem.lower()] = int(parts[1])
    return out


class CRBD:
    """The Crop Row Benchmark Dataset, items sorted by image number.

    Parameters
    ----------
    root : str or path-like, optional
        The CRBD folder (holding ``Images/``, ``GT data/``, ``TMGEM results/``) or a data
        folder containing ``crbd/``. Default: ``TORCHROW_DATA`` (:func:`resolve_data_root`).

    Attributes
    ----------
    root : pathlib.Path
        The CRBD folder itself.
    names : list of str
        Image file names as on disk (extension case preserved).
    stems : list of str
        ``crop_row_NNN`` for each item.

    Raises
    ------
    FileNotFoundError
        One line naming the expected layout and the path given, when the folder does not
        hold CRBD (no ``Images/`` with ``crop_row_NNN.jpg`` files, or a missing ``.crp``).
    """

    def __init__(self, root: str | os.PathLike[str] | None = None) -> None:
        given = resolve_data_root(root)
        base = None
        for cand in (given, given / "crbd"):
            if (cand / "Images").is_dir():
                base = cand
                break
        if base is None:
            self._layout_error(given, "no Images/ folder")
        self.root = base
        self._images = base / "Images"
        self._gt_dir = base / "GT data"
        self._tmgem_dir = base / "TMGEM results"
        found: list[tuple[int, str, str]] = []
        for p in self._images.iterdir():
            m = _IMAGE_RE.match(p.name)
            if m and p.is_file():
                found.append((int(m.group(2)), p.name, m.group(1)))
        if not found:
            self._layout_error(given, "no crop_row_NNN.jpg images in Images/")
        found.sort()
        self.names: list[str] = [n for _, n, _ in found]
        self.stems: list[str] = [s for _, _, s in found]
        if len(set(s.lower() for s in self.stems)) != len(self.stems):
            self._layout_error(given, "duplicate image numbers in Images/")
        missing = [s for s in self.stems if not self._gt_path(s).is_file()]
        if missing:
            self._layout_error(given, f"{len(missing)} ground-truth file(s) missing, e.g. "
                                      f"'GT data/{missing[0]}.crp'")
        self._row_sets: dict[str, int] | None = None
        self._tmgem_sets: dict[str, int] | None = None
        self._gt_cache: dict[int, GroundTruth] = {}

    @staticmethod
    def _layout_error(given: Path, why: str) -> NoReturn:
        raise FileNotFoundError(
            f"not a CRBD folder ({why}): expected {_LAYOUT} under {str(given)!r} "
            f"or under its 'crbd/' sub-folder")

    # --- paths -------------------------------------------------------------------------
    def _gt_path(self, stem: str) -> Path:
        return self._gt_dir / f"{stem}.crp"

    def _tmgem_path(self, stem: str) -> Path:
        return self._tmgem_dir / f"{stem}.tmg"

    def image_path(self, i: int) -> Path:
        """Path of image ``i``."""
        return self._images / self.names[self._index(i)]

    def _index(self, i: int) -> int:
        n = len(self.names)
        if isinstance(i, (bool, np.bool_)) or not hasattr(i, "__index__"):  # 1.5 is not image 1
            raise TypeError(f"CRBD index must be an integer, got {type(i).__name__} {i!r}")
        i = operator.index(i)
        if not -n <= i < n:
            raise IndexError(f"CRBD index {i} out of range for {n} images")
        return i % n

    # --- sequence ----------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, i: int) -> CRBDItem:
        i = self._index(i)
        return CRBDItem(
            name=self.names[i], stem=self.stems[i], image_path=self.image_path(i),
            ground_truth=self.ground_truth(i), row_set=self._lookup(i, tmgem=False, strict=False),
            tmgem_set=self._lookup(i, tmgem=True, strict=False))

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    def __repr__(self) -> str:
        return f"CRBD({str(self.root)!r}, {len(self)} images)"

    # --- content -----------------------------------------------------------------------
    def image(self, i: int) -> np.ndarray:
        """Image ``i`` as ``uint8 (H, W, 3)`` RGB (:func:`torchrow.core.io.load_image`)."""
        from torchrow.core.io import load_image

        return load_image(self.image_path(i))

    def image_size(self, i: int) -> tuple[int, int]:
        """``(width, height)`` of image ``i`` in pixels, from the JPEG header when possible."""
        p = self.image_path(i)
        size = _jpeg_size(p)
        if size is None:
            h, w = self.image(i).shape[:2]
            size = (w, h)
        return size

    def ground_truth(self, i: int) -> GroundTruth:
        """Ground truth of image ``i`` (``GT data/<stem>.crp``); see :class:`GroundTruth`.

        ``height`` is the image's own height (read from its header; 240 for CRBD).

        Raises
        ------
        ValueError
            If the file is malformed or has more lines than the image has rows.
        """
        i = self._index(i)
        gt = self._gt_cache.get(i)
        if gt is not None:
            return gt
        path = self._gt_path(self.stems[i])
        arr = np.loadtxt(path, dtype=np.float64, ndmin=2)
        if arr.size == 0:
            arr = arr.reshape(0, 2)
        if arr.ndim != 2 or arr.shape[1] != 2:
            raise ValueError(f"{path}: expected lines of 'c<TAB>d', got shape {arr.shape}")
        height = self.image_size(i)[1]
        if arr.shape[0] > height:
            raise ValueError(f"{path}: {arr.shape[0]} lines for an image of {height} rows")
        c = np.ascontiguousarray(arr[:, 0])
        d = np.ascontiguousarray(arr[:, 1])
        c.flags.writeable = False
        d.flags.writeable = False
        gt = GroundTruth(c=c, d=d, v0=height - arr.shape[0], height=height)
        self._gt_cache[i] = gt
        return gt

    def tmgem(self, i: int) -> np.ndarray:
        """TMGEM's own detection for image ``i``: ``(H, 3)`` float64, x (px) of 3 rows per image row.

        Raises
        ------
        FileNotFoundError
            If ``TMGEM results/<stem>.tmg`` is absent.
        """
        i = self._index(i)
        path = self._tmgem_path(self.stems[i])
        if not path.is_file():
            raise FileNotFoundError(f"TMGEM result not found: {path}")
        arr = np.loadtxt(path, dtype=np.float64, ndmin=2)
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise ValueError(f"{path}: expected 3 columns, got shape {arr.shape}")
        return arr

    # --- classifications ---------------------------------------------------------------
    def _sets(self, tmgem: bool) -> dict[str, int]:
        attr = "_tmgem_sets" if tmgem else "_row_sets"
        table = getattr(self, attr)
        if table is None:
            path = self._images / (_TMGEM_SET_FILE if tmgem else _ROW_SET_FILE)
            if not path.is_file():
                raise FileNotFoundError(f"classification file not found: {path}")
            table = _read_set_file(path)
            setattr(self, attr, table)
        return table

    def _lookup(self, i: int, tmgem: bool, strict: bool = True) -> int | None:
        try:
            table = self._sets(tmgem)
        except (FileNotFoundError, ValueError):
            if strict:
                raise
            return None
        stem = self.stems[i]
        v = table.get(stem.lower())
        if v is None and strict:
            what = _TMGEM_SET_FILE if tmgem else _ROW_SET_FILE
            raise KeyError(f"{stem} is not listed in Images/{what}")
        return v

    def row_set(self, i: int) -> int:
        """1 if image ``i`` has straight rows, 2 if curved (``Images/imageClassification.txt``).

        Raises
        ------
        FileNotFoundError
            If the classification file is absent.
        KeyError
            If the image is not listed there.
        """
        return int(self._lookup(self._index(i), tmgem=False))  # type: ignore[arg-type]

    def tmgem_set(self, i: int) -> int:
        """0 = TMGEM training, 1 = test straight, 2 = test curved (``imageClassificationTMGEM.txt``);
        raises as :meth:`row_set` does."""
        return int(self._lookup(self._index(i), tmgem=True))  # type: ignore[arg-type]

    def indices(self, subset: str = "all") -> list[int]:
        """Item indices (ascending) of a subset.

        Parameters
        ----------
        subset : {"all", "straight", "curved", "train", "test"}
            ``straight``/``curved`` follow ``imageClassification.txt`` (sets 1/2);
            ``train``/``test`` follow ``imageClassificationTMGEM.txt`` (set 0 / sets 1-2).
            Images missing from the file belong to neither.

        Raises
        ------
        ValueError
            For an unknown subset name.
        FileNotFoundError
            If the needed classification file is absent.
        """
        if subset == "all":
            return list(range(len(self)))
        if subset in ("straight", "curved"):
            want: tuple[int, ...]
            table, want = self._sets(False), {"straight": (1,), "curved": (2,)}[subset]
        elif subset in ("train", "test"):
            table, want = self._sets(True), {"train": (0,), "test": (1, 2)}[subset]
        else:
            raise ValueError(f"unknown subset {subset!r}; expected one of {', '.join(SUBSETS)}")
        return [i for i, s in enumerate(self.stems) if table.get(s.lower()) in want]


@dataclass(frozen=True)
class CRDLDItem:
    """One CRDLD image: paths and its ground truth.

    Attributes
    ----------
    name : str
        Image file name (``12.jpg``).
    image_path, label_path : pathlib.Path
    ground_truth : CRDLDTruth
        Labelled lines in the image's own pixels (:func:`torchrow.evaluation.crdld.truth_from_mask`).
    """

    name: str
    image_path: Path
    label_path: Path
    ground_truth: CRDLDTruth


def _number_key(path: Path) -> tuple[int, int, str]:
    """Numeric file names first, by number (0, 1, 2, ..., 10), then the others by name."""
    stem = path.stem
    return (0, int(stem), path.name) if stem.isdigit() else (1, 0, path.name)


class CRDLD:
    """A split of the Crop Row Detection Lincoln Dataset, items sorted by image number.

    Parameters
    ----------
    root : str or path-like, optional
        A split folder holding ``image/`` and ``label/``; or a folder holding ``train/`` and
        ``test/`` split folders; or a data folder holding ``crdld_dev/`` with them. Default:
        ``TORCHROW_DATA`` (:func:`resolve_data_root`).
    split : {"test", "train"}
        The split taken where ``root`` holds split folders.

    Attributes
    ----------
    root : pathlib.Path
        The split folder itself.
    names : list of str
        Image file names (``N.jpg``).

    Raises
    ------
    FileNotFoundError
        One line naming the expected layout and the path given, when no folder there holds
        ``image/`` and ``label/``, when ``image/`` has no images, or when an image has no label
        (``label/<stem>.*``).
    ValueError
        For an unknown split.
    """

    def __init__(self, root: str | os.PathLike[str] | None = None, split: str = "test") -> None:
        if split not in CRDLD_SPLITS:
            raise ValueError(f"unknown CRDLD split {split!r}; expected one of {', '.join(CRDLD_SPLITS)}")
        given = resolve_data_root(root)
        base = next((c for c in (given, given / split, given / _CRDLD_DIR / split)
                     if (c / "image").is_dir() and (c / "label").is_dir()), None)
        if base is None:
            self._layout_error(given, split, "no image/ and label/ folders")
        self.root = base
        self.split = split
        images = sorted((p for p in (base / "image").iterdir()
                         if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS), key=_number_key)
        if not images:
            self._layout_error(given, split, "no images in image/")
        labels: dict[str, Path] = {}
        for p in sorted((base / "label").iterdir()):
            if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS:
                labels.setdefault(p.stem, p)
        missing = [p.name for p in images if p.stem not in labels]
        if missing:
            self._layout_error(given, split, f"{len(missing)} label(s) missing, e.g. for image/{missing[0]}")
        self._images = images
        self._labels = [labels[p.stem] for p in images]
        self.names: list[str] = [p.name for p in images]
        self._gt_cache: dict[int, CRDLDTruth] = {}

    @staticmethod
    def _layout_error(given: Path, split: str, why: str) -> NoReturn:
        raise FileNotFoundError(
            f"not a CRDLD folder ({why}): expected {_CRDLD_LAYOUT} under {str(given)!r}, its "
            f"'{split}/' or its '{_CRDLD_DIR}/{split}/' sub-folder")

    def _index(self, i: int) -> int:
        n = len(self.names)
        i = int(i)
        if not -n <= i < n:
            raise IndexError(f"CRDLD index {i} out of range for {n} images")
        return i % n

    def image_path(self, i: int) -> Path:
        """Path of image ``i``."""
        return self._images[self._index(i)]

    def label_path(self, i: int) -> Path:
        """Path of the label mask of image ``i``."""
        return self._labels[self._index(i)]

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, i: int) -> CRDLDItem:
        i = self._index(i)
        return CRDLDItem(self.names[i], self._images[i], self._labels[i], self.ground_truth(i))

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    def __repr__(self) -> str:
        return f"CRDLD({str(self.root)!r}, {len(self)} images)"

    def image(self, i: int, width: int | None = Params.image_width) -> np.ndarray:
        """Image ``i`` as ``uint8 (h, w, 3)`` RGB, resized to ``width`` as the detector does
        (default the working width, 320: what a detector takes); ``width=None`` keeps the
        stored size, the pixels of :meth:`ground_truth`."""
        from torchrow.core.io import load_image

        return load_image(self.image_path(i), width)

    def image_size(self, i: int) -> tuple[int, int]:
        """``(width, height)`` of image ``i`` as stored (px), from the JPEG header when possible."""
        size = _jpeg_size(self.image_path(i))
        if size is None:
            h, w = self.image(i, None).shape[:2]
            size = (w, h)
        return size

    def ground_truth(self, i: int) -> CRDLDTruth:
        """Labelled lines of image ``i`` in its stored pixels (the mask scaled to the image size);
        computed once per dataset object.

        Raises
        ------
        ValueError
            If the label cannot be decoded.
        """
        import cv2

        from torchrow.evaluation.crdld import truth_from_mask

        i = self._index(i)
        gt = self._gt_cache.get(i)
        if gt is None:
            path = self._labels[i]
            mask = cv2.imdecode(np.fromfile(path, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
            if mask is None:
                raise ValueError(f"cannot decode label mask: {path}")
            w, h = self.image_size(i)
            gt = truth_from_mask(mask, w, h)
            self._gt_cache[i] = gt
        return gt
