"""modi: MoDi and GANimator motion synthesis on skeleton-aware operators (see README)."""

__version__ = "0.1.0"
