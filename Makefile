# swpc — make targets. `make test` and `make demo` work on a fresh machine.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# One BLAS thread in every process a target starts (swpc_hw/blas_threads.py: the swpc
# command, the demo and the benchmarks set it themselves; pytest gets it from here).
export OPENBLAS_NUM_THREADS := 1
export OMP_NUM_THREADS := 1
# Bytecode is written (into the git-ignored __pycache__ folders) even where the environment
# says PYTHONDONTWRITEBYTECODE (this development VM does, and so may CI's): without it every
# Python process compiles swpc from source again and pytest rewrites every test module's
# asserts again, 11 of the 20 s each of make test's processes took to collect the suite
# (2026-11-30; 8.7 s with the bytecode kept).
unexport PYTHONDONTWRITEBYTECODE

.PHONY: all install lock test lint typecheck bench demo demo-offline console clean typecheck-pythons test-browser console-screenshots ctrl-emu

all: test

$(BIN)/python:
	$(PY) -m venv $(VENV)

# The exact versions of requirements.lock (pyproject.toml has the lower bounds): first
# pyproject's requirements (extras service, test and mocap) under the lock, then swpc itself,
# editable, without them.  The second step is -qq: setuptools tells every editable install
# "Please be careful with folders in your working directory ..." as a warning, which was
# the first thing `make demo` printed on a fresh machine; an error still shows.
$(STAMP): pyproject.toml requirements.lock | $(BIN)/python
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -c 'import tomllib; p = tomllib.load(open("pyproject.toml", "rb"))["project"]; \
		x = p["optional-dependencies"]; print(*p["dependencies"], *x["service"], *x["test"], *x["mocap"], sep="\n")' \
		> $(VENV)/requirements.txt
	$(BIN)/python -m pip install -q -c requirements.lock -r $(VENV)/requirements.txt
	$(BIN)/python -m pip install -qq --no-deps -e .
	touch $(STAMP)

# requirements.lock from pyproject.toml: the newest versions within its bounds, for every
# Python swpc supports (uv's universal resolution).
lock: | $(BIN)/python
	$(BIN)/python -m pip install -q uv
	$(BIN)/uv pip compile pyproject.toml --extra service --extra test --extra mocap --universal --python-version 3.11 \
		--no-header -o requirements.lock.new
	{ sed -n '1,3p' requirements.lock; cat requirements.lock.new; } > requirements.lock
	rm requirements.lock.new

install: $(STAMP)

lint: $(STAMP)
	$(BIN)/ruff check swpc_hw firmware_protocol services simulators tests benchmarks
	$(BIN)/lint-imports --no-cache

typecheck: $(STAMP)
	$(BIN)/mypy

# mypy on the other supported Pythons, each in its own venv from the lock (.cache/venv-X.Y):
# the lock takes another numpy there, with other type stubs.  The suite itself runs on
# .venv's Python; docs/figures.md has make test on each.  A Python the machine does not
# have is skipped with a message (the project downloads no interpreter), unless
# SWPC_PYTHONS_REQUIRED is set.
PYTHONS ?= 3.12 3.13
typecheck-pythons:
	@set -e; for x in $(PYTHONS); do \
		py=$$(python$$x -c 'import sys; print(sys.executable)' 2>/dev/null \
			|| ls -d $${PYENV_ROOT:-$$HOME/.pyenv}/versions/$$x.*/bin/python$$x 2>/dev/null | tail -n 1); \
		if [ -z "$$py" ]; then \
			echo "typecheck-pythons: no Python $$x on PATH or under pyenv: skipped"; \
			[ -z "$(SWPC_PYTHONS_REQUIRED)" ] || exit 1; continue; fi; \
		v=.cache/venv-$$x; [ -x $$v/bin/python ] || $$py -m venv $$v; \
		$$v/bin/python -m pip install -q -c requirements.lock -e '.[service,test,mocap]'; \
		echo "mypy on $$($$v/bin/python -V)"; $$v/bin/mypy; \
	done

# One pytest worker per core and one more, a test module's tests on one worker (module
# fixtures).  About a seventh of the suite's test time waits on wall time (scans listening on
# the bus, zenoh links, processes starting up), which the extra worker fills; measured in
# docs/figures.md ("Time").  Only the plugins the suite uses: hypothesis's and
# schemathesis's pytest plugins cost every worker ~3 s of imports, and the suite uses both
# as libraries.
#
# mypy runs beside pytest, its output printed after pytest's: on a fresh clone its cache is
# cold (about 30 s of one core) and one core idles through it when it runs first, while
# pytest's workers leave a core idle as they start and as the last module ends (a warm
# cache, .mypy_cache/, takes under a second).  Either failing fails the target.
PYTEST := PYTEST_DISABLE_PLUGIN_AUTOLOAD=1 $(BIN)/python -m pytest -p xdist -p pytest_timeout
WORKERS ?= $(shell echo $$(( $$(nproc) + 1 )))
test: lint
	@mkdir -p .cache; $(BIN)/mypy > .cache/mypy.out 2>&1 & mypy=$$!; \
	echo "$(PYTEST) -q -p no:cacheprovider --ignore=tests/browser -n $(WORKERS) --dist loadfile"; \
	$(PYTEST) -q -p no:cacheprovider --ignore=tests/browser -n $(WORKERS) --dist loadfile; \
	tests=$$?; wait $$mypy; typed=$$?; echo "$(BIN)/mypy:"; cat .cache/mypy.out; \
	[ $$tests -eq 0 ] && [ $$typed -eq 0 ]

# The operator console in headless Chromium (Debian's chromium + chromium-driver; skipped
# with a message when absent, a failure under CI).  Screenshots: $(SWPC_SCREENSHOTS).
test-browser: $(STAMP)
	$(BIN)/python -m pytest -q -p no:cacheprovider -s tests/browser

# The same, writing its screenshots into docs/console (the ones the README shows).
console-screenshots: $(STAMP)
	SWPC_SCREENSHOTS=docs/console $(BIN)/python -m pytest -q -p no:cacheprovider -s tests/browser

bench: $(STAMP)
	$(BIN)/python -m benchmarks

demo: $(STAMP)
	$(BIN)/python -m services.demo

# The console on the simulated robot, kept up until Ctrl-C: prints where to click.
# PORT=N: on that port (default 8080 when free, else any free one).
console: $(STAMP)
	$(BIN)/python -m services.demo --console --out out/console $(if $(PORT),--port $(PORT))

demo-offline: $(STAMP)
	$(BIN)/python -m services.demo --offline

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache build *.egg-info

# The module controllers emulated in C on SocketCAN, as firmware (firmware_protocol/c/emulator/;
# the VM's deadman step runs it; tests/firmware/test_c_emulator.py checks it against Python's).
CC ?= cc
CTRL_EMU_SRC := firmware_protocol/c/swpc.c firmware_protocol/c/emulator/controller.c \
	firmware_protocol/c/emulator/main.c
build/swpc-ctrl-emu: $(CTRL_EMU_SRC) firmware_protocol/c/swpc.h firmware_protocol/c/emulator/controller.h
	mkdir -p build
	$(CC) -std=c99 -O2 -Wall -Wextra -Werror -I firmware_protocol/c $(CTRL_EMU_SRC) -o $@ -lm

ctrl-emu: build/swpc-ctrl-emu

# Real SocketCAN on a real kernel: boots a Debian kernel under QEMU (TCG) with virtme-ng and
# runs deploy/vm/in-vm.sh inside (set-up cached in .cache/vm/). See deploy/README.md.
.PHONY: test-vcan
test-vcan: $(STAMP)
	bash deploy/vm/run-in-vm.sh
