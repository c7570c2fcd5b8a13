# One venv, installed from pyproject.toml's pins and constraints.txt's versions of everything beneath them.
# `make run` and `make test` are the README's two commands.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install lock run test lint typecheck unit bench-paper bench-verse bench-perf calibrate openapi loadtest clean web browser pacs node-deps

$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip -c constraints.txt
	$(BIN)/python -m pip install --quiet -e '.[dev]' -c constraints.txt
	@# the engine's numba kernels compiled once into their on-disk cache (3-4 s), not on a first job
	$(BIN)/python -c "from spine_engine.warmup import warm_up; print(f'engine kernels compiled in {warm_up():.1f} s')"
	touch $(STAMP)

install: $(STAMP)

# constraints.txt anew: pyproject.toml resolved with today's releases in a throwaway venv, every package's
# version written down (then `make test` says whether the new set works).
LOCK_VENV := .lock-venv
lock:
	rm -rf $(LOCK_VENV) && $(PYTHON) -m venv $(LOCK_VENV)
	$(LOCK_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(LOCK_VENV)/bin/python -m pip install --quiet -e '.[dev]'
	{ sed -n '/^#/p' constraints.txt; $(LOCK_VENV)/bin/python -m pip freeze --all --exclude-editable; } > constraints.txt.new
	mv constraints.txt.new constraints.txt && rm -rf $(LOCK_VENV)
	@echo "constraints.txt rewritten: git diff constraints.txt, then make test"

# `make run PORT=8080 HOST=0.0.0.0` serves elsewhere (default 127.0.0.1:8000).
HOST ?= 127.0.0.1
PORT ?= 8000
run: $(STAMP)
	$(BIN)/spine migrate
	$(BIN)/spine serve --host $(HOST) --port $(PORT)

lint: $(STAMP)
	$(BIN)/ruff check spine_engine services spine_client benches migrations tests tools
	$(BIN)/lint-imports --no-cache
	$(BIN)/mypy

# pytest on three processes (pytest-xdist) on the two cores: the fault and process tests mostly wait
# (two processes left 45 % of the cores idle). The schemathesis fuzz test gives its 17 operations one
# node id, which xdist would run once: it runs in a pytest of its own beside them (alone, it kept one
# core busy and left the other idle for its 40 s), its report printed after theirs; either failing
# fails the target. A shell's background job ignores Ctrl-C, so an interrupt stops it by SIGTERM.
FUZZ := tests/api/test_fuzz.py
test: $(STAMP) lint browser pacs node-deps
	@fuzz_log=$$(mktemp /tmp/spine-test-fuzz-XXXXXX.log); \
	$(BIN)/python -m pytest -ra -p no:cacheprovider $(FUZZ) >"$$fuzz_log" 2>&1 </dev/null & fuzz=$$!; \
	trap 'kill $$fuzz 2>/dev/null; rm -f "$$fuzz_log"; exit 130' INT TERM; \
	$(BIN)/python -m pytest -n 3 --dist loadfile -ra --durations=15 --ignore=$(FUZZ); rest=$$?; \
	wait $$fuzz; fuzzed=$$?; echo "--- $(FUZZ), run beside the tests above (exit $$fuzzed):"; \
	cat "$$fuzz_log"; rm -f "$$fuzz_log"; [ $$rest = 0 ] && [ $$fuzzed = 0 ]

bench-paper: $(STAMP)
	$(BIN)/spine bench paper

bench-verse: $(STAMP)
	$(BIN)/spine bench verse

bench-perf: $(STAMP)
	$(BIN)/spine bench perf

# the calibrations that follow the engine, in order (needs ../shared/data: VerSe dev, AASCE training)
calibrate: $(STAMP)
	$(BIN)/spine bench recalibrate

openapi: $(STAMP)
	$(BIN)/spine openapi > openapi.yaml

# Web front end: web/ (TypeScript + Vite + three.js) built into services/api/static/, which is
# committed (a Python-only install serves it) and served by the API at /.
web:
	cd web && npm ci --no-audit --no-fund && npm run build

# Debian packages some tests need, installed with apt-get when missing and we are root (CI is).
# Outside CI a missing one only makes its tests skip (saying why); in CI (CI=true or
# SPINE_REQUIRE_BACKENDS=1) an install that fails stops `make test`, and tests/conftest.py turns
# every skip into a failure, so that a green CI cannot hide a missing back end.
REQUIRE_BACKENDS = $(if $(filter true 1,$(CI) $(SPINE_REQUIRE_BACKENDS)),1,)
define apt_install
	if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 && [ -z "$$SPINE_NO_APT_INSTALL" ]; then \
		echo "installing Debian's $(2) for $(3)"; \
		{ apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
			$(2); } >/tmp/spine-apt-$(1).log 2>&1 \
			|| { tail -n 20 /tmp/spine-apt-$(1).log; echo "$(2) could not be installed: $(3) will be skipped"; \
				[ -z "$(REQUIRE_BACKENDS)" ] || { echo "CI: failing (a skipped test would hide it)"; exit 1; }; }; \
	else \
		echo "$(1) is missing and cannot be installed here (needs root and apt-get): $(3) will be skipped"; \
		[ -z "$(REQUIRE_BACKENDS)" ] || { echo "CI: failing (a skipped test would hide it)"; exit 1; }; \
	fi
endef

# Debian's chromium for the browser tests (tests/browser/), and poppler-utils' pdftotext, which reads
# back the page's printed reports.
CHROMIUM ?= /usr/bin/chromium
browser:
	@if [ -x "$(CHROMIUM)" ] && command -v pdftotext >/dev/null 2>&1; then \
		echo "browser test: $(CHROMIUM)"; \
	else \
		$(call apt_install,chromium,chromium fonts-dejavu-core poppler-utils,the browser test); \
	fi

# Debian's Orthanc with its DICOMweb plug-in, DCMTK (dsrdump) and dicom3tools (dciodvfy), for the
# PACS and DICOM tests (tests/dicom): the tests start their own Orthanc on a free loopback port.
ORTHANC ?= /usr/sbin/Orthanc
pacs:
	@if [ -x "$(ORTHANC)" ] && command -v dsrdump >/dev/null 2>&1 && command -v dciodvfy >/dev/null 2>&1 \
		&& ls /usr/share/orthanc/plugins/libOrthancDicomWeb.so* >/dev/null 2>&1; then \
		echo "PACS tests: $(ORTHANC)"; \
	else \
		$(call apt_install,orthanc,orthanc orthanc-dicomweb dcmtk dicom3tools,the PACS and DICOM tests); \
	fi

# The Cornerstone adapters OHIF reads SRs with (@cornerstonejs/adapters, pinned in tests/node/package.json
# and its lock), for the DICOM tests that load the service's SR in Node (tests/dicom/ohif.py). Node and npm
# are Debian's nodejs and npm, installed with apt-get as above when missing.
NODE_STAMP := tests/node/node_modules/.installed
# The page's own packages (web/package-lock.json): tests/dicom/test_header_agreement.py bundles the page's
# DICOM reader for Node with them, to hold it to the service's.
WEB_STAMP := web/node_modules/.installed
node-deps: $(NODE_STAMP) $(WEB_STAMP)

$(WEB_STAMP): web/package.json web/package-lock.json $(NODE_STAMP)
	@if command -v npm >/dev/null 2>&1; then \
		cd web && npm ci --no-audit --no-fund --loglevel=error && touch node_modules/.installed; \
	fi

$(NODE_STAMP): tests/node/package.json tests/node/package-lock.json
	@if ! command -v npm >/dev/null 2>&1; then \
		$(call apt_install,node,nodejs npm,the SR adapter tests); \
	fi
	@if command -v npm >/dev/null 2>&1; then \
		cd tests/node && npm ci --no-audit --no-fund --loglevel=error && touch node_modules/.installed; \
	fi

# Service load benchmark: PostgreSQL + Redis on 127.0.0.1, API and workers started by the bench.
LOADTEST_ARGS ?= --spawn --url http://127.0.0.1:8090 --workers 1 --worker-concurrency 2
loadtest: $(STAMP)
	DATABASE_URL=$${DATABASE_URL:-postgresql+psycopg://postgres@127.0.0.1:5432/spine_load} \
	CELERY_BROKER_URL=$${CELERY_BROKER_URL:-redis://127.0.0.1:6379/1} \
	$(BIN)/python -m tools.loadbench $(LOADTEST_ARGS)

clean:
	rm -rf $(VENV) .spine .pytest_cache .mypy_cache .ruff_cache tests/node/node_modules
