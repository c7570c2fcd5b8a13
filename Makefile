# One venv, installed from pyproject.toml's pins. `make run` and `make test` are the README's two commands.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install run test lint typecheck unit bench-paper bench-verse bench-perf openapi loadtest clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

run: $(STAMP)
	$(BIN)/spine migrate
	$(BIN)/spine serve --host 127.0.0.1 --port 8000

lint: $(STAMP)
	$(BIN)/ruff check spine_engine services migrations tests
	$(BIN)/mypy

test: $(STAMP) lint
	$(BIN)/python -m pytest -ra

bench-paper: $(STAMP)
	$(BIN)/spine bench paper

bench-verse: $(STAMP)
	$(BIN)/spine bench verse

bench-perf: $(STAMP)
	$(BIN)/spine bench perf

openapi: $(STAMP)
	$(BIN)/spine openapi > openapi.yaml

# Service load benchmark: PostgreSQL + Redis on 127.0.0.1, API and workers started by the bench.
LOADTEST_ARGS ?= --spawn --url http://127.0.0.1:8090 --workers 1 --worker-concurrency 2
loadtest: $(STAMP)
	DATABASE_URL=$${DATABASE_URL:-postgresql+psycopg://postgres@127.0.0.1:5432/spine_load} \
	CELERY_BROKER_URL=$${CELERY_BROKER_URL:-redis://127.0.0.1:6379/1} \
	$(BIN)/python -m services.loadbench $(LOADTEST_ARGS)

clean:
	rm -rf $(VENV) .spine .pytest_cache .mypy_cache .ruff_cache
