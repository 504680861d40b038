"""Engines that compose the stages: the batched detector, the video tracker and the run loops
(local and Ray) that pick an engine (tensor, reference, ONNX from :mod:`torchrow.onnx`).
"""
