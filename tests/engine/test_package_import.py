"""The package entry: ``register`` is there for ``from spine_engine import register``, and loading
the errors, models or validation (as the settings, the API and the ``spine`` client commands do)
does not import the fit's stack (numba, scipy.optimize): about a second per process."""

from __future__ import annotations

import subprocess
import sys

import pytest

import spine_engine


def test_register_is_the_reconstructions() -> None:
    from spine_engine.reconstruction import register

    assert spine_engine.register is register
    assert "register" in spine_engine.__all__
    with pytest.raises(AttributeError, match="no attribute 'fit_everything'"):
        spine_engine.fit_everything  # noqa: B018


@pytest.mark.parametrize(
    "module", ["spine_engine.errors", "spine_engine.models", "spine_engine.validation", "services.core.config"]
)
def test_light_imports_leave_the_fit_stack_unloaded(module: str) -> None:
    heavy = ("numba", "scipy.optimize", "spine_engine.reconstruction")
    code = f"import sys, {module}; print(sorted(m for m in {heavy!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out
