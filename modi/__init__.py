"""modi: MoDi and GANimator motion synthesis on skeleton-aware operators (see README)."""

from modi._version import __version__

__all__ = ["__version__"]
