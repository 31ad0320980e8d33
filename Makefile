# Two entry points for a fresh machine: `make demo` and `make test` (both create .venv when missing).
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
STAMP  := $(VENV)/.installed
OUT    ?= out

.PHONY: demo test install bench clean

$(STAMP): setup.cfg pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install --quiet --upgrade pip
	$(PIP) install --quiet -c constraints.txt -e '.[rl,dev]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	mkdir -p $(OUT)
	$(VENV)/bin/fms solve EX12 --out $(OUT)/EX12.schedule.json --gantt $(OUT)/EX12.gantt.png
	$(VENV)/bin/fms validate EX12 $(OUT)/EX12.schedule.json

test: $(STAMP)
	$(VENV)/bin/pytest

bench: $(STAMP)
	$(PY) bench/sim_speed.py

clean:
	rm -rf $(VENV) $(OUT) build src/*.egg-info
