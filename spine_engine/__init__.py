"""spine_engine: 3D spine reconstruction from radiograph landmarks by Cosserat-rod registration.

Li, Leow, Huang, Howe, "Modeling and Measurement of 3D Deformation of Scoliotic Spine Using
2D X-ray Images", CAIP 2009. Usable on its own: ``from spine_engine import register``.

``register`` is loaded on first use (PEP 562 module ``__getattr__``): the fit's stack (scipy,
numba, the compiled kernels) takes about a second to import, and the many importers that need
only the models, the errors or the validation (the API, the ``spine`` client commands, the
settings) should not pay it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .errors import FitFailed, InvalidInput, SpineEngineError
from .version import __version__

if TYPE_CHECKING:
    from .reconstruction import register

__all__ = ["FitFailed", "InvalidInput", "SpineEngineError", "__version__", "register"]


def __getattr__(name: str) -> Any:
    if name == "register":
        from .reconstruction import register  # lazy: `import spine_engine` for its errors must not load numba

        return register
    raise AttributeError(f"module 'spine_engine' has no attribute {name!r}")
