"""The skeletal ops: in-place skeletal conv, the convolutional scalers down and up, modulated or not.

* ``reference``: MoDi's math spelled out on the masked dense weight (per-sample weights, grouped convs): the oracle;
* ``dense``: the same result as one shared conv with style and demodulation as scales: the fallback path;
* ``checks``: every argument checked on the host, the CSR maps' values once per map (and the C++ ops' names and
  argument order);
* ``registration``: fake kernels and autograd of the C++ ops with ``torch.library`` (and their eager Functions);
  ``gradfix``: gradients of any order on the kernels (the two partial backwards as ops of their own);
* ``ops``: the public ops ``skeletal_conv``, ``skeletal_down``, ``skeletal_up`` (checks, then the path
  ``modi_ext.runtime.dispatch`` picks: kernels, dense form or reference).

The CSR maps come from ``modi_ext.csr``, the demodulation coefficients from ``modi_ext.demod``.
"""
from modi_ext.skeletal.ops import from_dense, skeletal_conv, skeletal_down, skeletal_up, to_dense

__all__ = ["skeletal_conv", "skeletal_down", "skeletal_up", "to_dense", "from_dense"]
