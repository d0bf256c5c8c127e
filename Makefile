# The two commands: `make run` (the gateway against the built-in simulators) and `make test`.
# Both create .venv and install the project into it on first use.
VENV ?= .venv
PY := $(VENV)/bin/python
CONFIG ?=

.PHONY: run test lint docs mbpoll interop mutation

$(VENV)/.installed: pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	touch $@

run: $(VENV)/.installed
	$(VENV)/bin/slc-gateway run $(CONFIG)

# mbpoll is the second, independent Modbus client of the end-to-end tests (Debian package).
mbpoll:
	@command -v mbpoll >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -qq && apt-get install -y -qq mbpoll openssl >/dev/null; \
	  elif command -v sudo >/dev/null 2>&1; then sudo apt-get update -qq && sudo apt-get install -y -qq mbpoll openssl >/dev/null; \
	  else echo "mbpoll not installed: its end-to-end tests will be skipped"; fi; }

# Three workers (pytest-xdist) on the 2-core machine: most tests wait on processes, brokers and sockets, so a
# third worker fills the cores they leave idle; a test file stays on one worker; the 25 slowest printed at the end.
PYTEST_WORKERS ?= 3
test: $(VENV)/.installed mbpoll
	$(PY) -m pytest -n $(PYTEST_WORKERS) --dist loadfile --durations=25 $(PYTEST_ARGS)

lint: $(VENV)/.installed
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy --strict gateway

# The documentation site (mkdocs.yml, docs/) into site/, with every warning an error (a broken link, a page
# missing from the nav's files); the generated reference pages first checked against the code
# (python tools/gen_reference.py writes them again).
docs: $(VENV)/.installed
	@$(PY) -c 'import material' 2>/dev/null || $(PY) -m pip install -q -e '.[test,docs]'
	$(PY) tools/gen_reference.py --check
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict

# Controllers written independently from the same manuals (../shared/interop), against the
# installed gateway: `make interop` (correctness), `make interop STRICT=1` (also availability and
# latency targets).
INTEROP ?= ../shared/interop/run
interop: $(VENV)/.installed
	@test -x $(INTEROP) || { echo "$(INTEROP) not found: clone the project with ../shared beside it"; exit 2; }
	SLC_GATEWAY=$(VENV)/bin/slc-gateway $(INTEROP) $(if $(STRICT),--strict)

# Mutation testing of the protocol cores, writes.py, image.py, cache.py, modbus/handler.py and admission.py,
# unit.py, unit_writes.py, the kinds' drivers, units, plans and target store, and issue 42's modules (schedule, poller,
# link_health, freshness, reload, tags, modbus/connection, sparkplug/*) (tools/mutation.py,
# docs/develop/mutation.md): a whole run takes about 2 hours on 2 cores, so use --changed (weekly, not in
# CI: any run pays about 17 min of type check and test map first); not part of `make test`.
# MUTATION_ARGS: module paths or globs, --changed (only the modules changed since their last run),
# --keep, --report (see tools/mutation.py).
mutation: $(VENV)/.installed
	@$(PY) -c 'import mutmut' 2>/dev/null || $(PY) -m pip install -q -e '.[test,mutation]'
	$(PY) tools/mutation.py $(MUTATION_ARGS)
