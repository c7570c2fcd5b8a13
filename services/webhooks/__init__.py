"""Webhooks: a job's ``callback_url`` receives the job when it ends, signed as Standard Webhooks do.

- ``policy``: which destinations are allowed (``SPINE_WEBHOOK_ALLOWED_URLS``), checked when a job is
  submitted and again before every delivery.
- ``signing``: ``webhook-id``, ``webhook-timestamp`` and ``webhook-signature`` headers, and the
  signing secret of a job's owner (its API key's secret, else the service-wide ``SPINE_WEBHOOK_SECRET``).
- ``store``: the ``webhook_deliveries`` table (one row per attempt) that ``GET /v1/jobs/{id}`` shows.
- ``delivery``: the Celery task that POSTs, records and retries with backoff, on a queue of its own
  (``<SPINE_QUEUE_NAME>.webhooks``) so that deliveries neither wait behind nor delay fits.
"""
