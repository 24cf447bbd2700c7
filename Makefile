# Two commands for a new machine: `make run` (the demo) and `make test` (type check, then the suite).
# Both create .venv if missing and install the project into it first.
PYTHON ?= python3.11
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: run test install clean

run: $(STAMP)
	@$(BIN)/python -m compileall -q -j 0 $(SOURCES)
	$(BIN)/hil run hil_configs/demo.yaml

# Byte-compiled sources: where PYTHONDONTWRITEBYTECODE is set (as on our machines), every process
# of every run compiled the project's modules afresh (~0.3 s of each start); a stale file is
# never used (Python checks the source's time stamp).
SOURCES := adapters common harness scenarios targets timing training tests bench tools

# The type checker first (tools/typecheck.py; how strictly: [tool.mypy] in pyproject.toml), then the suite.
test: $(STAMP)
	@bash tools/install_chromium.sh
	@$(BIN)/python -m compileall -q -j 0 $(SOURCES)
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
