# Two commands on a fresh clone: `make demo` and `make test`. Both set everything up.
SHELL := /bin/bash
PY := .venv/bin/python

.PHONY: setup demo test test-python test-frontend lint compose-check bench clean

setup:
	@bash scripts/setup.sh

demo: setup
	@$(PY) -m worker.demo $(if $(PORT),--port $(PORT))

lint: setup
	@.venv/bin/ruff check backend worker rig_agent tests bench
	@.venv/bin/lint-imports --no-cache

compose-check: setup
	@bash scripts/compose_check.sh

test-python: setup
	@$(PY) -m pytest -n 2 --dist loadgroup

test-frontend: setup
	@if [ -f frontend/package.json ]; then cd frontend && npx vitest run; fi

test: lint compose-check test-frontend test-python

bench: setup
	@for b in bench/*.py; do echo "== $$b"; $(PY) $$b; done

clean:
	rm -rf .venv frontend/node_modules frontend/dist var
