# colgnn: `make demo` (set-up + main job) and `make test` (set-up + lint + import contracts + tests) work on a
# fresh clone.
PY      ?= python3
VENV    := .venv
VPY     := $(VENV)/bin/python
STAMP   := $(VENV)/.setup-done
PIPQ    := $(VPY) -m pip install --quiet --disable-pip-version-check
export OMP_NUM_THREADS ?= 2

.PHONY: setup test test-slow demo results speed clean

setup: $(STAMP)

# torch first, pinned: any other torch request pulls gigabytes of CUDA packages.
$(STAMP): setup.py setup.cfg requirements.txt
	test -x $(VPY) || $(PY) -m venv $(VENV)
	$(PIPQ) --upgrade pip
	$(PIPQ) torch==2.13.0
	$(PIPQ) ros-jazzy-rclpy ros-jazzy-common-interfaces ros-jazzy-rmw-fastrtps-cpp
	$(PIPQ) -r requirements.txt
	$(PIPQ) -e .
	@# The predictor node compiles its network by default: fill torch's on-disk cache now, so that its first
	@# start takes seconds instead of 10-30 s a model.
	$(VPY) -c "from colgnn_core.runtime.predictor import warm_compile_cache as w; from colgnn_core.scenes import scene_names as n; print('compile cache warmed (s):', {k: round(v, 1) for k, v in w(n()).items()})"
	touch $(STAMP)

# Lint (ruff) and the import contracts (import-linter; both configured in pyproject.toml) before the tests.
test: setup
	$(VPY) -m ruff check .
	$(VENV)/bin/lint-imports
	$(VPY) -m pytest -q

test-slow: setup
	$(VPY) -m pytest -q -m slow

# The predictor node on sphere_mat's shipped model with a scripted press: separate processes over DDS,
# a rosbag2 (MCAP) recording, a picture and a summary, all under out/demo (colgnn_ros/demo.py).
demo: setup
	$(VPY) -m colgnn_ros.demo --scene sphere_mat --out out/demo --docs docs --command "make demo"

# docs/RESULTS.md, docs/results.json and docs/img/: every table and picture, from the shipped checkpoints and
# test data simulated on this machine (data/results, resumable). About 55 min on an idle 2-core machine, 35 min with the test data already simulated (stated in the report).
results: setup
	$(VPY) -m colgnn_core evaluate --all --out docs --compile --threads 2

# docs/SPEED.md and docs/bench/*.json: the four shipped models against the IPC solver, one process, written by the
# command itself (about 5 min; run it on a quiet machine: the page records the load).
speed: setup
	$(VPY) -m colgnn_core bench --scene all --threads 2 --compile --frames 20 --rollouts 5 --markdown docs/SPEED.md

clean:
	rm -rf $(VENV) build install log *.egg-info
