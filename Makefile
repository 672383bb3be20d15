# The README's two commands are `make demo` and `make test`; both install first (idempotent).
PYTHON ?= python3
PIP = $(PYTHON) -m pip

.PHONY: install demo test test-cuda-emulated cmake-build bench docs

install:
	$(PIP) install -q "torch==2.13.0" setuptools wheel ninja pybind11 numpy
	$(PIP) install -q --no-build-isolation -e ".[test,peers,onnx]"
	# Recent setuptools turn `pip install -e` into an isolated PEP 660 build that cannot see torch,
	# so the extension is compiled in place explicitly (ninja; incremental on later runs).
	$(PYTHON) setup.py -q build_ext --inplace

demo: install
	modi demo --out demo_out

test: install
	$(PYTHON) -m pytest -q -p no:cacheprovider tests

# The CUDA kernels on the CPU emulator, and again under AddressSanitizer (part of `make test` too).
test-cuda-emulated: install
	$(PYTHON) -m pytest -q -p no:cacheprovider -m cuda_emulated tests

cmake-build:
	cmake -S . -B build/cmake -DCMAKE_PREFIX_PATH="$$($(PYTHON) -c 'import torch; print(torch.utils.cmake_prefix_path)')"
	cmake --build build/cmake -j 2

bench: install
	$(PYTHON) benchmarks/compare.py --json benchmarks/results/cpu.json

# The docs (mkdocs.yml, docs/) into build/docs-site/, strictly: a warning (a broken link or anchor) fails the build.
# Needs only the docs tools (mkdocstrings reads the sources, so neither torch nor modi need be installed);
# the pins are setup.py's `docs` extra.
DOCS_REQUIRES = "mkdocs==1.6.1" "mkdocstrings==1.0.8" "mkdocstrings-python==2.0.11"

docs:
	$(PIP) install -q $(DOCS_REQUIRES)
	$(PYTHON) -m mkdocs build --strict
