"""The HTTP API: validates, stores and enqueues jobs, answers reads. It never runs a fit."""
