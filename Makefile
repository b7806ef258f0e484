# Two commands on a fresh machine: `make demo` and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test test-under-load test-slow lint bench clean

$(STAMP): pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/cellcal demo

# Four workers (pytest-xdist), each test file on one worker in file order. Four on two cores:
# many tests wait on services and subprocesses, so two more workers fill the cores meanwhile
# (on 12 service-heavy files, A B A B at load ~20: 376/493 s with two, 264/396 s with four,
# the same CPU time).
test: $(STAMP)
	$(PY) -m pytest -q -m "not slow" -n 4 --dist loadfile

# `make test` RUNS times in a row while BUSY CPU-bound processes run (tools/test-under-load).
RUNS ?= 1
BUSY ?= 4
test-under-load: $(STAMP)
	BUSY=$(BUSY) tools/test-under-load $(RUNS)

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

lint: $(STAMP)
	$(VENV)/bin/ruff check .

bench: $(STAMP)
	$(PY) -m benchmarks.handeye_accuracy
	$(PY) -m benchmarks.kappa_nu

clean:
	rm -rf $(VENV) build *.egg-info
