# make run | make test | make bench — each bootstraps .venv (and Qt's system libraries) when missing.
VENV := .venv
PY := $(VENV)/bin/python
export PYTHONDONTWRITEBYTECODE := 1

.PHONY: bootstrap run test bench simulate lint clean screenshot

bootstrap:
	@bash scripts/bootstrap.sh

run: bootstrap
	$(PY) -m app run

simulate: bootstrap
	$(PY) -m app simulate

test: bootstrap
	QT_QPA_PLATFORM=offscreen $(PY) -m pytest
	$(VENV)/bin/lint-imports

bench: bootstrap
	QT_QPA_PLATFORM=offscreen $(PY) -m bench

clean:
	rm -rf $(VENV) build .pytest_cache
