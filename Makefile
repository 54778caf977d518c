# beavr_sim: two commands for a fresh machine -- `make demo` and `make test`.
SHELL := /bin/bash
.DEFAULT_GOAL := help

VENV := .venv
PY := $(VENV)/bin/python
# The first Python 3.12 that actually runs: pyenv's install folders (a non-login shell may lack
# pyenv's shims, and a shim may point at another version), then python3.12 on PATH.
PYTHON312 ?= $(shell for c in $$(ls -1d $${PYENV_ROOT:-$$HOME/.pyenv}/versions/3.12*/bin/python3.12 2>/dev/null | sort -rV) $$(command -v python3.12 2>/dev/null) /usr/bin/python3.12 /usr/local/bin/python3.12; do \
	  if "$$c" -c 'import sys; assert sys.version_info[:2] == (3, 12)' >/dev/null 2>&1; then echo "$$c"; break; fi; done)
EXTRAS ?= viz,dev
STAMP := $(VENV)/.installed

.PHONY: help venv sysdeps demo test bench lint clean traces

help:
	@echo "make demo   - create .venv (Python 3.12), install, replay a bundled VR trace through teleop with the browser view"
	@echo "make test   - create .venv if needed, run the test suite"
	@echo "make bench  - run the simulation benchmark (JSON)"
	@echo "make lint   - ruff"

# LeRobot plugins (plugins/*: --env.type / --robot.type=beavr_sim, --teleop.type=beavr_quest);
# LeRobot imports each by its distribution name, so they are installed, not just on the path.
PLUGINS := $(wildcard plugins/lerobot_*_beavr_sim)

INSTALL_ARGS := -e ".[$(EXTRAS)]" $(addprefix -e ,$(PLUGINS))
# uv installs the same packages as pip (same resolution from PyPI) in a fraction of the time:
# parallel downloads and a cache (~/.cache/uv) it links from. It is fetched from PyPI into
# $(UV_DIR), beside the venv's packages (not among them); plain pip is the fallback whenever uv
# cannot be fetched or fails (USE_UV=0 forces it). Like pip, it compiles the bytecode at install
# (--compile-bytecode): where PYTHONDONTWRITEBYTECODE is set every process would otherwise
# recompile torch & co. on import. The same `pip freeze --all`, pip or uv.
UV_DIR := $(VENV)/.uv
UV := $(UV_DIR)/bin/uv
USE_UV ?= 1

$(STAMP): pyproject.toml $(addsuffix /pyproject.toml,$(PLUGINS))
	@if [ -z "$(PYTHON312)" ]; then echo "python3.12 not found: install Python 3.12 (e.g. pyenv install 3.12) or set PYTHON312=/path/to/python3.12" >&2; exit 1; fi
	@test -x $(PY) || $(PYTHON312) -m venv $(VENV)
	@if [ "$(USE_UV)" = 1 ] && { test -x $(UV) || $(PY) -m pip install --quiet --target $(UV_DIR) uv; } \
	  && $(UV) pip install --quiet --compile-bytecode --python $(PY) --upgrade-package pip pip $(INSTALL_ARGS); then \
	  echo "installed with uv"; \
	else \
	  [ "$(USE_UV)" != 1 ] || echo "uv unavailable or failed: installing with pip" >&2; \
	  $(PY) -m pip install --upgrade --quiet pip && $(PY) -m pip install --quiet $(INSTALL_ARGS); \
	fi
	@touch $(STAMP)

venv: $(STAMP) sysdeps

# Headless rendering needs Mesa's EGL and GL libraries. Installed here when missing and we are root;
# otherwise the exact packages are named.
sysdeps:
	@if ! /sbin/ldconfig -p 2>/dev/null | grep -q 'libEGL.so.1' || ! /sbin/ldconfig -p 2>/dev/null | grep -q 'libGL.so.1'; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing Mesa EGL/GL for headless rendering"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libegl1 libgl1 libgl1-mesa-dri libgles2 >/dev/null; \
	  else \
	    echo "Headless rendering needs: sudo apt-get install libegl1 libgl1 libgl1-mesa-dri libgles2" >&2; exit 1; \
	  fi; \
	fi
	@# The real-browser test of the view (tests/test_browser_view.py) drives Debian's chromium
	@# through playwright (never `playwright install`); without it that test skips.
	@if ! command -v chromium >/dev/null && ! command -v chromium-browser >/dev/null; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing chromium for the browser-view test"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; \
	  else \
	    echo "The browser-view test needs: sudo apt-get install chromium (it skips without)" >&2; \
	  fi; \
	fi
	@# The WebXR test (tests/test_webxr_browser.py) installs Meta's WebXR emulator (iwer) with npm
	@# into ~/.cache/beavr_sim/iwer; without npm that test skips.
	@if ! command -v npm >/dev/null; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing nodejs and npm for the WebXR test"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq nodejs npm >/dev/null; \
	  else \
	    echo "The WebXR test needs: sudo apt-get install nodejs npm (it skips without)" >&2; \
	  fi; \
	fi

# The main job on a bundled VR trace, in real time, with the browser view (Ctrl-C to stop).
DEMO_TASK ?= pour
demo: venv
	MUJOCO_GL=egl $(PY) -m beavr_sim.teleop --task $(DEMO_TASK) --source trace --headless --repeat 0

# The suite on TEST_WORKERS pytest-xdist processes, a test file to each (a file's module fixtures
# are built once, and test_readme_commands' commands, which use each other's output, stay in
# order). Most tests wait on real time (sessions at 30 Hz, processes starting), so one process
# leaves a 2-core machine two-thirds idle: 2 workers took it from 17.5 to 10 minutes.
# TEST_WORKERS=0 runs it in one process.
TEST_WORKERS ?= 2
test: venv
	MUJOCO_GL=egl $(PY) -m pytest -q --durations=25 -n $(TEST_WORKERS) --dist loadfile

bench: venv
	MUJOCO_GL=egl $(PY) -m beavr_sim.bench sim
	MUJOCO_GL=egl $(PY) -m beavr_sim.bench teleop
	MUJOCO_GL=egl $(PY) -m beavr_sim.bench retarget
	MUJOCO_GL=egl $(PY) -m beavr_sim.bench view
	MUJOCO_GL=egl $(PY) -m beavr_sim.bench hardware

# Regenerate the bundled VR traces (after changing the operator or the experts).
TRACE_TASKS ?= pickup_box pick_place stack_blocks flip_cube lantern tape pour
RX1_TRACE_TASKS ?= pick_place pickup_box stack_blocks pour
BIMANUAL_TRACE_TASKS ?= pick_place stack_blocks pour
traces: venv
	@for t in $(TRACE_TASKS); do MUJOCO_GL=egl $(PY) -m beavr_sim.traces synth --task $$t --seed 0 --tries 10 --out assets/traces/$$t.mcap || exit 1; done
	@mkdir -p assets/traces/rx1
	@for t in $(RX1_TRACE_TASKS); do MUJOCO_GL=egl $(PY) -m beavr_sim.traces synth --task $$t --embodiment rx1 --seed 0 --tries 10 --out assets/traces/rx1/$$t.mcap || exit 1; done
	@mkdir -p assets/traces/xarm7_leap_bimanual
	@for t in $(BIMANUAL_TRACE_TASKS); do MUJOCO_GL=egl $(PY) -m beavr_sim.traces synth --task $$t --embodiment xarm7_leap_bimanual --seed 0 --tries 10 --out assets/traces/xarm7_leap_bimanual/$$t.mcap || exit 1; done

lint: venv
	$(PY) -m ruff check beavr_sim tests plugins
	$(PY) -m ruff format --check beavr_sim tests plugins

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
