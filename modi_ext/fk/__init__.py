"""Forward kinematics."""
from modi_ext.fk.ops import ForwardKinematics, check_parents, fk, fk_reference

__all__ = ["fk", "fk_reference", "ForwardKinematics", "check_parents"]
