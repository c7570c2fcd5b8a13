# Image of the spine service: the same image runs the API (`spine serve`), the workers
# (`spine worker`) and the migrations (`spine migrate`); docker-compose.yml wires them up.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /app
COPY pyproject.toml constraints.txt README.md ./
COPY spine_engine ./spine_engine
COPY services ./services
COPY spine_client ./spine_client
COPY migrations ./migrations
RUN pip install -c constraints.txt . \
    && useradd --create-home --uid 10001 spine \
    && mkdir -p /data && chown spine /data

USER spine
ENV SPINE_DATA_DIR=/data
VOLUME ["/data"]
EXPOSE 8000

HEALTHCHECK --interval=10s --timeout=3s --start-period=20s --retries=3 \
    CMD python -c "import sys, urllib.request; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=2).status != 200)"

# The embedded default (SQLite + SQLite broker, API and worker in one container) when no
# DATABASE_URL / CELERY_BROKER_URL are given; docker-compose.yml overrides the command.
CMD ["spine", "serve", "--host", "0.0.0.0", "--port", "8000"]
