"""The demodulation coefficients of the modulated skeletal ops: ``d[b, o, j] = rsqrt(s^2 . sum W^2 + eps)``.

* ``reference``: the formula as MoDi writes it, on the masked dense weight (and ``DEMOD_EPS``): the oracle;
* ``dense``: the same from the compact weight in torch ops, never a per-sample weight: the dense form;
* ``registration``: fake kernels and autograd of the C++ op with ``torch.library`` (and its eager Function);
* ``ops``: ``demod_scale``, the public op: one kernel call each way on the CPU and on CUDA, the dense form
  elsewhere.

This package's ``__init__`` imports nothing: the skeletal ops' reference and dense form sit on its reference and
dense form, below the runtime that ``ops`` needs.  Import the op as ``modi_ext.demod.ops.demod_scale``.
"""
