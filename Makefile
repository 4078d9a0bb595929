# Two commands a new user needs: `make demo` and `make test`. Both set up .venv first.
PYTHON ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: setup demo test reproduce bench lint clean

$(BIN)/lenn-ros: setup.py setup.cfg
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[ros,test]'
	touch $@

setup: $(BIN)/lenn-ros

demo: setup
	$(BIN)/lenn-ros demo

test: setup
	$(BIN)/ruff check lenn_ros test bench
	$(BIN)/python -m pytest -q

reproduce: setup
	$(BIN)/lenn-ros reproduce --plots results

bench: setup
	$(BIN)/python bench/speed.py

clean:
	rm -rf $(VENV) build install log results *.egg-info
