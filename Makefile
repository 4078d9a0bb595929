# Two commands a new user needs: `make demo` and `make test`. Both set up .venv first.
# The rclpy wheels exist for CPython 3.11-3.13: take the first of them on PATH (or pass PYTHON=...).
PYTHON ?= $(firstword $(foreach candidate,python3.11 python3.12 python3.13,$(shell command -v $(candidate) 2>/dev/null)))
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: setup demo test docs reproduce bench lint clean

$(BIN)/lenn-ros: setup.py setup.cfg
	@if [ -z "$(PYTHON)" ]; then \
		echo "make: no python3.11, python3.12 or python3.13 on PATH (the rclpy wheels need one of them):" \
			"install one (Ubuntu 24.04: apt install python3.12-venv) or pass PYTHON=/path/to/python3.1x" >&2; \
		exit 1; \
	fi
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[ros,plot,progress,test,docs]'
	touch $@

setup: $(BIN)/lenn-ros

demo: setup
	$(BIN)/lenn-ros demo

test: setup
	$(BIN)/ruff check lenn_ros test bench docs
	$(MAKE) docs
	$(BIN)/python -m pytest -q

# The documentation site: the parameter page must match config.py (regenerate it with
# `python docs/gen_parameters.py`), then every page, link and anchor must build (--strict).
docs: setup
	$(BIN)/python docs/gen_parameters.py --check
	$(BIN)/mkdocs build --strict --quiet

reproduce: setup
	$(BIN)/lenn-ros reproduce --plots results

bench: setup
	$(BIN)/python bench/speed.py

clean:
	rm -rf $(VENV) build install log results site *.egg-info
