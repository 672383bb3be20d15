"""Forward kinematics: local joint quaternions -> global joint positions (and rotations); built as every op is.

* ``reference``: the one Python FK and quaternion product (``fk_reference``, ``forward_kinematics``, ``quat_mul``,
  ``quat_apply``), which ``modi`` and the tests use and the kernel is checked against;
* ``dense``: FK's dense form (the same torch loop: FK has no faster one);
* ``checks``: every argument checked on the host;
* ``registration``: fake kernels and autograd of the C++ op with ``torch.library``; ``gradfix``: gradients of any
  order (a graph of the gradient through the torch loop);
* ``ops``: the public op ``fk`` (checks, then the path ``modi_ext.runtime.dispatch`` picks: kernel, dense or ref).

The ``ForwardKinematics`` module lives with every other layer in ``modi_ext.layers``.
"""
from modi_ext.fk.checks import check_parents
from modi_ext.fk.ops import fk
from modi_ext.fk.reference import fk_reference, forward_kinematics, quat_apply, quat_mul

__all__ = ["fk", "fk_reference", "check_parents", "forward_kinematics", "quat_mul", "quat_apply"]
