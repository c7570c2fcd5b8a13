"""The client's commands of ``spine`` (``spine_client.cli``): their names and the help line ``spine --help``
shows for each. A module of its own, so that ``services.cli.main`` tells them apart without loading
the service's commands, nor the service's commands the client."""

from __future__ import annotations

CLIENT_COMMANDS = {
    "submit": "client: submit a job payload (JSON file), optionally wait for it",
    "submit-dir": "client: submit every *.json of a folder as batches, wait, write a summary",
    "get": "client: print a job as JSON, or its vertebrae or measures as CSV",
    "list": "client: list jobs, newest first",
    "cancel": "client: cancel a queued or running job",
    "store": "client: store a succeeded job's results in the PACS again",
    "fhir": "client: print a succeeded job's measures as a FHIR R4 Bundle",
}
"""Commands of the service's client (``spine_client.cli``), talking to SPINE_URL with SPINE_API_KEY."""
