"""modi_ext: skeleton-aware operators (skeletal conv, convolutional scaler, modulation, FK).

Sparse-per-entity C++/CUDA kernels registered under ``torch.ops.modi_ext``, a dense pure-torch form of each op (e.g.
``modi_ext.skeletal.dense``: one shared conv, style and demodulation as scales) that is the fallback when the extension
is not built, and MoDi's literal math (e.g. ``modi_ext.skeletal.reference``) as the test oracle.
``MODI_EXT_IMPL=auto|ext|dense|ref`` picks the path; ``dispatch_report()`` lists the choices ``auto`` made.  This
package never imports ``modi``.

One package per op -- ``skeletal/``, ``demod/``, ``fk/``, each with its reference, dense form and public op -- and
``runtime/``, how a call finds its path and checks it; ``csr`` turns neighbor lists into CSR maps, ``layers``
holds the ``nn.Module``s and ``validate`` the GPU validation command.  The import layers: ``tests/modi_ext/
test_modi_ext_imports.py``.

Imported before torch, it first chooses how long idle OpenMP threads spin (``modi_ext.runtime.omp_wait``: short when
other processes keep a CPU busy, where a long spin stalls every parallel region); ``omp_wait_policy()`` says which
setting this process runs with.
"""
from modi_ext.runtime import omp_wait as _omp_wait

_omp_wait.apply()  # before anything imports torch

from modi_ext.runtime import dispatch as _dispatch
from modi_ext.runtime import selfcheck as _selfcheck
from modi_ext.runtime.dispatch import dispatch_report
from modi_ext.runtime.loader import HAS_EXT, LOAD_ERROR, impl_choice

_dispatch.SELFCHECK = _selfcheck.run  # dispatch checks the kernels on first use with it (see dispatch.SELFCHECK)

__all__ = ["HAS_EXT", "LOAD_ERROR", "impl_choice", "dispatch_report", "omp_wait_policy"]


def omp_wait_policy() -> str:
    """The OpenMP wait setting in force, and who chose it (modi_ext, the user, or libgomp's default)."""
    return _omp_wait.describe()
