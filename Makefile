# Two commands on a fresh machine: `make demo` and `make test`.
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DEMO   := build/demo
SUDO   := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
# Debian's headless EGL + Mesa software rasteriser (llvmpipe); no GPU or display needed.
EGL_PACKAGES := libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri

.PHONY: demo test test-fast setup egl clean

setup: $(STAMP) egl

$(PY):
	python3 -m venv $(VENV)

$(STAMP): pyproject.toml | $(PY)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

# Installs the system libraries only when a headless GL context cannot be made.
egl: $(STAMP)
	@$(PY) -c "from surfelwarp.render.context import gl_context; gl_context()" 2>/dev/null || { \
	  echo "Installing EGL/Mesa system libraries: $(EGL_PACKAGES)"; \
	  $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq $(EGL_PACKAGES) >/dev/null; \
	  $(PY) -c "from surfelwarp.render.context import gl_context; gl_context()"; }

demo: setup
	$(PY) -m surfelwarp synth sheet --out $(DEMO)/sheet --frames 40
	$(PY) -m surfelwarp run $(DEMO)/sheet --out $(DEMO)/run --method surfelwarp
	$(PY) -m surfelwarp eval $(DEMO)/run $(DEMO)/sheet
	$(PY) -m surfelwarp view $(DEMO)/run
	@echo "Demo outputs: $(DEMO)/run (live/*.ply, model.ply, model_mesh.ply, metrics.json, surfels.png, eval.json)"
	@echo "  video of the saved frames: $(DEMO)/run/live.mp4 (pictures in $(DEMO)/run/render/)"
	@echo "  the frames in a browser:   $(DEMO)/run/view.html"

# Test files are shared out to WORKERS processes (pytest-xdist), a file's tests in one of them so
# that its fixtures are made once; one per core: on 2 cores ~1.5x faster than one process.
WORKERS ?= 2

test: setup
	$(PY) -m pytest -q -n $(WORKERS) --dist loadfile

# Everything but the end-to-end runs, fuzzing and clusters (about two minutes).
test-fast: setup
	$(PY) -m pytest -q -n $(WORKERS) --dist loadfile -m "not slow"

clean:
	rm -rf $(VENV) build
