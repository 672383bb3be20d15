"""Motions and what training reads: the ``Motion`` type, the MoDi representation, normalisation, datasets and
procedural clips."""
