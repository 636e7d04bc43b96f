"""Rig calibration from its own captures. Pure: arrays in, results (with uncertainties) out."""
