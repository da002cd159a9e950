# torchskin: `make demo` runs the main job, `make test` runs lint and the test suite.
# Both create .venv first. TORCH selects the torch build: the default is a CPU build of torch 2.13.0; for a
# CUDA build use e.g. `make setup TORCH=torch`. `make docs` builds the documentation into docs/_build/html.
PYTHON ?= python3
TORCH ?= torch==2.13.0
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
OUT ?= out

.PHONY: setup demo test lint docs bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml Makefile
	@for need in "libusb-1.0:libusb-1.0-0:open3d" "libgomp.so.1:libgomp1:lightgbm (the lut detector's learner)"; do \
		lib=$${need%%:*}; rest=$${need#*:}; pkg=$${rest%%:*}; who=$${rest#*:}; \
		if ! ldconfig -p 2>/dev/null | grep -q "$$lib"; then \
			SUDO=""; if [ "$$(id -u)" != 0 ]; then if command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then SUDO=sudo; else SUDO=none; fi; fi; \
			if [ "$$SUDO" = none ]; then \
				echo "warning: $$who needs the system library $$pkg; install it with: sudo apt-get install -y $$pkg"; \
			else \
				echo "installing $$pkg (needed by $$who)"; \
				($$SUDO apt-get install -y $$pkg >/dev/null 2>&1 || ($$SUDO apt-get update >/dev/null && $$SUDO apt-get install -y $$pkg >/dev/null)) \
				|| echo "warning: could not install $$pkg; $$who will not import (sudo apt-get install -y $$pkg)"; \
			fi; \
		fi; \
	done
	@if ! command -v g++ >/dev/null 2>&1 && ! command -v c++ >/dev/null 2>&1 && ! command -v clang++ >/dev/null 2>&1; then \
		SUDO=""; if [ "$$(id -u)" != 0 ]; then if command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then SUDO=sudo; else SUDO=none; fi; fi; \
		if [ "$$SUDO" = none ]; then \
			echo "warning: no C++ compiler: compiled kernels (--compile) will run eagerly; install one with: sudo apt-get install -y g++"; \
		else \
			echo "installing g++ (torch.compile's C++ backend for the compiled kernels)"; \
			($$SUDO apt-get install -y g++ >/dev/null 2>&1 || ($$SUDO apt-get update >/dev/null && $$SUDO apt-get install -y g++ >/dev/null)) \
			|| echo "warning: could not install g++; compiled kernels will run eagerly (sudo apt-get install -y g++)"; \
		fi; \
	fi
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q "$(TORCH)"
	$(PY) -m pip install -q -e ".[dev]"
	touch $(STAMP)

EXPORTS ?= exports

# the thesis experiment, then the detector pipeline: generate -> train -> evaluate -> export -> verify; verify
# ends by comparing the fresh-test figures with the committed ones (git HEAD's, else the exports found at the
# start) within the reproducibility tolerances, and fails loudly when they differ. Training runs torch's AVX2
# kernels on every x86-64 CPU (ATEN_CPU_CAPABILITY=avx2): the datasets are the same bytes under any kernels, but
# the box MLP's 1000 steps on 1.2 M pixels drift apart under AVX-512's (held-out shadow Pd 0.871 against 0.859),
# so a machine with AVX-512 would not reproduce the committed exports
REFERENCE := $(OUT)/reference_evaluation_test.json
demo: setup
	mkdir -p $(OUT)
	@git show HEAD:$(EXPORTS)/evaluation_test.json > $(REFERENCE) 2>/dev/null \
		|| cp $(EXPORTS)/evaluation_test.json $(REFERENCE) 2>/dev/null || rm -f $(REFERENCE)
	$(VENV)/bin/torchskin spectra --all-presets --plot $(OUT)/presets.png
	$(VENV)/bin/torchskin experiment --out $(OUT)/experiment
	$(PY) scripts/pipeline_generate.py --work $(OUT)/pipeline
	ATEN_CPU_CAPABILITY=avx2 $(PY) scripts/pipeline_train.py --work $(OUT)/pipeline
	$(PY) scripts/pipeline_evaluate.py --work $(OUT)/pipeline
	$(PY) scripts/pipeline_export.py --work $(OUT)/pipeline --exports $(EXPORTS)
	$(PY) scripts/pipeline_verify.py --exports $(EXPORTS) --reference $(REFERENCE)

# ruff, then mypy (its settings: [tool.mypy] in pyproject.toml; cache in .mypy_cache)
lint: setup
	$(VENV)/bin/ruff check torchskin tests scripts examples
	$(VENV)/bin/mypy

# the suite in two pytest-xdist workers of one torch thread each (TEST_WORKERS; whole files per worker: a module's
# fixtures are built once), then the reproducibility tests again with torch's AVX2 kernels (ATEN_CPU_CAPABILITY=avx2: on a CPU
# with AVX-512 the first run used those; each run ends with a line naming the capability it used; on a CPU whose
# best is AVX2 the first run used those, and the second is skipped: it would run the same kernels)
TEST_WORKERS ?= 2
test: lint
	@$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: failing" >&2; exit 1; fi; \
	if [ $$rc -ne 0 ]; then exit $$rc; fi
	@if [ "$$($(PY) -c 'import torch; print(torch.backends.cpu.get_cpu_capability())')" = AVX2 ]; then \
		echo "the suite ran torch's AVX2 kernels already (this CPU's best): the AVX2 reproducibility pass would repeat it, skipped"; \
	else ATEN_CPU_CAPABILITY=avx2 $(PY) -m pytest -q -p no:cacheprovider -m reproducibility -k "not ray_backend" tests/test_reproducibility.py; fi

# the documentation site (Sphinx + furo + MyST, pinned in the docs extra); a warning fails the build, as in
# tests/test_docs.py, which make test runs
docs: setup
	$(VENV)/bin/sphinx-build -W --keep-going -b html docs docs/_build/html

bench: setup
	$(VENV)/bin/torchskin bench

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache .ruff_cache .mypy_cache docs/_build docs/api
