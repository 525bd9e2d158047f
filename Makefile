# Two commands on a fresh machine with Python 3.11: `make demo` and `make test`.
PYTHON ?= python3.11
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
# The Blender add-on tests (tests/addon) and `make extension` need the bpy wheel (Python 3.11
# only, ~374 MB download; it pins numpy<2, which core supports).
BPY_VERSION ?= 5.0.1
BPY_STAMP   := $(VENV)/.bpy-$(BPY_VERSION)

.PHONY: demo test venv venv-bpy extension clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet -e '.[test,cluster]'
	touch $(STAMP)

venv: $(STAMP)

$(BPY_STAMP): $(STAMP)
	$(BIN)/python -m pip install --quiet bpy==$(BPY_VERSION)
	touch $(BPY_STAMP)

venv-bpy: $(BPY_STAMP)

# dist/riray-<version>.zip: riray_addon/ + core/ staged in a temporary folder (the checkout is
# left as it was), built and validated by Blender's own extension tool (docs/blender.md).
extension: $(BPY_STAMP)
	$(BIN)/python riray_addon/build_extension.py --out dist --validate

demo: $(STAMP)
	$(BIN)/riray demo --out demo_out

# Core must run on numpy 1.26 (what Blender bundles; the bpy wheel pins it in .venv) and on
# current numpy: the core tests run again in a second, bpy-free environment with numpy 2. Both
# environments have the cluster extra (Dask), so the sharded-bake tests run a real LocalCluster.
NP2      := .venv-numpy2
NP2STAMP := $(NP2)/.installed

$(NP2STAMP): pyproject.toml
	$(PYTHON) -m venv $(NP2)
	$(NP2)/bin/python -m pip install --quiet --upgrade pip
	$(NP2)/bin/python -m pip install --quiet -e '.[test,cluster]' 'numpy>=2'
	touch $(NP2STAMP)

# The add-on tests also run on the oldest supported Blender, 4.2 LTS: the bpy 4.2.x wheel in its
# own environment (~350 MB download; no matplotlib, which only the core bench test needs).
# tests/addon/test_settings.py opens a file saved there with 5.0 (RIRAY_OLD_BPY_PYTHON).
BPY42_VERSION ?= 4.2.23
BPY42         := .venv-bpy42
BPY42STAMP    := $(BPY42)/.bpy-$(BPY42_VERSION)

$(BPY42STAMP): pyproject.toml
	$(PYTHON) -m venv $(BPY42)
	$(BPY42)/bin/python -m pip install --quiet --upgrade pip
	$(BPY42)/bin/python -m pip install --quiet -e . pytest bpy==$(BPY42_VERSION)
	touch $(BPY42STAMP)

test: $(STAMP) $(BPY_STAMP) $(NP2STAMP) $(BPY42STAMP)
	RIRAY_OLD_BPY_PYTHON=$(abspath $(BPY42))/bin/python $(BIN)/python -m pytest
	$(NP2)/bin/python -m pytest tests/core -p no:cacheprovider
	$(BPY42)/bin/python -m pytest tests/addon -p no:cacheprovider

clean:
	rm -rf $(VENV) $(NP2) $(BPY42) demo_out build dist *.egg-info
