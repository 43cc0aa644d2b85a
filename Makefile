# Two commands do all set-up on a fresh machine:
#   make demo   -- create/reuse .venv, install pinned dependencies, run the main job
#   make test   -- create/reuse .venv, install pinned dependencies, run lint, types, tests and tutorials,
#                  and build the documentation site in strict mode
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
WORKERS ?= auto

.PHONY: venv demo test lint typecheck docs pytest pytest-portable bench clean

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	# torch first and alone: `torch==2.13.0` resolves to the local CPU build where one is provided.
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -c constraints.txt -e ".[dev,docs,sweep]"
	touch $(STAMP)

venv: $(STAMP)

demo: venv
	MPLBACKEND=Agg $(PY) -m torchcontact.demo --out runs/demo

lint: venv
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

typecheck: venv
	$(PY) -m mypy

# The documentation site, strict (a broken reference or a docstring warning fails), built into a
# temporary folder; `$(PY) -m mkdocs serve` shows it while editing.
docs: venv
	site=$$(mktemp -d) && NO_MKDOCS_2_WARNING=1 $(PY) -m mkdocs build --strict --quiet --site-dir "$$site" \
		&& rm -rf "$$site"

# The suite on every core (pytest-xdist), one torch thread per worker, with the CPU's own
# (AVX2 or AVX-512) kernels. Each worker takes whole files (their module fixtures are built
# once) in collection order, where tests/conftest.py puts the files with slow tests first:
# xdist's default order (most tests first) would start those few-test, minutes-long files last.
XDIST := -n $(WORKERS) --dist loadfile --no-loadscope-reorder
pytest: venv
	OMP_NUM_THREADS=1 MPLBACKEND=Agg $(PY) -m pytest $(XDIST)

# The numerical tests again on other floating-point kernels: MKL's CPU-independent code path
# (MKL_CBWR=COMPATIBLE) and two torch threads, where the run above used the CPU's own kernels
# and one thread. A test that judges digits the kernels or the threads decide fails here on any
# machine, not only on another CPU. One process: its two threads take both cores. The tests
# marked slow (compiling a model: minutes) run once, above.
pytest-portable: venv
	MKL_CBWR=COMPATIBLE OMP_NUM_THREADS=2 MPLBACKEND=Agg $(PY) -m pytest -q -p no:cacheprovider \
		-m "not slow" tests/contact tests/sim tests/filters tests/envs tests/states

# `docs` is not a step of `test`: tests/test_docs.py builds the site in strict mode.
test: lint typecheck pytest pytest-portable

bench: venv
	$(PY) -m pip install --quiet -c constraints.txt -e ".[dev,docs,sweep,bench]"
	$(PY) benchmarks/bench_contact.py
	$(PY) benchmarks/bench_sim.py
	$(PY) benchmarks/bench_sim3d.py
	$(PY) benchmarks/bench_bhand.py
	$(PY) benchmarks/accuracy_sim3d.py
	$(PY) benchmarks/bench_robots.py

clean:
	rm -rf $(VENV) runs site .pytest_cache .mypy_cache .ruff_cache
