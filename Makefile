# so101-sim: `make demo` runs the main job, `make test` runs the tests.
# Both create or refresh .venv (Python 3.12, which lerobot 0.6.x needs) on their own.

SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# lerobot imports installed distributions named lerobot_env_*: this one makes `lerobot-eval
# --env.type=so101_pick_place` work without --env.discover_packages_path
PLUGIN := plugins/lerobot_env_so101_sim
SHIPPED := policy/pick_place_diffusion

# The first Python 3.12 found: on PATH, under pyenv, or in the usual system places.
PYTHON312 ?= $(shell for c in python3.12 $$(pyenv root 2>/dev/null)/versions/3.12*/bin/python3.12 \
	$$HOME/.pyenv/versions/3.12*/bin/python3.12 /usr/local/bin/python3.12 /usr/bin/python3.12; do \
	if "$$c" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 12))' >/dev/null 2>&1; then \
	echo "$$c"; break; fi; done)

export HF_HUB_OFFLINE := 1

.PHONY: venv demo test bench lint clean

venv: $(STAMP)

$(STAMP): pyproject.toml $(PLUGIN)/pyproject.toml plugins/lerobot_robot_so101_sim/pyproject.toml
	@if [ -z "$(PYTHON312)" ]; then \
		echo "error: Python 3.12 not found (lerobot 0.6.x needs 3.12)."; \
		echo "  install it, e.g.: pyenv install 3.12 | apt-get install python3.12 python3.12-venv"; \
		echo "  or point at one: make PYTHON312=/path/to/python3.12 ..."; \
		exit 1; fi
	@echo "using $(PYTHON312)"
	@[ -x $(PY) ] && $(PY) -c 'import sys; sys.exit(sys.version_info[:2] != (3, 12))' \
		|| { rm -rf $(VENV); $(PYTHON312) -m venv $(VENV); }
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev]" -e ./$(PLUGIN) -e ./plugins/lerobot_robot_so101_sim
	@touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/so101-sim demo --out outputs/demo
	@# The main job: the shipped diffusion checkpoint closed-loop (the expert until one ships).
	rm -rf outputs/eval/demo
	@if [ -f $(SHIPPED)/model.safetensors ]; then \
		$(VENV)/bin/so101-sim eval --policy $(SHIPPED) --episodes 20 --n-envs 16 --videos 2 \
			--out outputs/eval/demo; \
	else \
		echo "no shipped checkpoint in $(SHIPPED): evaluating the scripted expert"; \
		$(VENV)/bin/so101-sim eval --policy expert --episodes 20 --n-envs 2 --videos 2 \
			--out outputs/eval/demo; fi

# Two pytest workers: most tests wait on one single-threaded start-up (imports, spawning env
# workers), so one worker leaves a core idle about half the time. Each worker takes whole test
# modules, the longest first (tests/conftest.py), so module fixtures are built once; the Ray
# modules go to one worker together: a second local cluster would join the first.
TEST_WORKERS ?= 2

test: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadscope

bench: $(STAMP)
	$(PY) benchmarks/bench_env.py

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) outputs .pytest_cache .ruff_cache
