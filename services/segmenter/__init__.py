"""Segmenter service: frames in, per-pixel safe-to-land probabilities out."""
