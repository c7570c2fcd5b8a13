"""The engine's benches: experiment and benchmark commands (``spine bench ...``), outside the wheel."""
