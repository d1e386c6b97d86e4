# Edge feature extractor (edge/feature_extractor): C library + flytrack-edge daemon, host bindings.
.PHONY: test-edge bench-edge

# The extractor is built portable (x86-64-v2 with AVX2/AVX-512BW paths chosen at run time; armv8-a):
# it runs on any camera computer. EDGE_NATIVE=ON builds it for this machine's CPU alone (-march=native).
# Passed on every configure, so that a build directory configured when native was the default follows.
EDGE_NATIVE ?= OFF
CMAKE_FLAGS += -DFLYTRACK_EDGE_NATIVE=$(EDGE_NATIVE)

# C unit tests (plain, ASan+UBSan, V4L2 seam; each vector path, the run-time choice of path, no wide
# instruction outside it), the NumPy reference comparison, the daemon end to end (stdin, Y4M, control,
# Aravis fake camera; bad input against both flytrack-edge and its ASan+UBSan build flytrack-edge-san),
# and no C file calling back into one that calls it (tests/edge/test_c_layering.py).
test-edge: cbuild
	@cd $(BUILD) && ctest --output-on-failure -R '^edge_'
	@$(PYTEST) -q host/tests/features tests/edge

# C extractor vs an OpenCV-Python pipeline on the same frames, one core. BENCH_JSON=PATH writes figures.
# Then the native build (build/edge/native) against the portable one, side by side with their ratio
# (bench/fx_bench_paths.c; only where the portable build has the run-time paths).
FX_BENCH_PATHS = $(BUILD)/edge/feature_extractor/fx_bench_paths
bench-edge: cbuild
	@$(PY) -m flytrack_host.edges.features.bench $(if $(BENCH_JSON),--json $(BENCH_JSON))
	@if [ -x $(FX_BENCH_PATHS) ] && [ -f $(BUILD)/edge/native/libflytrack_features.so ]; then \
	  $(FX_BENCH_PATHS) $(BUILD)/edge/native/libflytrack_features.so \
	    $(BUILD)/edge/feature_extractor/libflytrack_features.so; \
	else echo "bench-edge: no native copy to compare (EDGE_NATIVE=ON, or not x86_64)"; fi

# The extractor's portable vector path as the ARM edge computers build it: cross-compiled for aarch64
# (GCC vector extensions -> NEON) with -Wall -Wextra -Werror, test_scan and test_features run under
# qemu-aarch64 (packages gcc-aarch64-linux-gnu, libc6-dev-arm64-cross, qemu-user). Not in `make test`.
ARM_CC ?= aarch64-linux-gnu-gcc
ARM_OUT = $(BUILD)/edge/arm64
FX_DIR = edge/feature_extractor
ARM_FLAGS = -O3 -ffp-contract=off -fno-math-errno -Wall -Wextra -Werror -I$(FX_DIR)/include -I$(FX_DIR)/src
.PHONY: test-edge-arm
test-edge-arm:
	@FLYTRACK_EXTRA_APT=scripts/apt-packages-arm.txt scripts/setup.sh
	@command -v $(ARM_CC) >/dev/null && command -v qemu-aarch64 >/dev/null \
	  || { echo "test-edge-arm: needs $(ARM_CC) and qemu-aarch64 (scripts/apt-packages-arm.txt)" >&2; exit 2; }
	@mkdir -p $(ARM_OUT)
	@$(ARM_CC) $(ARM_FLAGS) -ffinite-math-only -fno-signed-zeros -c $(FX_DIR)/src/thresholds.c -o $(ARM_OUT)/thresholds.o
	@$(ARM_CC) $(ARM_FLAGS) -c $(FX_DIR)/src/scan.c -o $(ARM_OUT)/scan.o
	@$(ARM_CC) $(ARM_FLAGS) -c $(FX_DIR)/src/features.c -o $(ARM_OUT)/features.o
	@$(ARM_CC) $(ARM_FLAGS) -c $(FX_DIR)/src/regions.c -o $(ARM_OUT)/regions.o
	@$(ARM_CC) $(ARM_FLAGS) -c $(FX_DIR)/src/undistort.c -o $(ARM_OUT)/undistort.o
	@$(ARM_CC) $(ARM_FLAGS) -c $(FX_DIR)/src/background.c -o $(ARM_OUT)/background.o
	@for t in test_scan test_features test_lazy_update; do \
	  $(ARM_CC) $(ARM_FLAGS) -static $(FX_DIR)/tests/$$t.c $(ARM_OUT)/features.o $(ARM_OUT)/scan.o $(ARM_OUT)/regions.o \
	    $(ARM_OUT)/undistort.o $(ARM_OUT)/background.o $(ARM_OUT)/thresholds.o -lm -o $(ARM_OUT)/$$t && qemu-aarch64 $(ARM_OUT)/$$t || exit 1; done

# Two builds of the extractor on the same random frames, every result and the background bit for bit:
# OLD=path/to/libflytrack_features.so (e.g. main's, built in another build directory) against this
# tree's build. Not in `make test` (it needs the other build).
.PHONY: compare-edge
compare-edge: cbuild
	@test -n "$(OLD)" || { echo "compare-edge: give OLD=path/to/libflytrack_features.so" >&2; exit 2; }
	@$(CC) -O2 -Wall -Wextra -Werror -I$(FX_DIR)/include $(FX_DIR)/bench/fx_compare.c -ldl -lm -o $(BUILD)/fx_compare
	@$(BUILD)/fx_compare $(OLD) $(BUILD)/edge/feature_extractor/libflytrack_features.so $(FRAMES)

BENCH_TARGETS += bench-edge
PART_TARGETS += test-edge bench-edge test-edge-arm compare-edge
