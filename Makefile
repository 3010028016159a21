# The two commands of the README: `make demo` (the main job) and `make test` (the test suite).
# Both create the virtual environment and install everything on first use.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.rat-installed

.PHONY: demo test test-fast install zoo clean browser

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	MUJOCO_GL=$${MUJOCO_GL:-egl} $(BIN)/rat attack train --victim zoo:drawer-open-v3@bc --target opposite \
		--epsilon 0.1 --budget 1000 --preset cpu --seed 0 --out runs/demo

test: $(STAMP) browser
	$(BIN)/ruff check src tests examples benchmarks
	$(BIN)/python -m pytest -q

# The labelling page's browser test drives Debian's chromium; install it where we can (root and apt).
browser:
	@command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "installing chromium for the labelling page's browser test"; \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium >/dev/null 2>&1 || \
	    echo "could not install chromium: its test will be skipped (sudo apt-get install chromium)"; \
	  else echo "no chromium: the browser test will be skipped; install it with: sudo apt-get install chromium"; fi; }

# The fast tier while working: everything but the tests marked slow (Meta-World episodes, PPO, Ray, subprocesses).
test-fast: $(STAMP)
	$(BIN)/ruff check src tests examples benchmarks
	$(BIN)/python -m pytest -q -m "not slow"

zoo: $(STAMP)
	$(BIN)/rat victim zoo --jobs 2 --dest src/rat/zoo

clean:
	rm -rf $(VENV) runs
