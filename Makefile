# Two set-up commands: `make demo` and `make test`. Both build .venv first.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test venv clean

$(STAMP): setup.cfg pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e ".[dev]"
	touch $(STAMP)

venv: $(STAMP)

# A small test split, a contact sheet of every test setting and an animation, under demo/.
demo: $(STAMP)
	mkdir -p demo
	$(BIN)/xvoe generate --split test --pairs 20 --out demo/test.h5 --overwrite
	for i in 0 40 80 120 160 200 240 280 320 360 400; do \
		$(BIN)/xvoe show demo/test.h5 --index $$i --out demo/pair-$$i.png || exit 1; done
	$(BIN)/xvoe show demo/test.h5 --index 0 --out demo/pair-0.gif
	@echo "demo: contact sheets and an animation are in demo/"

test: $(STAMP)
	$(BIN)/python -m pytest

clean:
	rm -rf $(VENV) demo
