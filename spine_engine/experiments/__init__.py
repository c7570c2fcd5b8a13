"""Experiment and benchmark commands of the engine (``spine bench ...``)."""
