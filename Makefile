# The two commands of the README:
#   make run   - set up, then regenerate the main result (see README)
#   make test  - set up, then run the test suite
PY ?= python3
export OMP_NUM_THREADS ?= 1

.PHONY: setup run test lint bench

setup:
	bash scripts/setup.sh

run: setup
	bash scripts/main_job.sh

test: setup
	$(PY) -m pytest -q -n auto --dist loadfile tests; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: failing"; exit 1; fi; exit $$rc

lint:
	ruff check .

bench:
	$(PY) -m pytest benchmarks --benchmark-enable -q
