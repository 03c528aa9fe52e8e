# Two entry points for a new user: `make run` (the paper's reference stack) and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: run test lint bench docs clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
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
# so that its shared, expensive fixtures (10-repeat ensembles) are computed once.
test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/pytest -q -n auto --dist loadfile

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_packing.py
	$(BIN)/python benchmarks/bench_geometry.py
	$(BIN)/python benchmarks/bench_meshing.py

# The reference tables in docs/ that the code generates (a test checks they are current).
docs: $(STAMP)
	$(BIN)/python -m pipeline.reference

clean:
	rm -rf $(VENV) runs
