"""Batched tensor stages of ALGORITHM.md, kornia-style functional ops.

Conventions shared by every stage module (:mod:`.sky`, :mod:`.color`, :mod:`.vegetation`,
:mod:`.hough`, :mod:`.vanishing`, :mod:`.ransac`, :mod:`.lattice`), mirroring
:mod:`torchrow.reference`; the OpenCV-exact image kernels they compose are in :mod:`.kernels`;
:mod:`.camera` batches the metric steering of :mod:`torchrow.core.camera`:

* images are ``uint8 (B, 3, H, W)`` RGB; masks are ``bool (B, H, W)``; per-image scalars
  (``sky``, ``k``) are ``int64 (B,)``; the vegetation colour is ``uint8 (B, 3)``;
* no Python loop over images, no ``.item()``/``nonzero`` inside a stage; loops have static
  bounds with masks for finished images (an early exit once every image is finished is
  allowed outside ONNX export);
* device- and dtype-agnostic: outputs live on the input's device; every float comparison
  that decides a discrete output is float64 and written exactly as in the spec;
* results equal the reference's for every image, whatever else shares the batch.
"""

from torchrow.functional import camera, color, hough, kernels, lattice, ransac, sky, vanishing, vegetation

__all__ = ["kernels", "sky", "color", "vegetation", "hough", "vanishing", "ransac", "lattice", "camera"]
