# The two commands a newcomer needs: `make sim` and `make test`.
# Each sets up .venv on first use; later runs reuse it until pyproject.toml changes.

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: setup sim test lint soak faults draws bench bench-instructions install clean

setup: $(STAMP)

# A venv copied from another place (a checkout copied to /opt/mavvo with its .venv) keeps the old
# paths in its scripts and fails later with "required file not found": it is made anew here.
HASH := \#
ifneq ($(wildcard $(BIN)/pip),)
ifneq ($(shell head -1 $(BIN)/pip),$(HASH)!$(abspath $(BIN))/python)
$(STAMP): moved-venv
endif
endif

.PHONY: moved-venv
moved-venv:
	@echo "$(VENV) was made in another place ($$(head -1 $(BIN)/pip | cut -c3-)): making it anew here"
	rm -rf $(VENV)

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,fleet]'
	@# The distribution's PyGObject, for the gst: camera (says what to install where it is missing).
	$(BIN)/python tools/link_system_gi.py
	$(BIN)/python -m mavvo.estimation.warmup
	@touch $(STAMP)

# The service against the simulated flight controller and camera (lockstep, default scenario); prints
# the trajectory error and where the plot is.
sim: $(STAMP)
	$(BIN)/python -m mavvo.estimation.warmup
	$(BIN)/mavvo sim

# Each run first compiles the kernels the sources changed since the last (a second when none did), so
# that no test's service spends its start-up compiling. The suite runs in TEST_JOBS worker processes
# (pytest-xdist; 0: in this one): most of its time is flights waiting on real sockets and clocks, so two
# shorten it even on two loaded cores (docs/developers.md has the figures).
TEST_JOBS ?= 2
test: lint
	$(BIN)/python -m mavvo.estimation.warmup
	$(BIN)/python -m pytest -q -m "not slow" -n $(TEST_JOBS) --durations=15

# ruff (pyproject.toml): the usual bug finders, sorted imports, and the format, checked, not rewritten
# (`.venv/bin/ruff format . && .venv/bin/ruff check --fix .` rewrites).
lint: $(STAMP)
	$(BIN)/ruff check mavvo tools tests benchmarks
	$(BIN)/ruff format --check mavvo tools tests benchmarks

# The long runs make test skips (about 15 minutes): the solver soak, the survey and faults flights,
# the fault suite's real-time cases, 1200 fuzzed settings files, make install into a staging folder.
soak: $(STAMP)
	$(BIN)/python -m pytest -q -m slow -rP

# Every shipped scenario over five draws of its noise (about 50 minutes on 2 cores, the small-quad scenarios the longest): what the vehicle
# would feel, median and range; writes the tables into docs/service.md.
draws: $(STAMP)
	$(BIN)/python -m mavvo.sim.scenarios.draws --markdown docs/service.md

# Hostile and broken input against the real service on 127.0.0.1 (about 5 minutes): prints the table
# and writes it into docs/reliability.md. The quick cases also run in `make test`.
faults: $(STAMP)
	$(BIN)/python -m tools.faults.suite --markdown docs/reliability.md

# Benchmarks run single-threaded (the last line adds OpenCV on all cores); PoseLib is installed for the
# comparison when the platform has it.
# The small-quad benchmark flies fifteen draws of each scenario's noise, two at a time (about 110 minutes
# on 2 cores): five leave centimetre gaps between mavvo and a script inside the draws' spread.
SMALL_QUAD_SEEDS ?= own,101,102,103,104,105,106,107,108,109,110,111,112,113,114
bench: $(STAMP)
	-@$(BIN)/python -m pip install --quiet -e '.[compare]' || echo "poselib not available: comparing with OpenCV only"
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 $(BIN)/python benchmarks/solvers.py --markdown docs/benchmarks.md
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 $(BIN)/python benchmarks/relpose.py --markdown docs/benchmarks.md --plots docs/img
	$(BIN)/python benchmarks/relpose.py --threads --markdown docs/benchmarks.md
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 $(BIN)/python benchmarks/relpose_flight.py --markdown docs/benchmarks.md --plots docs/img
	OMP_NUM_THREADS=1 $(BIN)/python benchmarks/render.py --markdown docs/benchmarks.md
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 $(BIN)/python benchmarks/pipeline.py --threads --markdown docs/benchmarks.md
	$(BIN)/python benchmarks/batch_scaling.py --markdown docs/benchmarks.md
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 $(BIN)/python benchmarks/small_quad.py --seeds $(SMALL_QUAD_SEEDS) --jobs 2 --markdown docs/benchmarks.md

# The odometry's instructions per frame (valgrind), this tree beside AGAINST (default: the last commit):
# whether a change made the work larger, whatever the machine's load. Needs Debian's valgrind.
AGAINST ?= HEAD
bench-instructions: $(STAMP)
	$(BIN)/python benchmarks/instructions.py $(foreach r,$(AGAINST),--against $(r))

# Install on the companion computer (sudo make install): the package into a venv made in PREFIX (never
# a copied one), the settings under ETCDIR (kept if present), the unit, the mavvo user; then check-config
# and preflight. SYSTEM=0 installs the files only (no user, no systemctl): for a staging directory.
# CAMERA=picamera2 (Raspberry Pi CSI cameras) or CAMERA=gst (Jetson, GStreamer pipelines) makes the venv
# with --system-site-packages from the distribution's python3, which sees its libcamera / PyGObject;
# install those first (docs/camera.md). CAMERA=v4l2 (default) needs nothing from the system.
PREFIX  ?= /opt/mavvo
ETCDIR  ?= /etc/mavvo
UNITDIR ?= /etc/systemd/system
CACHEDIR ?= /var/cache/mavvo
SYSTEM  ?= 1
CAMERA  ?= v4l2
ifneq ($(filter $(CAMERA),picamera2 gst),)
VENV_FLAGS := --system-site-packages
INSTALL_PYTHON ?= /usr/bin/python3
else
VENV_FLAGS :=
INSTALL_PYTHON ?= $(PYTHON)
endif

install:
	@test "$(SYSTEM)" = 0 || test "$$(id -u)" = 0 || { echo "make install: needs root: sudo make install"; exit 1; }
	mkdir -p $(PREFIX) $(ETCDIR) $(UNITDIR)
	@if [ "$(abspath $(PREFIX))" != "$(CURDIR)" ]; then \
		tar --exclude=.venv --exclude=.git --exclude='*.egg-info' --exclude=__pycache__ --exclude=mavvo-sim-out \
			-cf - mavvo config systemd pyproject.toml README.md Makefile | tar -xf - -C $(PREFIX); fi
	@case "$(CAMERA)" in v4l2|gst|picamera2) ;; *) echo "make install: CAMERA=$(CAMERA): expected v4l2, gst or picamera2"; exit 2;; esac
	$(INSTALL_PYTHON) -m venv --clear $(VENV_FLAGS) $(PREFIX)/.venv
	$(PREFIX)/.venv/bin/python -m pip install --quiet --upgrade pip
	$(PREFIX)/.venv/bin/python -m pip install --quiet $(PREFIX)
	@# setuptools builds in the source tree: what it leaves there is no part of the installed copy.
	rm -rf $(PREFIX)/build $(PREFIX)/*.egg-info
	@test -e $(ETCDIR)/mavvo.yaml || install -m 0640 config/default.yaml $(ETCDIR)/mavvo.yaml
	sed -e 's|/opt/mavvo|$(abspath $(PREFIX))|g' -e 's|/etc/mavvo|$(abspath $(ETCDIR))|g' -e 's|/var/cache/mavvo|$(abspath $(CACHEDIR))|g' \
		systemd/mavvo.service > $(UNITDIR)/mavvo.service
	@# The compiled kernels into the unit's NUMBA_CACHE_DIR: the service's first start loads them instead of compiling for a minute.
	mkdir -p $(CACHEDIR)/numba
	NUMBA_CACHE_DIR=$(abspath $(CACHEDIR))/numba $(PREFIX)/.venv/bin/python -m mavvo.estimation.warmup
	@if [ "$(SYSTEM)" != 0 ]; then \
		id mavvo >/dev/null 2>&1 || useradd --system --no-create-home --shell /usr/sbin/nologin --groups dialout,video mavvo; \
		chgrp mavvo $(ETCDIR)/mavvo.yaml; chown -R mavvo:mavvo $(CACHEDIR); chmod 0700 $(CACHEDIR); systemctl daemon-reload; fi
	$(PREFIX)/.venv/bin/mavvo check-config $(ETCDIR)/mavvo.yaml
	@if [ "$(SYSTEM)" != 0 ]; then $(PREFIX)/.venv/bin/mavvo preflight --config $(ETCDIR)/mavvo.yaml --timeout 5 || \
		echo "preflight: run it again once the flight controller is connected: $(PREFIX)/.venv/bin/mavvo preflight --config $(ETCDIR)/mavvo.yaml"; fi
	@echo "installed: edit $(ETCDIR)/mavvo.yaml (camera, mounting, link.url; docs/camera.md), then: sudo systemctl enable --now mavvo"

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info mavvo-sim-out mavvo-replay-out
