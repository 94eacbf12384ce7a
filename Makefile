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

# A small fresh test split scored by the shipped model: metrics, figures, an explanation,
# contact sheets of every test setting and an animation, under demo/.
demo: $(STAMP)
	mkdir -p demo
	$(BIN)/xvoe generate --split test --pairs 20 --size 32 --seed 7 --out demo/test.h5 --overwrite
	$(BIN)/xvoe score --model xpl --data demo/test.h5 --out demo/scores/xpl.csv --overwrite
	$(BIN)/xvoe score --model random --data demo/test.h5 --out demo/scores/random.csv --overwrite
	$(BIN)/xvoe metrics demo/scores/xpl.csv demo/scores/random.csv --data demo/test.h5 --out demo/report --overwrite
	$(BIN)/xvoe explain --model xpl --data demo/test.h5 --index 160 --out demo/explanation-blocking-S2.png --overwrite
	for i in 0 40 80 120 160 200 240 280 320 360 400; do \
		$(BIN)/xvoe show demo/test.h5 --index $$i --out demo/pair-$$i.png --overwrite || exit 1; done
	$(BIN)/xvoe show demo/test.h5 --index 0 --out demo/pair-0.gif --overwrite
	@echo "demo: scores in demo/scores/, metrics and figures in demo/report/, an explanation and contact sheets in demo/"

# Two pytest workers of one thread each, a test file per worker: most tests are one-thread work or
# waits on the processes they start, which one process with two torch threads leaves a core idle for.
test: $(STAMP)
	OMP_NUM_THREADS=1 $(BIN)/python -m pytest -n 2 --dist loadfile

clean:
	rm -rf $(VENV) demo
