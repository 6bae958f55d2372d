# The lab's two entry points: `make demo` runs it, `make test` checks it.
# Both set up what is missing first (a virtualenv in .venv, the Node test clients).

VENV    ?= .venv
PYTHON  ?= python3
PY      := $(VENV)/bin/python
STAMP   := $(VENV)/.installed-$(shell cksum < pyproject.toml | cut -d' ' -f1)
JS      := tests/js
JSSTAMP := $(JS)/node_modules/.installed
WEB     := web
WEBSTAMP := labd/web/static/vendor/.built

.PHONY: setup demo test lint unit bench clean deploy-image deploy-smoke

setup: $(STAMP) $(JSSTAMP) $(WEBSTAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	rm -f $(VENV)/.installed-*
	touch $@

$(JSSTAMP): $(JS)/package.json $(JS)/package-lock.json
	cd $(JS) && npm ci --no-audit --no-fund --loglevel=error
	touch $@

# The pages' scripts and styles (Swagger UI, ReDoc, uPlot, three.js, roslibjs), from npm, served
# by the lab itself: see web/build.mjs.
$(WEBSTAMP): $(WEB)/package.json $(WEB)/package-lock.json $(WEB)/build.mjs
	cd $(WEB) && npm ci --no-audit --no-fund --loglevel=error && node build.mjs
	touch $@

# make demo BRIDGE_PORT=9191 HTTP_PORT=8181 to choose the ports (default: 9090 and
# 8080 if free, else free ones the demo prints).
demo: $(STAMP) $(WEBSTAMP)
	$(VENV)/bin/labd demo $(if $(BRIDGE_PORT),--bridge-port $(BRIDGE_PORT)) $(if $(HTTP_PORT),--http-port $(HTTP_PORT))

# The Python (ruff, mypy --strict: the packages and deploy/'s scripts), and the pages'
# scripts with their tests in Node (ESLint, from web/'s npm lock: web/eslint.config.mjs).
JSLINT := labd/web/static tests/js/pages $(WEB)/build.mjs $(WEB)/codemirror.mjs $(WEB)/eslint.config.mjs

lint: $(STAMP) $(WEBSTAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy
	$(WEB)/node_modules/.bin/eslint --config $(WEB)/eslint.config.mjs --max-warnings 0 $(JSLINT)

# Tests run in parallel (pytest-xdist): JOBS workers, more than the 2 cores, since most
# integration tests wait on processes and sockets; tests marked `rates` run one at a time.
# The pages' logic runs in Node's test runner (tests/js/pages/*.test.mjs), one pytest case
# a file (tests/labd/test_page_scripts.py); alone: node --test tests/js/pages/
JOBS ?= 3

unit: $(STAMP)
	$(PY) -m pytest -m "not integration" -n $(JOBS)

test: lint $(JSSTAMP) $(WEBSTAMP)
	$(PY) -m pytest -n $(JOBS) --dist loadgroup --durations=12

# The container images (labd:VERSION, labd-postgres:VERSION), built from this machine, and
# the deployment's smoke test: deploy/docker-compose.yml brought up on free ports, a
# submission, an evaluation, a rerun and a verified download through it, then torn down;
# then the same stack on a Ray cluster (deploy/docker-compose.ray.yml).
# About 4 minutes, so not part of `make test`; docs/operate.md. Both need root and Docker.
deploy-image: $(STAMP) $(WEBSTAMP)
	$(PY) deploy/build_image.py

deploy-smoke: $(STAMP) $(WEBSTAMP)
	$(PY) deploy/smoke.py
	$(PY) deploy/smoke.py --no-build --ray

bench: $(STAMP) $(WEBSTAMP)
	$(PY) bench/sim.py
	$(PY) bench/trial.py
	$(PY) bench/javascript.py
	$(PY) bench/bridge.py
	$(PY) bench/archive.py
	$(PY) bench/web.py
	$(PY) bench/replay.py
	$(PY) bench/live.py
	$(PY) bench/cli.py
	$(PY) bench/knn.py
	$(PY) bench/evaluate.py
	$(PY) bench/cluster.py
	$(PY) bench/crowds.py

clean:
	rm -rf $(VENV) $(JS)/node_modules $(WEB)/node_modules labd/web/static/vendor .mypy_cache .ruff_cache .pytest_cache
