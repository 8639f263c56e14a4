# One command runs the main job, one runs the tests; each sets itself up.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# ROS traffic stays on this machine; each target picks its own domain.
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST

.PHONY: setup run identify test test-quick test-durations lint bench bench-sizes bench-node bench-dask bench-certify bench-certify-scale bench-reach bench-generalise bench-unseen bench-speed bench-online bench-mimo bench-accuracy bench-scale bag experiment report clean

INTERFACES := $(wildcard interfaces/spm_sysid_interfaces/*.* interfaces/spm_sysid_interfaces/*/*)

$(STAMP): setup.py package.xml interfaces/build_in_venv.py $(INTERFACES)
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[ros,test,interfaces]'
	# the messages, service and action (spm_sysid_interfaces), built with colcon into .venv
	$(BIN)/python interfaces/build_in_venv.py
	touch $(STAMP)

# compile the numeric kernels now (numba's disk cache) and build their ahead-of-time
# extension, not in the first command; again whenever a kernel module changes
KERNELS := $(VENV)/.kernels
KERNEL_SOURCES := $(addprefix spm_sysid/core/,compiled/kernels.py model/chain.py model/simulation.py search/branch_bound.py model/coupled.py model/regressor_sim.py fit/levenberg.py fit/free_run.py compiled/registry.py compiled/aot.py jobs/warmup.py)
$(KERNELS): $(STAMP) $(KERNEL_SOURCES)
	$(BIN)/spm-sysid compile
	touch $(KERNELS)

setup: $(KERNELS)

## The main job: the ROS pipeline on the robot-arm data (bag -> node -> identify).
run: $(KERNELS)
	ROS_DOMAIN_ID=61 $(BIN)/python -m spm_sysid.apps.pipeline --out out/run

## The offline identification on the robot-arm data.
identify: $(KERNELS)
	$(BIN)/spm-sysid identify --criterion aic --seed 1 --json out/model.json --plots out/figures

# the report and dashboard tests run in a real headless Chromium from Debian's packages
BROWSER := $(VENV)/.browser
$(BROWSER):
	command -v chromium >/dev/null || [ "$$(id -u)" != 0 ] || { apt-get update -q && \
	  DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium; } || true
	command -v chromium >/dev/null && touch $(BROWSER) || echo "Chromium is missing" \
	  "(apt-get install chromium, as root): the browser tests will be skipped, and say so"

test: $(KERNELS) $(BROWSER)
	# three workers on 2 cores (most ROS tests wait on processes); tests spread one by one,
	# the files with an expensive module fixture (Dask cluster, colcon build) kept together;
	# a worker's crash fails one test, never hangs the run (test/helpers/scheduling.py)
	ROS_DOMAIN_ID=62 $(BIN)/python -m pytest -q -n 3 --dist loadgroup test

## The tests without those marked slow (each over about 15 s): a quicker check while working.
test-quick: $(KERNELS) $(BROWSER)
	ROS_DOMAIN_ID=62 $(BIN)/python -m pytest -q -n 3 --dist loadgroup -m "not slow" test

# measure every test (the whole suite, about 13 minutes) and list those over 2.5 s in
# test/slow_tests.txt: they are marked slow, so test-quick leaves them out
test-durations: $(KERNELS) $(BROWSER)
	ROS_DOMAIN_ID=62 $(BIN)/python -m pytest -q -n 3 --dist loadgroup --durations=0 -vv test \
		| tee /dev/stderr | $(BIN)/python test/helpers/slow_list.py

lint: $(KERNELS)
	$(BIN)/ruff check .

bench: $(KERNELS)
	$(BIN)/python -m benchmarks.commands bench

## GA time and memory against term-space size and samples, with the FastCan baseline.
bench-sizes: $(KERNELS)
	$(BIN)/python -m pip install --quiet -e '.[bench]'
	$(BIN)/python -m benchmarks.commands bench-sizes --fastcan

bag: $(KERNELS)
	$(BIN)/spm-sysid make-bag --output bags/robot_arm --force

experiment: $(KERNELS)
	$(BIN)/spm-sysid experiment --out out/experiment --force

report: $(KERNELS)
	$(BIN)/spm-sysid experiment --out out/experiment --report out/report --force

clean:
	rm -rf build install log out .pytest_cache

## Certification: robot-arm data and records made hard on purpose, 60 s each.
bench-certify: $(KERNELS)
	$(BIN)/python -m benchmarks.certify

## The spaces users search (84, 164 and 454 candidates) on real records, beside SCIP's MIQP.
bench-certify-scale: $(KERNELS)
	$(BIN)/python -m pip install --quiet -e '.[bench]'
	$(BIN)/python -m benchmarks.certify_scale

## The GA + polish at 84 candidates ((3, 3, 3)): 20 seeds per record and criterion, how many
## reach the best value known.
bench-reach: $(KERNELS)
	$(BIN)/python -m benchmarks.reach

## Where a command's time goes; the quick command against a DEAP GA; GA and simulation times.
bench-speed: $(KERNELS)
	$(BIN)/python -m pip install --quiet -e '.[bench]'
	$(BIN)/python -m benchmarks.speed --large

## Second-half free run against the linear ARX yardstick: robot arm, dryer, heat exchanger,
## two tanks, the two-link arm (two outputs); Silverbox and Wiener-Hammerstein on their
## test parts beside the published figures.
bench-accuracy: $(KERNELS)
	$(BIN)/python -m benchmarks.accuracy

## identify --focus simulation --orders auto at 10^4, 3*10^4, 10^5 samples (the
## Wiener-Hammerstein record cut) and a 10-minute 1 kHz joint: seconds, peak memory, slope.
bench-scale: $(KERNELS)
	$(BIN)/python -m benchmarks.scale

## Models on data they were not fitted on: two-tank cascade, robot-arm halves, coverage.
bench-generalise: $(KERNELS)
	$(BIN)/python -m benchmarks.generalise

## The command as typed on kinds of record nobody here fitted (two-level and PRBS inputs, spikes, ...).
bench-unseen: $(KERNELS)
	$(BIN)/python -m benchmarks.unseen

## Online monitor and tracker: detection delay, false alarms, drift tracking, cost per sample.
bench-online: $(KERNELS)
	$(BIN)/python -m benchmarks.online

## Several outputs: a two-link arm identified as one coupled model, against two single-output runs.
bench-mimo: $(KERNELS)
	$(BIN)/python -m benchmarks.mimo
	$(BIN)/python -m benchmarks.mimo --focus simulation --repeats 1

## Study on the local pool vs a 2-worker Dask cluster (the paper's 180 runs).
bench-dask: $(KERNELS)
	$(BIN)/python -m benchmarks.cluster

## Node benchmark: ingest at 1 kHz for 60 s, identify latency, memory with 100000 pairs.
bench-node: $(KERNELS)
	$(BIN)/python -m benchmarks.node
