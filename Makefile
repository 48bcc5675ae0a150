# The two commands of the README:
#   make run   - set up a virtual environment and serve the API on the embedded SQLite default
#   make test  - set up the virtual environment and run the whole test suite (SQLite and PostgreSQL)
PYTHON ?= python3
VENV ?= .venv
BIN = $(VENV)/bin

.PHONY: run test setup lint bench

$(BIN)/gaitmon: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(BIN)/gaitmon

setup: $(BIN)/gaitmon

run: setup
	$(BIN)/gaitmon serve

test: setup
	$(BIN)/ruff check .
	$(BIN)/pytest -n 2 --dist loadgroup

lint: setup
	$(BIN)/ruff check .

# The figures of the README (each prints Markdown; see the README's Benchmarks section for the others).
bench: setup
	$(BIN)/python -m bench.accuracy
	$(BIN)/python -m bench.robustness
	$(BIN)/python -m bench.speed
