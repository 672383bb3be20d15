"""The demodulation coefficients (filled in below)."""
