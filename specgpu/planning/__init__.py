"""Planning: basis tables, measurement plans (one registry for every method, the optimal design and Hadamard
included), the noise model and training priors, the estimators, per-pixel uncertainty and drift correction."""

import lazy_loader

# The names are listed in __init__.pyi; each loads its module on first use, so importing the room is cheap.
__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)
