"""constraints.txt pins the whole installed tree: it agrees with every pin of pyproject.toml (and of the
thin client's spine_client/pyproject.toml), names each package once, and is what the project's venv holds
(``make install`` installs with it; a venv made before it changed is rebuilt by ``make``, whose stamp
depends on the file)."""

from __future__ import annotations

import importlib.metadata
import re
import tomllib
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[2]
PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==(\S+)$")


def constraints() -> dict[str, str]:
    """constraints.txt as {canonical name: version}; every line a comment or ``name==version``."""
    pins: dict[str, str] = {}
    for number, line in enumerate((ROOT / "constraints.txt").read_text().splitlines(), start=1):
        if not line.strip() or line.startswith("#"):
            continue
        match = PIN.match(line)
        assert match, f"constraints.txt line {number} is not name==version: {line!r}"
        name = canonicalize_name(match[1])
        assert name not in pins, f"constraints.txt names {name} twice"
        pins[name] = match[2]
    return pins


def pyproject_pins(path: Path) -> dict[str, str]:
    """Every dependency of a pyproject.toml, extras included, as {canonical name: pinned version}."""
    project = tomllib.loads(path.read_text())["project"]
    requirements = list(project["dependencies"])
    for extra in project.get("optional-dependencies", {}).values():
        requirements += extra
    pins = {}
    for text in requirements:
        requirement = Requirement(text)
        (specifier,) = requirement.specifier
        assert specifier.operator == "==", f"{path.name}: {text} is not pinned with =="
        pins[canonicalize_name(requirement.name)] = specifier.version
    return pins


def test_constraints_agree_with_the_pyproject_pins() -> None:
    pins = constraints()
    for path in (ROOT / "pyproject.toml", ROOT / "spine_client" / "pyproject.toml"):
        for name, version in pyproject_pins(path).items():
            assert pins.get(name) == version, (
                f"{path.relative_to(ROOT)} pins {name}=={version}, constraints.txt has {pins.get(name)}: "
                "run `make lock`"
            )


def test_the_venv_holds_what_the_constraints_name() -> None:
    installed = {
        canonicalize_name(d.metadata["Name"]): d.version
        for d in importlib.metadata.distributions()
        if d.metadata["Name"]
    }
    pinned = constraints()
    differ = {
        name: (version, installed[name])
        for name, version in pinned.items()
        if name in installed and installed[name] != version
    }
    assert not differ, f"installed versions differ from constraints.txt (run `make install`): {differ}"
    missing = set(pinned) - set(installed)
    assert not missing, f"constraints.txt names packages the venv lacks (run `make install`): {sorted(missing)}"
