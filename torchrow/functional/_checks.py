"""Input guards shared by the tensor stages: one clear error naming expected and actual."""

from __future__ import annotations

import torch

from torchrow.core.params import Params

__all__ = ["check_images", "check_masks", "check_rows", "check_device"]


def check_images(images: torch.Tensor, name: str = "images") -> None:
    """Require ``uint8 (B, 3, H, W)`` with ``H, W >= 1`` (B may be 0)."""
    if not isinstance(images, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor uint8 (B, 3, H, W), got {type(images).__name__}")
    if images.dim() != 4 or images.shape[1] != 3 or images.shape[2] < 1 or images.shape[3] < 1:
        raise ValueError(f"{name}: expected shape (B, 3, H, W) with H, W >= 1, got {tuple(images.shape)}")
    if images.dtype != torch.uint8:
        raise ValueError(f"{name}: expected dtype torch.uint8, got {images.dtype}")


def check_masks(masks: torch.Tensor, name: str = "mask") -> None:
    """Require ``bool (B, H, W)``."""
    if not isinstance(masks, torch.Tensor) or masks.dim() != 3 or masks.dtype != torch.bool:
        got = f"{masks.dtype} {tuple(masks.shape)}" if isinstance(masks, torch.Tensor) else type(masks).__name__
        raise ValueError(f"{name}: expected a bool tensor (B, H, W), got {got}")


def check_rows(sky: torch.Tensor, batch: int, name: str = "sky") -> None:
    """Require an integer ``(B,)`` tensor of horizon rows."""
    if not isinstance(sky, torch.Tensor) or sky.shape != (batch,) or sky.dtype.is_floating_point:
        got = f"{sky.dtype} {tuple(sky.shape)}" if isinstance(sky, torch.Tensor) else type(sky).__name__
        raise ValueError(f"{name}: expected an integer tensor of shape ({batch},), got {got}")


def check_device(device: str | torch.device | None, name: str = "device") -> torch.device:
    """``device`` as a ``torch.device`` that exists here (default CPU), else ``ValueError``.

    Checked when a module is built, so that a missing CUDA device is one clear error and not
    a failure deep inside the first batch.
    """
    if device is None:
        return torch.device("cpu")
    if not isinstance(device, (str, torch.device)):
        raise TypeError(f"{name}: expected a str or torch.device, got {type(device).__name__}")
    try:
        dev = torch.device(device)
    except RuntimeError as exc:
        raise ValueError(f"{name}: not a torch device: {device!r} ({exc})") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"{name}: {device!r} asked for, but torch sees no CUDA device here")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"{name}: {device!r} asked for, but torch sees {torch.cuda.device_count()} CUDA device(s)")
    elif dev.type == "mps" and not (hasattr(torch.backends, "mps") and torch.backends.mps.is_available()):
        raise ValueError(f"{name}: {device!r} asked for, but MPS is not available here")
    return dev


def check_params(params: Params) -> None:
    if not isinstance(params, Params):
        raise TypeError(f"params: expected torchrow.core.params.Params, got {type(params).__name__}")


def clamp_sky(sky: torch.Tensor, height: int, device: torch.device) -> torch.Tensor:
    """``sky`` as int64 on ``device``, clamped to ``[0, H]``."""
    return sky.to(device=device, dtype=torch.int64).clamp(0, height)


def below_horizon(sky: torch.Tensor, height: int, as_bool: bool = False) -> torch.Tensor:
    """``uint8 (B, H, 1)``, 1 where row ``y`` lies below the horizon (``y >= sky[b]``): the
    rows every stage after sky removal sees. ``as_bool``: the same mask as ``bool``.

    Masks are combined as 0/1 ``uint8`` (``bool`` viewed as ``uint8``, no copy): on the CPU,
    PyTorch's ``bool`` ``&``/``|``/``where`` kernels are 10-30x slower than ``uint8`` ones.
    The exported graphs take the ``bool`` form: no dtype view to decompose.
    """
    rows = torch.arange(height, device=sky.device, dtype=torch.int64)
    below = (rows.view(1, height) >= sky.view(-1, 1)).unsqueeze(2)
    return below if as_bool else below.view(torch.uint8)


def as_u8(mask: torch.Tensor) -> torch.Tensor:
    """A ``bool`` tensor viewed as 0/1 ``uint8`` (no copy)."""
    return mask.view(torch.uint8)
