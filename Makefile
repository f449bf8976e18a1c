# The README's two commands: `make demo` and `make test`. Each creates .venv when it is missing and
# installs the pinned dependencies from requirements.txt; a second run installs nothing again.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.dyn_node-installed
# compiled again whenever a kernel source changes, so no node or test stops to compile
KERNELS := $(VENV)/.dyn_node-kernels
# the interface packages under interfaces/ (dyn_node_interfaces, ...), built into the venv
INTERFACES := $(VENV)/.dyn_node-interfaces
INTERFACE_FILES := $(shell find interfaces -type f -not -name '*~' 2>/dev/null)
INTERFACE_PKGS := $(patsubst %/package.xml,%,$(wildcard interfaces/*/package.xml))
PIP    := $(PY) -m pip --disable-pip-version-check -q
# Tests bring up their own ROS 2 processes; keep them on this machine and off other domains.
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
PYTEST_ARGS ?=

.PHONY: demo test bench soak lock clean

$(STAMP): requirements.txt setup.py package.xml
	@test -x $(PY) || { echo "creating $(VENV)"; $(PYTHON) -m venv $(VENV); }
	@echo "installing pinned dependencies into $(VENV) (first run only)"
	$(PIP) install -r requirements.txt
	$(PIP) install --no-deps --no-build-isolation -e .
	@# setup.cfg installs the commands in $(VENV)/lib/dyn_node (the ament layout `ros2 run` needs);
	@# linked into $(VENV)/bin too, so `source $(VENV)/bin/activate` puts them on PATH
	@for s in $(VENV)/lib/dyn_node/*; do ln -sf "../lib/dyn_node/$${s##*/}" "$(VENV)/bin/$${s##*/}"; done
	@touch $@

$(KERNELS): $(STAMP) $(wildcard dyn_node/core/compiled/*.py) dyn_node/retime/reach.py
	@echo "compiling the Numba kernels (after an install or a kernel change, ~40 s; cached in dyn_node/__pycache__)"
	$(PY) -c "import importlib, pkgutil, dyn_node.core.compiled as c; [importlib.import_module(m.name) for m in pkgutil.iter_modules(c.__path__, c.__name__ + '.')]"
	@# the retimer's compiled TOPP-RA passes (~10 s): else the first retime request pays them
	$(PY) -c "import dyn_node.retime.reach"
	@touch $@

# cmake + rosidl from the pinned wheels (needs cmake, g++ and the interpreter's headers); build.sh
# orders the packages by their dependencies and skips a control_msgs the venv has from elsewhere
$(INTERFACES): $(STAMP) $(INTERFACE_FILES)
	@echo "building the interface packages into $(VENV) (after a change under interfaces/, ~30 s each)"
	interfaces/build.sh --venv $(VENV) --build-dir build/interfaces $(INTERFACE_PKGS)
	@touch $@

demo: $(KERNELS) $(INTERFACES)
	$(PY) -m dyn_node.ros.demo

test: $(KERNELS) $(INTERFACES)
	$(PY) -m pytest $(PYTEST_ARGS)

bench: $(KERNELS) $(INTERFACES)
	@# bytecode as a pip-installed package has it (pip compiles it at install): a shell with
	@# PYTHONDONTWRITEBYTECODE set would otherwise compile every module at each command's start
	$(PY) -m compileall -q dyn_node benchmarks
	$(PY) -m benchmarks.run $(BENCH_ARGS)

# Not in CI: the demo stack at 1 kHz with recording and splitting for SOAK_MINUTES (default 30).
soak: $(KERNELS)
	$(PY) -m benchmarks.soak $(SOAK_ARGS)

lock: $(STAMP)
	@echo "review, then paste below the closure marker in requirements.txt:"
	@$(PY) -c "import importlib.metadata as m; print('\n'.join(sorted(f\"{d.metadata['Name']}=={d.version}\" for d in m.distributions() if (d.read_text('INSTALLER') or '').strip() == 'pip' and d.metadata['Name'] != 'dyn_node')))" 

clean:
	rm -rf $(VENV) build *.egg-info
