# The two commands of the README. Each creates .venv when missing and installs into it.
PY := .venv/bin/python
STAMP := .venv/.installed

.PHONY: demo test venv lint model

demo: $(STAMP)
	$(PY) -m damon_ros.cli demo

test: $(STAMP)
	$(PY) -m ruff check damon_ros test
	.venv/bin/lint-imports
	$(PY) -m pytest -q test

lint: $(STAMP)
	$(PY) -m ruff check damon_ros test
	.venv/bin/lint-imports

venv: $(STAMP)

$(STAMP): requirements.txt setup.py
	test -x $(PY) || python3 -m venv .venv
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -r requirements.txt
	$(PY) -m pip install -q --no-deps --no-build-isolation -e .
	touch $(STAMP)

# The shipped model, from fixed seeds (see README "The shipped model"; ~25 min on 2 cores).
DATA ?= data/d1m
N ?= 20000
model: $(STAMP)
	$(PY) -m damon_ros.cli collect --n 1000000 --seed 0 --out $(DATA)
	$(PY) -m damon_ros.cli train --data $(DATA) --out models/default --epochs 12 --seed 0 --threads 1
	$(PY) -m damon_ros.cli build-graph --data $(DATA) --model models/default --n-vertices $(N) --seed 0
