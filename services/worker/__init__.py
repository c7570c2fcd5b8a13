"""The Celery worker: runs queued jobs through spine_engine and stores their outcome."""
