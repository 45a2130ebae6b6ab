# Two commands do everything (see README):
#   make demo   sets up .venv and runs the main job (a 4D language method beside the 2D floor) on a small
#               synthetic scene
#   make test   builds a fresh virtualenv from scratch and runs the whole test suite (CI runs this)
PYTHON ?= python3
VENV ?= .venv
TEST_VENV ?= .venv-test
# torch first and pinned: the CPU build lies on local disk; an unpinned torch pulls a CUDA build.
TORCH_SPEC ?= torch==2.13.0
# the versions of the other dependencies the suite passes with (pyproject.toml keeps lower bounds only)
CONSTRAINTS ?= constraints.txt
PYTEST_ARGS ?= -n 2 -q

.PHONY: setup demo test lint clean

$(VENV)/.installed: pyproject.toml $(CONSTRAINTS)
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install -q --upgrade pip
	$(VENV)/bin/python -m pip install -q -c $(CONSTRAINTS) "$(TORCH_SPEC)"
	$(VENV)/bin/python -m pip install -q -c $(CONSTRAINTS) -e ".[text,test]"
	touch $@

setup: $(VENV)/.installed

demo: setup
	$(VENV)/bin/bench4d demo
	@echo "To type bench4d without $(VENV)/bin/ in front: source $(VENV)/bin/activate"

test:
	rm -rf $(TEST_VENV)
	$(PYTHON) -m venv $(TEST_VENV)
	$(TEST_VENV)/bin/python -m pip install -q --upgrade pip
	$(TEST_VENV)/bin/python -m pip install -q -c $(CONSTRAINTS) "$(TORCH_SPEC)"
	$(TEST_VENV)/bin/python -m pip install -q -c $(CONSTRAINTS) -e ".[text,test]"
	bash tests/browser_setup.sh
	$(TEST_VENV)/bin/python -m pytest $(PYTEST_ARGS)

lint: setup
	$(VENV)/bin/python -m ruff check benchmark methods annotations tests

clean:
	rm -rf $(VENV) $(TEST_VENV) .pytest_cache
