"""Judging a reconstruction: ``metrics`` (image fidelity, particle error in true spacings, density
spread, energies), ``evaluate`` (``gf-cli evaluate``: per split, view and frame, with plots) and
``resample`` (in-between frames from the decoder against held-back frames)."""
