# Edge feature extractor (edge/feature_extractor): C library + flytrack-edge daemon, host bindings.
.PHONY: test-edge bench-edge

# C unit tests (plain, ASan+UBSan, V4L2 seam), the NumPy reference comparison, the daemon end to end
# (stdin, Y4M, control, Aravis fake camera; bad input against both flytrack-edge and its ASan+UBSan
# build flytrack-edge-san).
test-edge: cbuild
	@cd $(BUILD) && ctest --output-on-failure -R '^edge_'
	@$(PYTEST) -q host/tests/features tests/edge

# C extractor vs an OpenCV-Python pipeline on the same frames, one core. BENCH_JSON=PATH writes figures.
bench-edge: cbuild
	@$(PY) -m flytrack_host.features.bench $(if $(BENCH_JSON),--json $(BENCH_JSON))

BENCH_TARGETS += bench-edge
PART_TARGETS += test-edge bench-edge
