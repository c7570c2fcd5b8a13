"""Typed errors of the engine. Each names the offending field (a JSON path) and the reason."""

from dataclasses import dataclass


@dataclass(frozen=True)
class FieldError:
    """One offending field: `loc` is its JSON path (e.g. ("pa", "landmarks", 3, "level"))."""

    loc: tuple[str | int, ...]
    msg: str
    type: str

    @property
    def path(self) -> str:
        """The JSON path as a dotted string, e.g. ``pa.landmarks[3].level``."""
        out = ""
        for part in self.loc:
            out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else part)
        return out


class SpineEngineError(Exception):
    """Base class of every error the engine raises on purpose."""


class InvalidInput(SpineEngineError):
    """The payload is not a valid registration problem; `errors` lists every offending field."""

    def __init__(self, errors: list[FieldError]):
        self.errors = errors
        super().__init__("; ".join(f"{e.path}: {e.msg}" for e in errors))


class FitFailed(SpineEngineError):
    """The registration ran but did not produce a usable reconstruction (e.g. no convergence)."""

    def __init__(self, reason: str, iterations: int = 0):
        self.reason = reason
        self.iterations = iterations
        super().__init__(reason)


class UnknownProfile(InvalidInput):
    """`options.profile` names no profile shipped with the engine."""

    def __init__(self, name: str, known: list[str]):
        super().__init__(
            [FieldError(("options", "profile"), f"unknown profile {name!r}; known: {known}", "unknown_profile")]
        )
