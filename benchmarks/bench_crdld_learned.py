"""What a small learned row mask buys the improved mode on a forward camera (ALGORITHM.md 11.6).

    python benchmarks/bench_crdld_learned.py [--data DIR] [--eval val|test] [--epochs 60] [--net small|wide]

Trains an encoder-decoder on the CPU to predict the CRDLD label masks at a quarter of the
working size (320 x 320): ``small`` (the default; 4 stride-2 levels on the half-size image, 66k
weights, about 3 s an epoch here) or ``wide`` (5 stride-2 levels of two batch-normalised
convolutions on the full working image with its pixel coordinates as two more channels, 419k
weights, about 18 s an epoch), then runs the
improved mode (forward-camera setting, tensor path) with each image's predicted mask as its
row evidence (11.1.1: logit above ``--threshold``), beside the green mask (11.1) and the label
mask itself (the best any evidence can do through sections 11.2-11.4). Scored with 10.1's
score at sigma 0.1 and 0.3.

``--eval val`` (the default) trains on the ``crdld_dev/train`` images whose index is not a
multiple of 5 and scores the other fifth; ``--eval test`` trains on all of ``train`` and scores
``test``: run it once, after every choice is made on ``val``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from torchrow.core.params import FORWARD_CAMERA, Params
from torchrow.evaluation.crdld import label_mask, score_image
from torchrow.evaluation.datasets import CRDLD

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import data_root


def conv(cin: int, cout: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, stride, 1)


class RowNet(nn.Module):
    """``float (B, 3, H, W)`` in [-0.5, 0.5] -> row logits ``(B, 1, H/4, W/4)`` (about)."""

    def __init__(self, widths: tuple[int, int, int, int] = (16, 24, 32, 32)) -> None:
        super().__init__()
        a, b, c, e = widths
        self.c1, self.c2, self.c3, self.c4, self.c5 = conv(3, a, 2), conv(a, b, 2), conv(b, c, 2), conv(c, e, 2), conv(e, e)
        self.d3, self.d2, self.d1 = conv(e + c, c), conv(c + b, b), conv(b + a, a)
        self.out = nn.Conv2d(a, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x1 = F.relu(self.c1(F.avg_pool2d(x, 2)))
        x2 = F.relu(self.c2(x1))
        x3 = F.relu(self.c3(x2))
        u = F.relu(self.c5(F.relu(self.c4(x3))))
        for skip, layer in ((x3, self.d3), (x2, self.d2), (x1, self.d1)):
            u = F.relu(layer(torch.cat([F.interpolate(u, size=skip.shape[-2:], mode="nearest"), skip], 1)))
        return self.out(u)


def _conv_bn(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class WideRowNet(nn.Module):
    """``float (B, 3, H, W)`` in [-0.5, 0.5] -> row logits ``(B, 1, H/4, W/4)`` (about). The
    image's normalised row and column are two more input channels: where a row lies says how
    far ahead it is, so how wide and how steep a crop row looks there."""

    def __init__(self, widths: tuple[int, ...] = (16, 32, 48, 64, 96)) -> None:
        super().__init__()
        self.enc = nn.ModuleList()
        prev = 5
        for c in widths:
            self.enc.append(nn.Sequential(_conv_bn(prev, c, 2), _conv_bn(c, c)))
            prev = c
        self.dec = nn.ModuleList([_conv_bn(widths[i + 1] + widths[i], widths[i]) for i in range(len(widths) - 2, 0, -1)])
        self.out = nn.Conv2d(widths[1], 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, _, h, w = x.shape
        yy = torch.linspace(-1, 1, h, device=x.device, dtype=x.dtype).view(1, 1, h, 1).expand(b, 1, h, w)
        xx = torch.linspace(-1, 1, w, device=x.device, dtype=x.dtype).view(1, 1, 1, w).expand(b, 1, h, w)
        x = torch.cat([x, yy, xx], 1)
        skips = []
        for level in self.enc:
            x = level(x)
            skips.append(x)
        u = skips[-1]
        for layer, skip in zip(self.dec, skips[-2:0:-1]):
            u = layer(torch.cat([F.interpolate(u, size=skip.shape[-2:], mode="bilinear", align_corners=False), skip], 1))
        return self.out(u)


# each network with the brightness jitter it was trained and measured with
NETS: dict[str, tuple[type[nn.Module], float]] = {"small": (RowNet, 0.2), "wide": (WideRowNet, 0.3)}


def load(ds: CRDLD, idx: list[int], params: Params) -> tuple[np.ndarray, np.ndarray]:
    """Working images ``uint8 (N, H, W, 3)`` and label masks ``bool (N, H, W)`` at their size."""
    from torchrow.reference.pipeline import prepare
    xs, ys = [], []
    for i in idx:
        rgb = prepare(ds.image(i, None), params)
        h, w = rgb.shape[:2]
        xs.append(rgb)
        ys.append(label_mask(cv2.imread(str(ds.label_path(i)), cv2.IMREAD_GRAYSCALE), w, h))
    return np.stack(xs), np.stack(ys)


def as_input(x: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(x).permute(0, 3, 1, 2).float() / 255 - 0.5


def train(x: np.ndarray, y: np.ndarray, epochs: int, seed: int = 0, net_name: str = "small") -> nn.Module:
    """BCE (positive weight 2) on the label masks pooled to the output's size; flips and
    brightness jitter; AdamW with a one-cycle rate, batches of 16."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    cls, jitter = NETS[net_name]
    net = cls()
    xt, yt = as_input(x), F.avg_pool2d(torch.from_numpy(y).float()[:, None], 4)
    steps = epochs * -(-len(x) // 16)
    opt = torch.optim.AdamW(net.parameters(), 3e-3, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, 3e-3, total_steps=steps)
    for ep in range(epochs):
        net.train()
        perm, total = rng.permutation(len(x)), 0.0
        for j in range(0, len(perm), 16):
            b = torch.from_numpy(perm[j:j + 16])
            xb, yb = xt[b], yt[b]
            if rng.random() < 0.5:
                xb, yb = xb.flip(-1), yb.flip(-1)
            xb = xb * (1 + jitter * (torch.rand(len(b), 1, 1, 1) - 0.5)) + 0.1 * (torch.rand(len(b), 3, 1, 1) - 0.5)
            loss = F.binary_cross_entropy_with_logits(net(xb), yb, pos_weight=torch.tensor(2.0))
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += float(loss.detach()) * len(b)
        if ep % 10 == 9 or ep == epochs - 1:
            print(f"epoch {ep + 1}: loss {total / len(x):.4f}", file=sys.stderr, flush=True)
    return net.eval()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None)
    ap.add_argument("--eval", default="val", choices=("val", "test"))
    ap.add_argument("--epochs", type=int, default=60)
    ap.add_argument("--net", default="small", choices=tuple(NETS))
    ap.add_argument("--threshold", type=float, default=-1.0, help="logit above which a pixel is row evidence")
    args = ap.parse_args()

    from torchrow.engines.detector import CropRowDetector

    root = data_root(args.data)
    params = Params(mode="improved", **FORWARD_CAMERA)
    tr = CRDLD(root, "train")
    if args.eval == "val":
        fit_idx = [i for i in range(len(tr)) if i % 5]
        ev, ev_idx = tr, [i for i in range(len(tr)) if i % 5 == 0]
    else:
        fit_idx = list(range(len(tr)))
        ev = CRDLD(root, "test")
        ev_idx = list(range(len(ev)))
    net = train(*load(tr, fit_idx, params), args.epochs, net_name=args.net)
    x, labels = load(ev, ev_idx, params)
    h, w = x.shape[1:3]
    with torch.no_grad():
        logits = torch.cat([net(as_input(x[i:i + 32])) for i in range(0, len(x), 32)])
    learned = F.interpolate((logits > args.threshold).float(), size=(h, w), mode="nearest")[:, 0] > 0
    det = CropRowDetector(params)
    images = torch.from_numpy(x).permute(0, 3, 1, 2).contiguous()
    evidences = {"green mask (11.1)": None, "learned mask": learned, "label mask": torch.from_numpy(labels)}
    print(f"CRDLD {'train, every 5th image' if args.eval == 'val' else 'test'} "
          f"({args.net} network, {len(fit_idx)} training images, {args.epochs} epochs, threshold {args.threshold}), "
          "images with two or more labelled lines")
    print("| evidence | images | sigma 0.1 mean | median | sigma 0.3 | ok | ok below 0.2 |\n|---|---|---|---|---|---|---|")
    for name, evidence in evidences.items():
        recs = [r.to_record() for r in det.detect(images, evidence=evidence).results()]
        s1, s3, oks = [], [], []
        for j, i in enumerate(ev_idx):
            truth = ev.ground_truth(i)
            if len(truth.lines) < 2 or truth.central < 0:
                continue
            st = str(recs[j]["status"])
            s1.append(score_image(recs[j]["rows"], st, truth, 0.1, (w, h)))
            s3.append(score_image(recs[j]["rows"], st, truth, 0.3, (w, h)))
            oks.append(st == "ok")
        a1, ok = np.array(s1), np.array(oks)
        low = float((a1[ok] < 0.2).mean()) if ok.any() else float("nan")
        print(f"| {name} | {len(a1)} | {a1.mean():.3f} | {np.median(a1):.3f} | {np.mean(s3):.3f} | "
              f"{ok.mean():.1%} | {low:.1%} |")


if __name__ == "__main__":
    main()
