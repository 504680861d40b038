"""Differentiable building blocks (:mod:`torchrow.nn.blocks`) and their calibration (:mod:`torchrow.nn.calibrate`)."""

from torchrow.nn.blocks import *  # noqa: F403
from torchrow.nn.blocks import __all__  # noqa: F401
