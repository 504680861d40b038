"""Core types of torchrow (the lowest layer: it imports no other torchrow package): parameters,
results and records (``ImageResult``, ``BatchResult``, ``FrameResult``), shared tables, image
loading (spec section 0), frame sources and ROS bag reading, steering signals, the camera model
(metric steering, spec section 12), progress.
"""
