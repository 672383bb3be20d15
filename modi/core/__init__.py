"""Skeleton math every other layer builds on: rotations, forward kinematics, skeletons, topology, the body
(height, units, sides), contacts, IK, joint reduction.  Imports nothing above ``modi.errors``/``modi.faults``."""
