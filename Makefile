# Retain: every target sets up .venv itself (pinned by requirements.lock), then runs.
# Any KEY=VALUE on the command line is passed through as a config override, e.g.
#   make bench METHOD=consft PROFILE=quick SEED=1 steps_per_task=2000

# Python 3.12 (lerobot 0.6 needs >= 3.12): `python3.12` where it runs, else a pyenv install of it
PYTHON ?= $(firstword $(foreach p,python3.12 $(wildcard $(HOME)/.pyenv/versions/3.12*/bin/python3.12),\
	$(if $(shell $(p) -c 'import sys; assert sys.version_info[:2] == (3, 12)' 2>/dev/null && echo ok),$(p))))
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export MUJOCO_GL ?= egl
# offline unless the environment says otherwise (HF_HUB_OFFLINE=0 make bench ... policy_path=<hub id>)
export HF_HUB_OFFLINE ?= 1
export TRANSFORMERS_OFFLINE ?= $(HF_HUB_OFFLINE)
export TOKENIZERS_PARALLELISM := false
export PYTHONUNBUFFERED := 1

# Command-line variables (METHOD=..., steps_per_task=...) become overrides for the harness.
OVERRIDES := $(strip $(foreach v,$(MAKEOVERRIDES),$(if $(findstring =,$(v)),$(v))))
quote = $(foreach v,$(1),'$(v)')  # one shell word each: GRID="a=1,2;b=3" keeps its ';'

.PHONY: bench compare sweep study report test lint ui mlflow-server venv clean-cache bench-train bench-methods bench-envs \
	bench-eval bench-tracking libero-check test-slow gpu-check

PIP := $(PY) -m pip install --quiet --disable-pip-version-check

# A venv of another Python (an older checkout's 3.11) is rebuilt. The second pip step is
# robosuite's mink pin (requirements-nodeps.lock says why). draccus, a lerobot dependency, ships
# its own test suite as a top-level package `tests`, which would shadow this project's tests/.
$(STAMP): requirements.lock requirements-nodeps.lock pyproject.toml
	@$(PY) -c 'import sys; sys.exit(sys.version_info[:2] != (3, 12))' 2>/dev/null || { \
		test -n "$(PYTHON)" || { echo "error: Python 3.12 not found (python3.12 on PATH, or PYTHON=...)"; exit 1; }; \
		rm -rf $(VENV) && $(PYTHON) -m venv $(VENV); }
	$(PIP) -r requirements.lock
	$(PIP) --no-deps -r requirements-nodeps.lock
	$(PIP) --no-deps --no-build-isolation -e .
	site=$$($(PY) -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])') && test -n "$$site" \
		&& rm -rf "$$site/tests"
	$(PY) -m suites.libero.install
	@touch $(STAMP)

venv: $(STAMP)

bench: $(STAMP)
	$(PY) -m harness bench $(call quote,$(OVERRIDES))

REPORT_ARGS := $(filter EXPERIMENT=% BENCH=% PROFILE=% results_dir=% log_run=% open=%,$(OVERRIDES))
REPORT = $(PY) -m harness.report $(call quote,$(REPORT_ARGS))

# every method on the same foundation, then the report: make compare BENCH=mw-quick SEEDS=3
compare: $(STAMP)
	$(PY) -m harness bench METHOD=all $(call quote,$(filter-out METHOD=%,$(OVERRIDES)))
	$(REPORT)

# one run per grid point and seed, then the report: make sweep METHOD=consft GRID="kappa=0.1,1.0"
sweep: $(STAMP)
	$(PY) -m harness bench $(call quote,$(OVERRIDES))
	$(REPORT)

# a study's parts, each a comparison that resumes where it stopped, then each part's report:
#   make study STUDY=regimes [PART=mw-broad-6] [SEED=0 SEEDS=1] [DRY=1] [executor=local jobs=2]; docs/study.md
study: $(STAMP)
	$(PY) -m harness study $(call quote,$(OVERRIDES))

# tables, plots and the HTML page (report.html, with the rollout videos) rebuilt from the MLflow
# store: make report [EXPERIMENT=mw-quick] [open=1: open the page in the browser]
report: $(STAMP)
	$(REPORT)

# make bench-train [device=cuda] [compile=true]: the CPU sizes' step phases, or pi0 on a GPU
bench-train: $(STAMP)
	$(PY) -m harness.perf.throughput train $(call quote,$(filter device=% compile=%,$(OVERRIDES)))

bench-methods: $(STAMP)
	$(PY) -m harness.perf.throughput methods

# make bench-eval [BENCH=libero-quick] [WORKERS=2] [cameras=true image_size=128] [device=cuda]
bench-eval: $(STAMP)
	$(PY) -m harness.perf.throughput eval $(or $(WORKERS),2) --bench $(or $(BENCH),mw-quick) \
		$(if $(filter true,$(cameras)),--cameras --image-size $(or $(image_size),128)) \
		$(if $(device),--device $(device))

# make bench-envs [BENCH=libero-paper] [TASKS=12] [cameras=true image_size=128] [STEPS=200] [RESETS=10] [VIEWS=100]:
# the memory and build time of a benchmark's simulators, one per task as an evaluation holds them;
# then, on LIBERO, its first task's control step: the physics alone, robosuite's path and the fast
# path, side by side (and with cameras=true the same with both cameras rendering; STEPS=0 skips
# it), how far its joint positions move when the controls are off in their last bits, and a fresh
# scene's reset by robosuite's reload and in place; then, for LIBERO, Meta-World and bimanual, a
# camera view's milliseconds at render=faithful and render=fast and their images' difference over
# VIEWS frames (default 100; 0 skips it)
bench-envs: $(STAMP)
	$(PY) -m harness.perf.throughput envs --bench $(or $(BENCH),libero-paper) $(if $(TASKS),--tasks $(TASKS)) \
		$(if $(filter true,$(cameras)),--cameras --image-size $(or $(image_size),128)) \
		$(if $(STEPS),--steps $(STEPS)) $(if $(RESETS),--resets $(RESETS)) $(if $(VIEWS),--view-frames $(VIEWS))

# every CUDA path end to end on a tiny budget, a PASS or FAIL line and a figure per part (pi0 at
# batch 64: samples/s and MFU; evaluation with two 128-px cameras; a GPU run killed and resumed):
#   make gpu-check [device=cuda|cpu] [parts=train,methods,eval,resume]; without a GPU, a CPU
#   smoke test.
#   On a device machine without the project's packages: docs/performance.md, "The GPU check"
gpu-check: $(STAMP)
	$(PY) -m harness.perf.gpu_check $(call quote,$(filter device=% parts=%,$(OVERRIDES)))

# N processes log what a benchmark job logs, all at once, to one loopback `mlflow server` started as
# mlflow-server starts it, then to SQLite; the store is read back: nothing lost, errors retried or
# reported, runs/s and points/s. make bench-tracking [WRITERS=8,16,32] [STORES=server,sqlite]
WRITERS ?= 8,16,32
STORES ?= server,sqlite
bench-tracking: $(STAMP)
	$(PY) -m harness.perf.tracking_load --writers $(WRITERS) --stores $(STORES)
# a benchmark's demos as a LeRobotDataset v3.0 folder (docs/lerobot.md):
#   make lerobot-export BENCH=libero-quick out=exports/libero-quick [cameras=true] [images=png]
.PHONY: lerobot-export
lerobot-export: $(STAMP)
	$(PY) -m harness lerobot-export $(call quote,$(OVERRIDES))

# every real LIBERO task builds, starts from an init state and steps (slow: about 10 minutes for
# all 130); make libero-check LIBERO_SUITES="libero_object libero_goal"
libero-check: $(STAMP)
	$(PY) -m suites.libero.build_all $(LIBERO_SUITES)

# the suite without its slow checks (about 8 minutes on two cores), which test-slow runs
# (pytest -m slow: reruns, kills and resumes of whole runs, statistics over many scenes, every
# LIBERO task, lerobot-eval's oracle, the report page's videos played in headless Chromium, which
# its test installs with apt-get where it is missing; most of an hour on two cores); CI runs both
test: $(STAMP)
	$(PY) -m pytest -n 2 --dist loadfile -p no:warnings -m "not slow" tests

test-slow: $(STAMP)
	$(PY) -m pytest -n 2 --dist load -p no:warnings -m slow tests  # by test: 130 LIBERO tasks split

# style (ruff), then the one-way data flow: import-linter's contracts in pyproject.toml
lint: $(STAMP)
	$(PY) -m ruff check harness methods suites policies tests
	$(VENV)/bin/lint-imports --no-logo

ui: $(STAMP)
	$(VENV)/bin/mlflow ui --backend-store-uri sqlite:///$(CURDIR)/results/mlflow.db --host 127.0.0.1 --port 5000

# one tracking server for many processes or machines (SQLite under results/ is for one machine):
#   make mlflow-server [MLFLOW_HOST=0.0.0.0] [MLFLOW_PORT=5000] [MLFLOW_BACKEND=postgresql://...]
# then MLFLOW_TRACKING_URI=http://<host>:<port> for every bench; docs/scale-out.md
MLFLOW_HOST ?= 127.0.0.1
MLFLOW_PORT ?= 5000
MLFLOW_SERVER_DIR ?= $(CURDIR)/results/mlflow-server
MLFLOW_BACKEND ?= sqlite:///$(MLFLOW_SERVER_DIR)/mlflow.db
mlflow-server: $(STAMP)
	@mkdir -p $(MLFLOW_SERVER_DIR)
	@echo "MLflow server on http://$(MLFLOW_HOST):$(MLFLOW_PORT): runs in $(MLFLOW_BACKEND)," \
		"artifacts in $(MLFLOW_SERVER_DIR)/artifacts"
	$(VENV)/bin/mlflow server --backend-store-uri '$(MLFLOW_BACKEND)' \
		--artifacts-destination $(MLFLOW_SERVER_DIR)/artifacts --serve-artifacts \
		--host $(MLFLOW_HOST) --port $(MLFLOW_PORT)

clean-cache:
	rm -rf cache
