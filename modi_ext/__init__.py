"""modi_ext: skeleton-aware operators (skeletal conv, convolutional scaler, modulation, FK).

Sparse-per-entity C++/CUDA kernels registered under ``torch.ops.modi_ext``, a dense pure-torch form
(``modi_ext.dense``: one shared conv, style and demodulation as scales) that is the fallback when the extension is
not built, and MoDi's literal math (``modi_ext.reference``) as the test oracle.  ``MODI_EXT_IMPL=auto|ext|dense|ref``
picks the path; ``dispatch_report()`` lists the choices ``auto`` made.  This package never imports ``modi``.
"""
from modi_ext._loader import HAS_EXT, LOAD_ERROR, impl_choice
from modi_ext.dispatch import dispatch_report

__all__ = ["HAS_EXT", "LOAD_ERROR", "impl_choice", "dispatch_report"]
