# Two entry points: `make demo` and `make test`. Both create .venv if missing and install the
# package (editable, with every extra) with the pinned versions of constraints.txt.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
EXTRAS ?= dev,docs,eval,ros,notebooks
# torch's CPU build: a wheel that pip finds locally (its find-links) where there is one, else
# PyTorch's CPU wheel index. (From PyPI, torch==2.13.0 is the CUDA build: several GB.)
TORCH ?= torch==2.13.0
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu

.PHONY: demo test test-slow lint format docs docs-serve bench clean

$(STAMP): setup.cfg pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --no-index --no-deps '$(TORCH)' 2>/dev/null \
	  || $(PY) -m pip install -q --no-deps --index-url $(TORCH_INDEX) '$(TORCH)'
	$(PY) -m pip install -q -c constraints.txt -e '.[$(EXTRAS)]'
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m pyro_slam.cli demo --out out --overwrite

test: $(STAMP)
	$(PY) -m pytest -q

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

# the documentation site (mkdocs; API reference from docstrings, tutorials from notebooks/)
# -> site/; --strict turns every warning into an error
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --site-dir site

docs-serve: $(STAMP)
	$(VENV)/bin/mkdocs serve

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: $(STAMP)
	$(VENV)/bin/ruff check --fix .
	$(VENV)/bin/ruff format .

clean:
	rm -rf $(VENV) out build site *.egg-info
