# Two entry points for a new user: `make run` (the paper's reference stack) and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
IMAGE  := $(VENV)/.image-installed

DOLFINX       := .venv-dolfinx
DOLFINX_STAMP := $(DOLFINX)/.installed
DOLFINX_REQS  := tests/clients/dolfinx-requirements.txt

.PHONY: run solve test image dolfinx dolfinx-if-python lint bench docs clean

# The pipeline and its dependencies into .venv: wheels only, nothing compiled, no root.
# setuptools announces every editable install that maps packages (ours: the root folders
# as chipstack.*) with an "Editable installation" notice about folders named like the
# package in the working directory; here that folder is the package itself, so the
# notice is filtered by its message (nothing else is).
$(STAMP): pyproject.toml
	@echo "make: installing chipstack and its dependencies into $(VENV) (pip, about a minute)"
	@$(PYTHON) -m venv $(VENV)
	@$(BIN)/pip install --quiet --upgrade pip
	@PYTHONWARNINGS="ignore:Editable installation" $(BIN)/pip install --quiet -e '.[test]'
	@touch $(STAMP)

# The image mesh kind (mesh.kind = "image") only: pygalmesh, compiled against CGAL and
# Eigen (5 to 9 minutes, peak 4.4 GB). Their Debian packages are installed with apt-get
# (as root, or with sudo) when missing; this says so before it does.
image: $(IMAGE)
$(IMAGE): $(STAMP)
	@if ! dpkg -s libcgal-dev libeigen3-dev >/dev/null 2>&1; then \
		if ! command -v apt-get >/dev/null; then \
			echo "make image: install the CGAL and Eigen headers (Debian: libcgal-dev libeigen3-dev), then run make image again"; \
			exit 2; \
		fi; \
		SUDO=; [ "$$(id -u)" -eq 0 ] || SUDO=sudo; \
		echo "make image: running '$${SUDO:+sudo }apt-get install libcgal-dev libeigen3-dev' (CGAL and Eigen headers for pygalmesh)"; \
		$$SUDO apt-get update -qq && \
		$$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
			libcgal-dev libeigen3-dev >/dev/null || exit 2; \
	fi
	@echo "make image: compiling pygalmesh against CGAL (5 to 9 minutes, peak 4.4 GB)"
	@PYTHONWARNINGS="ignore:Editable installation" $(BIN)/pip install --quiet -e '.[image]'
	@touch $(IMAGE)

# The first Python >= 3.12 here (the PyPI DOLFINx wheel has none for 3.11): python3.12,
# python3.13, python3.14 and python3 on the PATH, then pyenv's versions, oldest first.
# Each is asked, since pyenv's shims are on the PATH for every version but run only the
# selected ones; prints the interpreter's own path, or fails.
FIND_PYTHON312 = (for p in python3.12 python3.13 python3.14 python3 \
	$$(ls -d "$${PYENV_ROOT:-$$HOME/.pyenv}"/versions/3.*/bin/python3 2>/dev/null | sort -V); do \
		"$$p" -c 'import sys; sys.version_info >= (3, 12) and print(sys.executable)' \
			2>/dev/null | grep . && exit 0; \
	done; exit 1)

# DOLFINx in its own virtual environment (the tests' DOLFINx client, tests/parts.py): the
# PyPI wheel dolfinx-solver-real (PETSc, MPI and HDF5 inside) and gmsh, on the first
# Python >= 3.12 (FIND_PYTHON312); 20 to 40 s with a warm pip cache, 450 MB.
dolfinx: $(DOLFINX_STAMP)
$(DOLFINX_STAMP): $(DOLFINX_REQS)
	@py=$$( $(FIND_PYTHON312) ) || { \
		echo "make dolfinx: no Python >= 3.12 found (python3.12, python3.13, python3.14, python3, pyenv's versions); the DOLFINx wheel needs one"; \
		exit 2; }; \
	echo "make dolfinx: building $(DOLFINX) from $$py ($$("$$py" -V)): pip install dolfinx-solver-real, gmsh (20 to 40 s with a warm pip cache, 450 MB)"; \
	rm -rf $(DOLFINX) && "$$py" -m venv $(DOLFINX) && \
	$(DOLFINX)/bin/pip install --quiet -r $(DOLFINX_REQS) && \
	$(DOLFINX)/bin/python -c 'import dolfinx_solver, dolfinx, gmsh' && touch $@

# `make test` builds the DOLFINx environment when this machine has a Python for it;
# without one the DOLFINx tests skip, saying why (tests/parts.py).
dolfinx-if-python:
	@if $(FIND_PYTHON312) >/dev/null; then \
		$(MAKE) --no-print-directory --silent $(DOLFINX_STAMP); \
	else \
		echo "make test: no Python >= 3.12 found for DOLFINx (make dolfinx); its tests skip"; \
	fi

# The paper scenario through every stage: deposition, descriptors, voxel mesh. Run again,
# the stage cache reuses what is unchanged (a killed run resumes where it stopped).
run: $(STAMP)
	@$(BIN)/pipeline run --to mesh --out runs/paper-squares --seed 0

# A cropped volume of the same stack pressed between platens in CalculiX (ccx on the PATH;
# Debian: apt-get install calculix-ccx).
solve: $(STAMP)
	@if ! command -v ccx >/dev/null; then \
		echo "make solve: CalculiX (ccx) is not on the PATH (Debian: apt-get install calculix-ccx)"; \
		exit 2; \
	fi
	@$(BIN)/pipeline run paper-volume --to solve --out runs/paper-volume --seed 0

# Lint, format check and every test, the image route's included (so `make test` builds
# pygalmesh: `make image`). Tests run on every core (-n auto); a module's tests stay on
# one worker (--dist loadfile) so that its shared, expensive fixtures (10-repeat
# ensembles) are computed once; the longest modules go first (tests/conftest.py); the
# 30 slowest tests are listed at the end (issue 73: the record of where the time goes).
test: $(STAMP) $(IMAGE) dolfinx-if-python
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/pytest -q -n auto --dist loadfile --no-loadscope-reorder --durations=30

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_packing.py
	$(BIN)/python benchmarks/bench_geometry.py
	$(BIN)/python benchmarks/bench_meshing.py

# What the code generates in docs/: the reference tables, docs/measured.md from the
# figures recorded under benchmarks/results/, docs/cli.md from the command line's parser,
# the counts of tests from pytest's collection (tests/collected.py; a test checks each is
# current), and the README's picture of the reference stack and its mesh
# (docs/stack-and-mesh.png, from runs/paper-squares: run as `make run` runs it if missing,
# else reused).
docs: $(STAMP)
	$(BIN)/python -m chipstack.pipeline.reference
	$(BIN)/python -m chipstack.pipeline.measured
	$(BIN)/python -m chipstack.pipeline.cli_docs
	$(BIN)/python tests/collected.py
	$(BIN)/python -m chipstack.pipeline.picture

clean:
	rm -rf $(VENV) $(DOLFINX) runs
