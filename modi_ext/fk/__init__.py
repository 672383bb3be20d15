"""Forward kinematics: local joint quaternions -> global joint positions (and rotations).

* ``reference``: the one Python FK and quaternion product (``fk_reference``, ``forward_kinematics``, ``quat_mul``,
  ``quat_apply``), which ``modi`` and the tests use and the kernel is checked against;
* ``ops``: the public op ``fk`` (checks, then the C++ kernel or the reference), its fake kernels and autograd, and
  the ``ForwardKinematics`` module.
"""
from modi_ext.fk.ops import ForwardKinematics, check_parents, fk
from modi_ext.fk.reference import fk_reference, forward_kinematics, quat_apply, quat_mul

__all__ = ["fk", "fk_reference", "ForwardKinematics", "check_parents", "forward_kinematics", "quat_mul", "quat_apply"]
