# Each target bootstraps .venv from nothing, so a fresh clone needs only `make demo` / `make test`.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
BROWSER := $(VENV)/.browser

.PHONY: demo test bench drive-bench fuzz lint clean

$(STAMP): pyproject.toml setup.py protocol/_fastpath.c
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev,bench]'
	touch $(STAMP)

# The browser test (tests/integration/test_view_browser.py) drives Debian's Chromium: installed
# here when missing if we are root with apt-get (CI); elsewhere the test skips and says why.
# The stamp is left only once chromium is there, so a machine without it checks again next time.
$(BROWSER):
	@if ! command -v chromium >/dev/null 2>&1; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; \
	  else echo "chromium is missing and cannot be installed here (needs root and apt-get): the browser test will skip"; fi; \
	fi
	@if command -v chromium >/dev/null 2>&1; then mkdir -p $(VENV) && touch $@; fi

demo: $(STAMP)
	$(BIN)/rascal demo

# pytest exits 5 when it collects nothing: say so instead of failing CI for it.
test: $(STAMP) $(BROWSER)
	$(BIN)/python -m pytest -q; status=$$?; \
	if [ $$status -eq 5 ]; then echo "pytest collected no tests"; exit 0; fi; exit $$status

bench: $(STAMP)
	$(BIN)/python -m benchmarks

# The drive leaderboard (benchmarks/README.md): the standard suite, about 70 min (estimated); run it alone.
# DRIVE_ARGS="--suite quick" is a 2-3 min smoke test; also --suite full, --seeds, --km, --plan.
drive-bench: $(STAMP)
	$(BIN)/python -m benchmarks.bench_drive $(DRIVE_ARGS)

# The receive-path fuzz campaign: a million generated datagrams (FUZZ_ARGS="--inputs N --seed S").
fuzz: $(STAMP)
	$(BIN)/python -m tests.protocol.fuzz_campaign $(FUZZ_ARGS)

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

clean:
	rm -rf $(VENV) runs .pytest_cache .ruff_cache
