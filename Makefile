# Two commands do all set-up on a fresh machine:
#   make demo   -- create/reuse .venv, install pinned dependencies, run the main job
#   make test   -- create/reuse .venv, install pinned dependencies, run lint, types, tests and tutorials
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: venv demo test lint typecheck pytest pytest-portable bench clean

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	# torch first and alone: `torch==2.13.0` resolves to the local CPU build where one is provided.
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -c constraints.txt -e ".[dev]"
	touch $(STAMP)

venv: $(STAMP)

demo: venv
	MPLBACKEND=Agg $(PY) -m torchcontact.demo --out runs/demo

lint: venv
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

typecheck: venv
	$(PY) -m mypy

pytest: venv
	MPLBACKEND=Agg $(PY) -m pytest

# The numerical tests again on other floating-point kernels: MKL's CPU-independent code path
# (MKL_CBWR=COMPATIBLE) and one thread, where the run above used the CPU's own (AVX2 or
# AVX-512) kernels and two threads. A test that judges digits the kernels decide fails here on
# any machine, not only on another CPU.
pytest-portable: venv
	MKL_CBWR=COMPATIBLE OMP_NUM_THREADS=1 MPLBACKEND=Agg $(PY) -m pytest -q -p no:cacheprovider \
		tests/contact tests/sim tests/filters tests/envs tests/states

test: lint typecheck pytest pytest-portable

bench: venv
	$(PY) -m pip install --quiet -c constraints.txt -e ".[dev,bench]"
	$(PY) benchmarks/bench_contact.py
	$(PY) benchmarks/bench_sim.py
	$(PY) benchmarks/bench_robots.py

clean:
	rm -rf $(VENV) runs .pytest_cache .mypy_cache .ruff_cache
