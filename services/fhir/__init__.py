"""FHIR R4 export of a succeeded job's measures (an integration: imports ``services.db`` and ``services.core`` only)."""
