# Calibration (host/flytrack_host/calibration): tests and the side-by-side benchmark against aniposelib.
.PHONY: test-calib bench-calib calib-bench-deps
PART_TARGETS += test-calib bench-calib
BENCH_TARGETS += bench-calib

test-calib: setup
	@$(PYTEST) -q host/tests/calibration

# aniposelib goes in with --no-deps (its opencv-contrib-python would replace our cv2); then only the
# packages it imports for bundle adjustment and triangulation. cv2 must still import afterwards.
calib-bench-deps: setup
	@$(PY) -c "import aniposelib.cameras, numba, toml, jax" 2>/dev/null || { \
	  $(VENV)/bin/pip install -q --no-deps aniposelib==0.8.0 && \
	  $(VENV)/bin/pip install -q numba==0.68.1 toml==0.10.2 jax==0.10.2; } \
	  || { echo "bench-calib: could not install aniposelib 0.8.0 and its deps (numba, toml, jax) into .venv;" \
	       "check network/pip access, or install them by hand with pip --no-deps aniposelib==0.8.0." >&2; exit 1; }
	@$(PY) -c "import cv2, aniposelib.cameras; cv2.getBuildInformation()" \
	  || { echo "bench-calib: cv2 or aniposelib does not import after installing the benchmark deps" >&2; exit 1; }

# FlyTrack self-calibration vs aniposelib bundle adjustment on the same synthetic rigs (4, 6, 11 cameras).
# CALIB_INIT=factorization (default), pairwise or both: FlyTrack's initialisation (printed in the "init" column).
CALIB_INIT ?= factorization
bench-calib: calib-bench-deps
	@OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 NUMBA_NUM_THREADS=1 \
	  $(PY) -m flytrack_host.calibration.bench --cameras 4 6 11 --init $(CALIB_INIT) $(if $(BENCH_JSON),--json $(BENCH_JSON))
