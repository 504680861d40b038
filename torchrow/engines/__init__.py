"""Engines that compose the stages: the batched detector, the video tracker, ONNX export and
runners, the run loop.
"""
