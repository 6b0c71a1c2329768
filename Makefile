# Two entry points for a fresh machine (Python >= 3.11 with venv):
#   make run    set up .venv, run the ROS 2 node on the default scene for DURATION simulated
#               seconds (Ctrl-C stops it cleanly), record out/track_one_box.mcap, convert it
#               to out/track_one_box.rrd for rerun
#   make test   set up .venv with the test tools, lint, run the test suite
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip --disable-pip-version-check -q
STAMP := $(VENV)/.installed

.PHONY: setup run test bench clean

$(STAMP): setup.py package.xml
	python3 -m venv $(VENV)
	$(PIP) install --upgrade pip setuptools wheel
	$(PIP) install -e '.[test]'
	touch $(STAMP)

setup: $(STAMP)

DURATION ?= 5.0
RTF ?= 1.0

run: $(STAMP)
	mkdir -p out
	ROS_AUTOMATIC_DISCOVERY_RANGE=$${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST} \
	$(VENV)/bin/sim_node --ros-args --params-file config/sim_node.params.yaml \
	    -p record_path:=out/track_one_box.mcap -p duration:=$(DURATION) \
	    -p real_time_factor:=$(RTF)
	$(VENV)/bin/feeder-sim replay out/track_one_box.mcap --rrd out/track_one_box.rrd --no-viewer

test: $(STAMP)
	$(VENV)/bin/ruff check feeder_sim test benchmarks
	$(PY) -m pytest -q test

bench: $(STAMP)
	$(PY) benchmarks/conveying.py
	$(PY) benchmarks/pile.py
	$(PY) benchmarks/throughput.py
	$(PY) benchmarks/node.py
	$(PY) benchmarks/methods.py

clean:
	rm -rf $(VENV) out build install log *.egg-info
