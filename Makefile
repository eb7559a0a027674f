# Two entry points (see README): `make demo` and `make test`.
# Both create .venv with Python 3.11+, install torch==2.13.0 first (the CPU wheel), then the project.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
DEMO_OUT ?= demo_out

.PHONY: demo test lint venv clean

$(BIN)/n2f2: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e ".[test,ray]"
	touch $(BIN)/n2f2

venv: $(BIN)/n2f2

demo: venv
	$(BIN)/n2f2 demo --out $(DEMO_OUT)

# Lint, format and type checks of src/ first (settings in pyproject.toml), then the suite.
lint: venv
	$(BIN)/ruff check src
	$(BIN)/ruff format --check src
	$(BIN)/pyright -p .

test: lint
	$(BIN)/python -m pytest tests

clean:
	rm -rf $(VENV) $(DEMO_OUT)
