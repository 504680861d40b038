"""onnxruntime vs torch on every CRBD image, with an exported model (the heavy test's check as a
script that prints progress): ``python benchmarks/onnx_parity_all.py MODEL.onnx [--data DIR]``.

Records must be identical (discrete outputs equal, rows within 1e-4 px). Run from the
repository root (it reuses ``tests/test_export.py``'s comparison).
"""

import argparse
import sys
import time

import numpy as np
import torch

sys.path.insert(0, 'tests')
from test_export import _same

from torchrow.engines.detector import CropRowDetector
from torchrow.evaluation.datasets import CRBD
from torchrow.onnx.runtime import OnnxDetector

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("model")
ap.add_argument("--data", default=None)
args = ap.parse_args()
ds = CRBD(args.data)
det = OnnxDetector(args.model)
tdet = CropRowDetector()
problems = []
n = 0
t0 = time.time()
for s in range(0, len(ds), 32):
    idx = list(range(s, min(len(ds), s + 32)))
    x = torch.from_numpy(np.stack([ds.image(i) for i in idx])).permute(0, 3, 1, 2).contiguous()
    names = [ds.names[i] for i in idx]
    p = _same(tdet(x).results(names), det(x).results(names))
    problems += p
    n += len(idx)
    print(f"{n} images, {len(problems)} differences, {time.time()-t0:.0f} s", flush=True)
print("DONE", n, "images;", len(problems), "differences", problems[:10])
