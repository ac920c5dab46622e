# The README's commands. Everything is built from nothing but Python 3.11 and this repository.
PYTHON ?= python3
VENV ?= .venv
# The CPU build available locally; override e.g. `make setup TORCH_SPEC="torch==2.5.1"` (a plain `torch` pulls CUDA).
TORCH_SPEC ?= torch==2.13.0
# The tests cover the rl-zoo3 launcher, so its extra is installed too.
EXTRAS ?= tests,zoo
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-$(EXTRAS)
# Test processes (pytest-xdist): `auto` is one per CPU core (2 on CI); TEST_WORKERS=0 runs the suite in one process.
TEST_WORKERS ?= auto
export OMP_NUM_THREADS ?= 1
export MKL_NUM_THREADS ?= 1

.PHONY: setup demo test test-slow lint type bench clean

$(PY):
	$(PYTHON) -m venv $(VENV)

# Torch first, by pip (the local CPU build), then the rest by uv (parallel downloads; pip where uv cannot be
# installed), neither compiling bytecode: compiling every installed module took 37 of the install's 51 s on two cores.
# Two imports side by side of everything the package, its CLIs and its tests use then write the bytecode of only what
# runs (about 3,800 modules, 17 s); without them every process would compile its imports again where
# PYTHONDONTWRITEBYTECODE is set. A tool that is not installed (EXTRAS without tests or zoo) is left out.
WARM_PACKAGE := import importlib, importlib.util, pkgutil, sb3_taskalloc, envs, tuning; \
	[importlib.import_module(m.name) for p in (sb3_taskalloc, envs, tuning) \
	 for m in pkgutil.walk_packages(p.__path__, p.__name__ + '.') if not m.name.endswith('__main__')]; \
	import torch._dynamo
WARM_TOOLS := import importlib, importlib.util; \
	[importlib.import_module(n) for n in 'pytest xdist rl_zoo3.train sqlalchemy pandas psycopg tensorboard'.split() \
	 if importlib.util.find_spec(n.split('.')[0])]
$(STAMP): pyproject.toml | $(PY)
	$(PY) -m pip install -q --no-compile "$(TORCH_SPEC)"
	($(PY) -m pip install -q uv && $(PY) -m uv pip install -q --python $(PY) -e ".[$(EXTRAS)]") \
		|| $(PY) -m pip install -q --no-compile -e ".[$(EXTRAS)]"
	export PYTHONDONTWRITEBYTECODE=; $(PY) -c "$(WARM_PACKAGE)" & $(PY) -c "$(WARM_TOOLS)" && wait $$!
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(PY) -m sb3_taskalloc.demo --out demo_out

# pytest exit code 5 means "no test collected": that is a failure here, never a silent pass.
PYTEST = @$(PY) -m pytest -q -ra --durations=15 -n $(TEST_WORKERS) -m $(1) $(PYTEST_ARGS); rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "ERROR: pytest collected no tests (exit 5)"; exit 1; fi; exit $$rc

# The suite but the minutes-long learning checks (marker `slow`), which `make test-slow` runs: CI runs `make test`,
# which has 8 minutes on 2 cores, the install included, and keeps one seed of the Almighty learning check.
test: $(STAMP)
	$(call PYTEST,"not slow")

test-slow: $(STAMP)
	$(call PYTEST,slow)

lint: $(STAMP)
	$(PY) -m ruff check sb3_taskalloc envs tuning tests
	$(PY) -m ruff format --check sb3_taskalloc envs tuning tests

type: $(STAMP)
	$(PY) -m mypy sb3_taskalloc envs tuning

bench: $(STAMP)
	$(PY) -m sb3_taskalloc.bench all --out bench_out

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache
