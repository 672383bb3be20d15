"""Harnesses that run the authors' released code (``../shared/peers``) beside modi: equality and speed.

They patch the released sources at run time (CPU device, torch forms of their fused CUDA ops) and never copy them.
"""
