# The two commands of the README: `make demo` (the main job) and `make test` (the test suite).
# Both create the virtual environment and install everything on first use.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.rat-installed

.PHONY: demo test test-fast install zoo clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	MUJOCO_GL=$${MUJOCO_GL:-egl} $(BIN)/rat attack train --victim zoo:drawer-open-v3 --target opposite \
		--epsilon 0.1 --budget 1000 --preset cpu --seed 0 --out runs/demo

test: $(STAMP)
	$(BIN)/python -m pytest -q

# The fast tier while working: everything but the tests marked slow (Meta-World episodes, PPO, Ray, subprocesses).
test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow"

zoo: $(STAMP)
	$(BIN)/rat victim zoo --jobs 2 --dest src/rat/zoo

clean:
	rm -rf $(VENV) runs
