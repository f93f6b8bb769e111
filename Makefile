# The two README commands: `make demo` and `make test`. Each builds .venv/ from scratch if needed.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
DEMO_OUT ?= demo-out

.PHONY: install demo test bench clean

$(BIN)/stomach-unfold: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test,slicer,bench,batch,fast]'
	touch $@

install: $(BIN)/stomach-unfold

demo: install
	$(BIN)/stomach-unfold phantom $(DEMO_OUT)/phantom.nrrd --size small
	$(BIN)/stomach-unfold unfold $(DEMO_OUT)/phantom.nrrd --points $(DEMO_OUT)/phantom.mrk.json --output-dir $(DEMO_OUT)/unfold
	@echo "Demo written to $(DEMO_OUT)/unfold: open view.png and report.json"

test: install
	$(BIN)/python -m pytest -q

bench: install
	$(BIN)/stomach-unfold bench --full-size --output-dir docs/benchmark

clean:
	rm -rf $(VENV) $(DEMO_OUT) build *.egg-info
