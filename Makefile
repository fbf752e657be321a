# Two entry points for a fresh machine with Python 3.11:
#   make demo   -- create .venv, install everything from PyPI, run the main job
#   make test   -- create .venv, install everything from PyPI, run the test suite
PYTHON ?= python3.11
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: setup demo test test-all clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[blender,test,cuda-build,cluster]'
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/gf-cli demo --out demo_out

test: $(STAMP)
	GF_REQUIRE_NATIVE=1 $(PY) -m pytest -q -ra

test-all: $(STAMP)
	GF_REQUIRE_NATIVE=1 $(PY) -m pytest -q -ra -m ''

clean:
	rm -rf $(VENV) demo_out $${GF_EXT_DIR:-$$HOME/.cache/gaussfluids}
