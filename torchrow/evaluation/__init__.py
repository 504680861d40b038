"""Evaluation data and scores: the CRBD and CRDLD datasets, CRDA metrics and the CRDLD score,
synthetic fields with exact ground truth.
"""
