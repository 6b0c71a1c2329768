# Two entry points for a fresh machine (Python >= 3.11 with venv):
#   make run    set up .venv, run the default scene for 2 s, record out/track_one_box.mcap
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

run: $(STAMP)
	$(VENV)/bin/feeder-sim run track_one_box --duration 2 \
	    --record out/track_one_box.mcap --summary out/track_one_box.json

test: $(STAMP)
	$(VENV)/bin/ruff check feeder_sim test benchmarks
	$(PY) -m pytest -q test

bench: $(STAMP)
	$(PY) benchmarks/conveying.py

clean:
	rm -rf $(VENV) out build install log *.egg-info
