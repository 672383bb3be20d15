"""modi_ext: skeleton-aware operators (skeletal conv, convolutional scaler, modulation, FK).

Sparse-per-entity C++/CUDA kernels registered under ``torch.ops.modi_ext``, with a dense
pure-torch reference (``modi_ext.reference``) that is both the test oracle and the fallback
when the extension is not built. ``MODI_EXT_IMPL=ref|ext`` forces a path.
This package never imports ``modi``.
"""
from modi_ext._loader import HAS_EXT, LOAD_ERROR, impl_choice

__all__ = ["HAS_EXT", "LOAD_ERROR", "impl_choice"]
