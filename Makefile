# Two entry points do all the set-up on a fresh machine (Debian python3, gcc, cmake):
#   make demo   set up, then run the full suite on the default scenario, recording a bag
#   make test   set up, then run the tests
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
VENV_ABS := $(abspath $(VENV))
PY := $(VENV_ABS)/bin/python
SCENARIO ?= standing_push
CONTROLLER ?= none
PYTEST_ARGS ?=
# test processes (pytest-xdist; each test file runs whole on one, so module fixtures are computed once):
# 2 halves the suite on 2 cores (session 38: 555 s instead of 1018 s); 0 runs it in this process
TEST_WORKERS ?= 2

# rclpy needs a log dir; DDS stays on this machine; the ament index is the venv.
export ROS_LOG_DIR ?= $(CURDIR)/build/ros_log
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
export RMW_IMPLEMENTATION := rmw_fastrtps_cpp
export AMENT_PREFIX_PATH := $(VENV_ABS)
export MPLBACKEND := Agg

.PHONY: setup demo test lint bench interfaces install clean lock library library-execution

$(PY):
	@$(PYTHON) -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' || { \
	  echo "humfall_ros needs CPython 3.11: ROS 2 Jazzy's wheels on PyPI are cp311 (make PYTHON=python3.11 ...)"; exit 1; }
	@$(PYTHON) -c 'import venv, ensurepip' 2>/dev/null || { \
	  echo "$(PYTHON) has no venv/ensurepip module (Debian: apt install python3-venv)"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

$(VENV)/.deps-stamp: requirements.txt constraints.txt | $(PY)
	$(PY) -m pip install -q -r requirements.txt -c constraints.txt
	touch $@

INTERFACE_SRC := $(wildcard interfaces/*/msg/*.msg interfaces/*/srv/*.srv interfaces/*/CMakeLists.txt \
	interfaces/*/package.xml interfaces/cmake/*.cmake) tools/build_interface.sh

# tf2_msgs is not among the ROS wheels on PyPI: build our vendored copy of TFMessage
# unless a real one is importable (on a ROS install colcon ignores the copy).
$(VENV)/.interfaces-stamp: $(VENV)/.deps-stamp $(INTERFACE_SRC)
	@$(PY) -c 'import tf2_msgs.msg' 2>/dev/null && [ ! -f $(VENV)/.tf2-vendored ] || \
	  { tools/build_interface.sh tf2_msgs $(VENV) && touch $(VENV)/.tf2-vendored; }
	flock /tmp/humfall-interfaces.lock tools/build_interface.sh humfall_interfaces $(VENV)
	touch $@

interfaces: $(VENV)/.interfaces-stamp

install: $(VENV)/.interfaces-stamp
	# setuptools copies the sources into build/lib and never deletes there: a module moved or removed in the
	# source stayed in every later wheel (fall/step_control.py after its move to control/, session 27)
	rm -rf build/lib build/bdist.*
	$(PY) -m pip install -q --no-deps --force-reinstall .

setup: install

demo: setup
	$(VENV_ABS)/bin/humfall up --scenario $(SCENARIO) --controller $(CONTROLLER)

test: setup lint
	$(PY) -m pytest -q --durations=15 -n $(TEST_WORKERS) --dist loadfile $(PYTEST_ARGS)

lint: $(VENV)/.deps-stamp
	$(VENV_ABS)/bin/ruff check humfall_ros test benchmarks tools

bench: setup
	$(PY) benchmarks/run_all.py

# Rebuild the shipped plan library of the multi-contact planner (paper 2's tree search over a grid of pushes;
# docs/multicontact.md "Session 31", "Session 32"): `make -j2 library` takes ~20 min on 2 cores (97 plans). Forward 47.5 and
# 50 J are planned with the release bounded (release_t_max 0.1: the defaults find no 50 J plan from two feet, and
# their 47.5 J plan re-solves into plans that fail the re-simulation check above 47.5 J); a re-plan keeps each
# stored segment's duration bounds. Pushes without a plan (walls 0.6 m 40 / 50 J, 0.65 m 50 J, 0.7 m 50 J, 0.75 m 40 J)
# are left out and listed.
# --densify 1.25 then adds, between neighbouring entries without a wall, pushes 1.25 J apart as accepted warm re-plans of
# their neighbours (session 33: ~1 min; the online re-plans from them take fewer IPOPT iterations).
# --probe re-plans every entry half way to its neighbours (the online ranking tries an entry that failed there last).
# The tree searches, the densify and the probes run with the settings the shipped library was built with (LIBRARY_PINS:
# releases from 0.1 s, no short-release children; sessions 34 / 35 changed both defaults after it; 600 IPOPT iterations
# and none of IPOPT's infeasibility heuristics, both changed in session 36; foot landings from Table I's 0.25 s,
# 0.15 s since session 37: each stored segment keeps its duration bounds, so re-plans are unchanged) and its
# capture-cost weight (2000 J/m^2;
# 6000 since session 36: each file records it, the merge keeps it and the re-plans, densify and probes included, solve
# with it), so this target reproduces it; a library built with the new defaults is measured, not shipped
# (docs/multicontact.md "Session 34", "Session 35", "Session 36"). Since session 40 the pins and the defaults both
# keep plans off one foot at their end (single_foot_terminal false, single_foot_t_max 0.4 s: docs/multicontact.md
# "Session 40"); the library was rebuilt with them.
LIBRARY_OUT ?= config/multicontact_library/standing_pushes.json.gz
LIBRARY_PARTS := build/library/forward.json.gz build/library/forward_bounded_release.json.gz \
	build/library/backward.json.gz build/library/walls.json.gz \
	build/library/walls_between_a.json.gz build/library/walls_between_b.json.gz
BUILD_LIBRARY := OMP_NUM_THREADS=1 $(PY) -m humfall_ros.multicontact.build_library
LIBRARY_PINS := release_alternatives=[0],release_t_min=0.1,step_capture_weight=2000,max_iter=600,expect_infeasible=false,step_t_min=0,single_foot_terminal=false,single_foot_t_max=0.4
LIBRARY_TREE := --set '$(LIBRARY_PINS)'

build/library/forward.json.gz: | $(VENV)/.deps-stamp
	mkdir -p $(@D) && $(BUILD_LIBRARY) --kes 10,12.5,15,17.5,20,22.5,25,27.5,30,32.5,35,37.5,40,42.5,45 $(LIBRARY_TREE) --out $@

build/library/forward_bounded_release.json.gz: | $(VENV)/.deps-stamp
	mkdir -p $(@D) && $(BUILD_LIBRARY) --kes 47.5,50 --set 'release_t_max=0.1,$(LIBRARY_PINS)' --out $@

build/library/backward.json.gz: | $(VENV)/.deps-stamp
	mkdir -p $(@D) && $(BUILD_LIBRARY) --kes 10,15,20,25,30,35,40,45,50 --directions -1 $(LIBRARY_TREE) --out $@

build/library/walls.json.gz: | $(VENV)/.deps-stamp
	mkdir -p $(@D) && $(BUILD_LIBRARY) --kes 20,30,40,50 --walls 0.6,0.7,0.8,0.9,1.0 $(LIBRARY_TREE) --out $@

# the walls half way between (session 38): re-plans from a wall 5 cm away instead of 10
build/library/walls_between_a.json.gz: | $(VENV)/.deps-stamp
	mkdir -p $(@D) && $(BUILD_LIBRARY) --kes 20,30,40,50 --walls 0.65,0.75 $(LIBRARY_TREE) --out $@

build/library/walls_between_b.json.gz: | $(VENV)/.deps-stamp
	mkdir -p $(@D) && $(BUILD_LIBRARY) --kes 20,30,40,50 --walls 0.85,0.95 $(LIBRARY_TREE) --out $@

library: $(LIBRARY_PARTS)
	$(BUILD_LIBRARY) $(foreach f,$(LIBRARY_PARTS),--add $(f)) $(LIBRARY_TREE) --densify 1.25 --probe --out $(LIBRARY_OUT)

# The library of the plans made for the 3-D robot (planner.FOR_EXECUTION: step_capture_margin 0.25; the "execution"
# planner_profile's, planner.EXECUTION_LIBRARY): forward pushes 10-50 J by the tree search with today's defaults every
# 2.5 J, densified to 1.25 J and probed; ~3 min on one core, 33 plans (docs/multicontact.md "Session 43").
EXECUTION_LIBRARY_OUT ?= config/multicontact_library/execution_pushes.json.gz
library-execution: | $(VENV)/.deps-stamp
	$(BUILD_LIBRARY) --kes 10,12.5,15,17.5,20,22.5,25,27.5,30,32.5,35,37.5,40,42.5,45,47.5,50 \
		--set step_capture_margin=0.25 --densify 1.25 --probe --out $(EXECUTION_LIBRARY_OUT)

# Re-resolve the newest versions in a scratch venv and write them to constraints.txt.
lock:
	rm -rf build/lock-venv && $(PYTHON) -m venv build/lock-venv
	build/lock-venv/bin/pip install -q --upgrade pip && build/lock-venv/bin/pip install -q -r requirements.txt
	{ head -2 constraints.txt; build/lock-venv/bin/pip freeze | grep -viE '^(tf2-msgs|humfall)'; } > constraints.tmp
	mv constraints.tmp constraints.txt && rm -rf build/lock-venv

clean:
	rm -rf build $(VENV) *.egg-info
