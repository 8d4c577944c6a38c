# The two commands of the README. Each creates .venv when missing and installs into it.
PY := .venv/bin/python
STAMP := .venv/.installed

.PHONY: demo test venv lint

demo: $(STAMP)
	$(PY) -m damon_ros.cli demo

test: $(STAMP)
	$(PY) -m ruff check damon_ros test
	$(PY) -m pytest -q test

lint: $(STAMP)
	$(PY) -m ruff check damon_ros test

venv: $(STAMP)

$(STAMP): requirements.txt setup.py
	test -x $(PY) || python3 -m venv .venv
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -r requirements.txt
	$(PY) -m pip install -q --no-deps --no-build-isolation -e .
	touch $(STAMP)
