# Two entry points for a new user: `make run` (the paper's reference stack) and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: run test lint bench docs clean

# The image mesh kind needs CGAL and Eigen headers to build pygalmesh: installed from
# Debian's packages when they are missing and apt-get is there (as root, or with sudo).
$(STAMP): pyproject.toml
	@if ! dpkg -s libcgal-dev libeigen3-dev >/dev/null 2>&1 && command -v apt-get >/dev/null; then \
		SUDO=; [ "$$(id -u)" -eq 0 ] || SUDO=sudo; \
		echo "make: installing libcgal-dev and libeigen3-dev for the image mesh kind"; \
		$$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq --no-install-recommends libcgal-dev libeigen3-dev; \
	fi
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	@$(BIN)/pip install --quiet -e '.[image]' || \
		echo "make: pygalmesh (CGAL) did not build; every mesh kind but 'image' works (it needs libcgal-dev and libeigen3-dev)"
	touch $(STAMP)

# The paper scenario through every stage: deposition, descriptors, voxel mesh; then a
# cropped volume of the same stack pressed in CalculiX (when ccx is on the PATH). Run
# again, the stage cache reuses what is unchanged (a killed run resumes where it stopped).
run: $(STAMP)
	$(BIN)/pipeline run --to mesh --out runs/paper-squares --seed 0
	@if command -v ccx >/dev/null; then \
		$(BIN)/pipeline run paper-volume --to solve --out runs/paper-volume --seed 0; \
	else \
		echo "make run: CalculiX (ccx) is not on the PATH, so the solve stage is skipped (Debian: apt-get install calculix-ccx)"; \
	fi

# Tests run on every core (-n auto); a module's tests stay on one worker (--dist loadfile)
# so that its shared, expensive fixtures (10-repeat ensembles) are computed once; the
# longest modules go first (tests/conftest.py), not the ones with the most tests.
test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/pytest -q -n auto --dist loadfile --no-loadscope-reorder

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_packing.py
	$(BIN)/python benchmarks/bench_geometry.py
	$(BIN)/python benchmarks/bench_meshing.py

# The reference tables in docs/ that the code generates (a test checks they are current).
docs: $(STAMP)
	$(BIN)/python -m pipeline.reference

clean:
	rm -rf $(VENV) runs
