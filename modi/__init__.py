"""modi: MoDi and GANimator motion synthesis on skeleton-aware operators (see README)."""

from modi_ext import omp_wait as _omp_wait

_omp_wait.apply()  # before torch loads libgomp: the OpenMP spin for this machine (modi_ext/omp_wait.py)

__version__ = "0.1.0"
