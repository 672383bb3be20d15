"""The package version: one place, read by setup.py and by every checkpoint writer (``modi_version``)."""

__version__ = "0.3.0"
