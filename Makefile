# Two entry points for a fresh machine: `make demo` and `make test` (both create .venv when missing).
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
STAMP  := $(VENV)/.installed
OUT    ?= out
# test workers (pytest-xdist): the CI machine has 2 cores; `make test TEST_JOBS=0` runs in one process
TEST_JOBS ?= 2

.PHONY: demo test install bench clean

# extras: rl = torch (the CPU build pinned by constraints.txt) and sb3; ros = ROS 2 Jazzy from PyPI's wheels;
# dev = pytest (with xdist: the tests run on TEST_JOBS workers) and colcon (tests/ros/test_colcon.py builds a
# ROS 2 workspace)
$(STAMP): setup.cfg pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install --quiet -c constraints.txt -e '.[rl,ros,dev]'
	touch $(STAMP)

install: $(STAMP)

# the shop, agent and recorder ROS 2 nodes as processes, on this machine only
demo: $(STAMP)
	mkdir -p $(OUT)
	ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST $(VENV)/bin/fms up EX12 --solver best \
		--out $(OUT)/EX12.schedule.json --db $(OUT)/fms.sqlite --gantt-dir $(OUT)
	$(VENV)/bin/fms validate EX12 $(OUT)/EX12.schedule.json

test: $(STAMP)
	$(VENV)/bin/pytest -n $(TEST_JOBS)

bench: $(STAMP)
	$(PY) bench/sim_speed.py

clean:
	rm -rf $(VENV) $(OUT) build src/*.egg-info
