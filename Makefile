# make run | make test | make bench | make study — each readies .venv (and the system packages) first:
# make test with the test stack, the others with what running needs only (scripts/bootstrap.sh).
VENV := .venv
PY := $(VENV)/bin/python
export PYTHONDONTWRITEBYTECODE := 1

.PHONY: bootstrap bootstrap-run run test lint bench study depth-library simulate constraints clean

# everything, the test stack included: what a developer and CI need
bootstrap:
	@bash scripts/bootstrap.sh test

bootstrap-run:
	@bash scripts/bootstrap.sh run

run: bootstrap-run
	$(PY) -m app run

simulate: bootstrap-run
	$(PY) -m app simulate

# CI's command (.ci/run)
test: bootstrap
	QT_QPA_PLATFORM=offscreen $(PY) -m pytest -n auto
	@$(MAKE) --no-print-directory lint

# the static checks make test ends with: the floors' import contracts, then ruff ([tool.ruff] in pyproject.toml)
lint: bootstrap
	$(VENV)/bin/lint-imports
	$(VENV)/bin/ruff check .

bench: bootstrap-run
	QT_QPA_PLATFORM=offscreen $(PY) -m bench

# The validation study as a benchmark (app/study.py): 12 seeded phantoms and the paper's two, in the ideal world
# and in the realistic one, figures in build/bench/accuracy.json (the realistic world's keys prefixed
# realistic_), the plot beside it, every case's phantom and session in build/study.
study: bootstrap-run
	QT_QPA_PLATFORM=offscreen $(PY) -m app study --phantoms 12 --seed 20261125 --paper --world both --out build/study \
		--json build/bench/accuracy.json --plot build/bench/accuracy.png

# The model-based depth's libraries of finite-element solves (session/depth.py), shipped beside it, the layer's
# sides free and held in a mould: rebuild them after a change to the continuum mechanics (about 6 minutes each
# on one core).
depth-library: bootstrap-run
	$(PY) -m session.depth --sides free --out session/depth_library.npz
	$(PY) -m session.depth --sides mould --out session/depth_library_mould.npz

# constraints.txt pinned afresh: the dependencies of pyproject.toml (every extra) resolved today in a throwaway
# environment; the file's opening comment is kept.
constraints:
	rm -rf build/constraints-venv
	$(or $(PYTHON),python3) -m venv build/constraints-venv
	build/constraints-venv/bin/python -m pip install -q --upgrade pip
	build/constraints-venv/bin/python -m pip install -q -e ".[test,study]"
	{ sed '/^[^#]/,$$d' constraints.txt; build/constraints-venv/bin/python -m pip freeze --exclude-editable; } \
		> build/constraints.txt
	mv build/constraints.txt constraints.txt
	rm -rf build/constraints-venv

clean:
	rm -rf $(VENV) build .pytest_cache
