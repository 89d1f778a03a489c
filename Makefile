# The two commands of the README:  `make demo`  and  `make test`.
# Both create the virtual environment and install granfe into it when missing.

VENV    := .venv
PY      := $(VENV)/bin/python
MPIEXEC := $(VENV)/bin/mpiexec
NP      ?= 2
# python3.12 from PATH, else a pyenv-installed 3.12 (pyenv shims refuse when 3.12 is not global)
PYTHON312 ?= $(shell for p in python3.12 $$HOME/.pyenv/versions/3.12*/bin/python3.12 /usr/bin/python3.12 /usr/local/bin/python3.12; do \
	$$p --version >/dev/null 2>&1 && { echo $$p; break; }; done)
SCENE   ?= scenes/cpt_2d.toml
PYTEST_ARGS ?=

export PYVISTA_OFF_SCREEN := true
export MPLBACKEND := Agg

.PHONY: demo test test-serial test-mpi venv lint clean

venv: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	@test -n "$(PYTHON312)" || { echo "error: python3.12 not found (needed for the dolfinx-solver-real wheel)"; exit 1; }
	@test -x $(PY) || $(PYTHON312) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e .[test]
	@touch $@

# the main job: the coupled DE x FE scene on 2 MPI ranks (outputs in output/<scene name>/)
demo: venv
	NUMBA_NUM_THREADS=1 $(MPIEXEC) -n $(NP) $(VENV)/bin/granfe run $(SCENE) --overwrite

# ruff, then the serial half (everything), then the MPI half (tests marked `mpi`) on 2 ranks;
# NUMBA_NUM_THREADS=1 under MPI so two ranks do not oversubscribe two cores.
test: venv
	$(MAKE) --no-print-directory lint
	$(MAKE) --no-print-directory test-serial
	$(MAKE) --no-print-directory test-mpi

test-serial: venv
	$(PY) -m pytest $(PYTEST_ARGS)

test-mpi: venv
	NUMBA_NUM_THREADS=1 $(MPIEXEC) -n 2 $(PY) -m pytest -m mpi -p no:cacheprovider $(PYTEST_ARGS)

# the style rules of pyproject.toml (imports, docstrings, complexity) on the whole tree
lint: venv
	$(PY) -m ruff check granfe dem coupling tests demos benchmarks meshes

clean:
	rm -rf output .pytest_cache
	find . -name __pycache__ -prune -exec rm -rf {} +
