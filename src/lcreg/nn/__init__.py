"""Thin neural modules over :mod:`lcreg.geometry`: encoders, the IC-LK solver, LocalConsistency, decoders, heads."""
