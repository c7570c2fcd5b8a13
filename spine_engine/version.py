"""The engine's version, reported in every result (``EngineInfo.version``); pyproject.toml says the same."""

__version__ = "0.1.0"
