"""The skeletal ops: in-place skeletal conv, the convolutional scalers down and up, modulated or not.

* ``reference``: MoDi's math spelled out on the masked dense weight (per-sample weights, grouped convs): the oracle;
* ``dense``: the same result as one shared conv with style and demodulation as scales: the fallback path;
* ``checks``: every argument checked on the host, and the CSR maps' values once per map;
* ``autograd``: the kernel call with its autograd, the differentiable backward (gradients of any order on the
  kernels, "gradfix"), and the registration of fake kernels and autograd with ``torch.library``;
* ``ops``: the public ops ``skeletal_conv``, ``skeletal_down``, ``skeletal_up`` (checks, then the path
  ``modi_ext.runtime.dispatch`` picks: kernels, dense form or reference).

The CSR maps come from ``modi_ext.csr``, the demodulation coefficients from ``modi_ext.demod``.
"""
from modi_ext.skeletal.ops import from_dense, skeletal_conv, skeletal_down, skeletal_up, to_dense

__all__ = ["skeletal_conv", "skeletal_down", "skeletal_up", "to_dense", "from_dense"]
