"""xvoe: the X-VoE benchmark and the XPL intuitive-physics model in PyTorch and Pyro."""

__version__ = "0.1.0"
