# Two entry points for a fresh machine (Python >= 3.11 with venv):
#   make run    set up .venv, run the ROS 2 node on the default scene for DURATION simulated
#               seconds (Ctrl-C stops it cleanly), record out/track_one_box.mcap, convert it
#               to out/track_one_box.rrd for rerun
#   make test   set up .venv with the test tools, lint, run the test suite
VENV ?= .venv
PY := $(VENV)/bin/python
# not -q: a line per package collected and installed, a fresh install's progress
PIP_INSTALL := $(PY) -m pip --disable-pip-version-check install --progress-bar off
# `make run` installs what running needs (the ROS 2 wheels, rerun for the replay); `make test`
# adds the study tools (Dask) and the test tools (colcon, pytest, hypothesis, ruff, pymunk)
RUN_STAMP := $(VENV)/.installed-run
TEST_STAMP := $(VENV)/.installed-test

.PHONY: setup run test bench figures clean

$(PY):
	python3 -m venv $(VENV)
	@# no colcon package inside (the ROS wheels' share/ folders hold package.xml files)
	touch $(VENV)/COLCON_IGNORE
	$(PIP_INSTALL) --upgrade pip setuptools wheel

IFC := $(wildcard interfaces/build.py interfaces/requirements.txt interfaces/feeder_sim_interfaces/*.* \
    interfaces/feeder_sim_interfaces/*/*)

$(RUN_STAMP): setup.py package.xml $(IFC) | $(PY)
	@echo "installing feeder_sim with the ROS 2 wheels and rerun into $(VENV), then building its part services (a minute or two)"
	$(PIP_INSTALL) -e '.[ros,replay,interfaces]'
	$(PY) interfaces/build.py
	touch $(RUN_STAMP)

$(TEST_STAMP): setup.py package.xml $(IFC) | $(PY)
	@echo "installing feeder_sim with the ROS 2 wheels, rerun and the test tools into $(VENV), then building its part services"
	$(PIP_INSTALL) -e '.[test]'
	$(PY) interfaces/build.py
	touch $(TEST_STAMP) $(RUN_STAMP)

setup: $(RUN_STAMP)

DURATION ?= 5.0
RTF ?= 1.0

run: $(RUN_STAMP)
	mkdir -p out
	@# the first compile, with its progress, before the node starts (seconds when cached)
	$(VENV)/bin/feeder-sim compile track_one_box --method event_driven
	ROS_AUTOMATIC_DISCOVERY_RANGE=$${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST} \
	$(VENV)/bin/sim_node --ros-args --params-file config/sim_node.params.yaml \
	    -p record_path:=out/track_one_box.mcap -p duration:=$(DURATION) \
	    -p real_time_factor:=$(RTF)
	$(VENV)/bin/feeder-sim replay out/track_one_box.mcap --rrd out/track_one_box.rrd --no-viewer

test: $(TEST_STAMP)
	$(VENV)/bin/ruff check feeder_sim test benchmarks interfaces
	@# not -q: each module's name starts its line of dots, so a long one shows which it is
	$(PY) -m pytest test

bench: $(TEST_STAMP)
	$(PY) benchmarks/conveying.py
	$(PY) benchmarks/pile.py
	$(PY) benchmarks/throughput.py
	$(PY) benchmarks/node.py
	$(PY) benchmarks/methods.py

# Maintainers only: regenerate the figures and reports the README publishes (the tracked files
# under docs/; about 40 min on a 2-core machine). Every other documented command writes under out/.
STUDY_FIGURES = track_speed_map:conveying_speed_mps hook_orienter:fraction_open_end_up \
    hook_orienter_fed:fraction_open_end_up cup_drop:outcomes
figures: $(TEST_STAMP)
	$(VENV)/bin/feeder-sim paper --out out/paper
	cp out/paper/*.png docs/figures/
	$(VENV)/bin/feeder-sim accuracy --out docs/accuracy
	$(VENV)/bin/feeder-sim stability --out docs/stability
	for pair in $(STUDY_FIGURES); do study=$${pair%%:*}; plot=$${pair##*:}; \
	    $(VENV)/bin/feeder-sim study config/studies/$$study.yaml --out out/studies/$$study \
	        && cp out/studies/$$study/$$plot.png docs/studies/$$study.png || exit 1; done

clean:
	rm -rf $(VENV) out build install log *.egg-info
