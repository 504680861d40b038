"""Core types of torchrow: parameters, results and records, shared tables, image loading (spec
section 0), steering signals.
"""
