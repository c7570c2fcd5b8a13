"""spine_engine: 3D spine reconstruction from radiograph landmarks by Cosserat-rod registration.

Li, Leow, Huang, Howe, "Modeling and Measurement of 3D Deformation of Scoliotic Spine Using
2D X-ray Images", CAIP 2009. Usable on its own: ``from spine_engine import register``.
"""

__version__ = "0.1.0"

from .errors import FitFailed, InvalidInput, SpineEngineError
from .reconstruction import register

__all__ = ["FitFailed", "InvalidInput", "SpineEngineError", "__version__", "register"]
