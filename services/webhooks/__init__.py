"""Webhooks: a job's ``callback_url`` receives the job when it ends, and when a run of STOW-RS attempts of
its results ends (``job.dicom_stored``, ``job.dicom_store_failed``), signed as Standard Webhooks do.

- ``signing``: ``webhook-id``, ``webhook-timestamp`` and ``webhook-signature`` headers, and the
  signing secret of a job's owner (its API key's secret, else the service-wide ``SPINE_WEBHOOK_SECRET``).
- ``delivery``: one POST to the receiver and the backoff its answer calls for.
- ``submission``: the API's check of a ``callback_url`` against ``SPINE_WEBHOOK_ALLOWED_URLS``.

The policy of destinations is ``services.core.webhook_policy``; the ``webhook_deliveries`` table and
the outbox (``job_ended``) are ``services.db.deliveries``; the Celery task that POSTs, records and
retries, on a queue of its own (``<SPINE_QUEUE_NAME>.webhooks``) so that deliveries neither wait
behind nor delay fits, is ``services.worker.webhook_tasks``.
"""
