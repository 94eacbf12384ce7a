"""xvoe: the X-VoE benchmark and the XPL intuitive-physics model in PyTorch and Pyro."""

from .allocator import tune as _tune_allocator

_tune_allocator()       # before any large tensor: freed buffers stay in the heap (xvoe/allocator.py)

__version__ = "0.1.0"
