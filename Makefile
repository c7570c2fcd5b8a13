# One venv, installed from pyproject.toml's pins. `make run` and `make test` are the README's two commands.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install run test lint typecheck unit bench-paper bench-verse bench-perf openapi loadtest clean web browser

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
	$(BIN)/ruff check spine_engine services spine_client migrations tests
	$(BIN)/mypy

test: $(STAMP) lint browser
	$(BIN)/python -m pytest -ra

bench-paper: $(STAMP)
	$(BIN)/spine bench paper

bench-verse: $(STAMP)
	$(BIN)/spine bench verse

bench-perf: $(STAMP)
	$(BIN)/spine bench perf

openapi: $(STAMP)
	$(BIN)/spine openapi > openapi.yaml

# Web front end: web/ (TypeScript + Vite + three.js) built into services/api/static/, which is
# committed (a Python-only install serves it) and served by the API at /.
web:
	cd web && npm ci --no-audit --no-fund && npm run build

# Debian's chromium for the browser test (tests/test_web_e2e.py): installed with apt-get when
# missing and we are root (CI is); otherwise that test is skipped and says why.
CHROMIUM ?= /usr/bin/chromium
browser:
	@if [ -x "$(CHROMIUM)" ]; then \
		echo "browser test: $(CHROMIUM)"; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 && [ -z "$$SPINE_NO_BROWSER_INSTALL" ]; then \
		echo "installing Debian's chromium for the browser test"; \
		{ apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
			chromium fonts-dejavu-core; } >/tmp/spine-apt-chromium.log 2>&1 \
			|| { tail -n 20 /tmp/spine-apt-chromium.log; echo "chromium could not be installed: the browser test will be skipped"; }; \
	else \
		echo "no chromium at $(CHROMIUM) and no way to install it (needs root and apt-get): the browser test will be skipped"; \
	fi

# Service load benchmark: PostgreSQL + Redis on 127.0.0.1, API and workers started by the bench.
LOADTEST_ARGS ?= --spawn --url http://127.0.0.1:8090 --workers 1 --worker-concurrency 2
loadtest: $(STAMP)
	DATABASE_URL=$${DATABASE_URL:-postgresql+psycopg://postgres@127.0.0.1:5432/spine_load} \
	CELERY_BROKER_URL=$${CELERY_BROKER_URL:-redis://127.0.0.1:6379/1} \
	$(BIN)/python -m services.loadbench $(LOADTEST_ARGS)

clean:
	rm -rf $(VENV) .spine .pytest_cache .mypy_cache .ruff_cache
