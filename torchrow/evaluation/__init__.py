"""Evaluation data and scores: the CRBD dataset, CRDA metrics, synthetic fields with exact ground
truth.
"""
