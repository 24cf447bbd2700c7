# Two commands for a new machine: `make run` (the demo) and `make test` (type check, then the suite).
# Both create .venv if missing and install the project into it first.
PYTHON ?= python3.11
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: run test install clean

run: $(STAMP)
	$(BIN)/hil run hil_configs/demo.yaml

# The type checker first (tools/typecheck.py; how strictly: [tool.mypy] in pyproject.toml), then the suite.
test: $(STAMP)
	@bash tools/install_chromium.sh
	$(BIN)/python tools/typecheck.py
	$(BIN)/python -m pytest -q

install: $(STAMP)

$(STAMP): pyproject.toml sdk/pyproject.toml setup.py constraints.txt Makefile tools/check_system.sh
	@bash tools/check_system.sh "$(PYTHON)"
	@test -x $(BIN)/python || $$(bash tools/check_system.sh --print-python "$(PYTHON)") -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ./sdk -e ".[dev,ai]" -c constraints.txt
	@$(BIN)/python -m hil.scenarios.gl || bash tools/check_system.sh --gl-help
	@touch $(STAMP)

clean:
	rm -rf $(VENV) runs .pytest_cache
