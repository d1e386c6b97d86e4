# Tracking (host/flytrack_host/tracking): tests and the tracker benchmark (Stone Soup side by side).
.PHONY: test-tracking bench-tracker
PART_TARGETS += test-tracking bench-tracker
BENCH_TARGETS += bench-tracker

# cbuild: the tests run the tracker on both paths, NumPy and the C kernel.
test-tracking: setup cbuild
	@$(PYTEST) -q host/tests/tracking

# Stone Soup is a benchmark-only comparator (host/requirements-bench.txt); the bench says so if absent.
bench-tracker: setup cbuild
	@$(VENV)/bin/pip install -q -r host/requirements-bench.txt \
	  || echo "bench-tracker: could not install host/requirements-bench.txt (Stone Soup); comparison will be skipped"
	@$(VENV)/bin/flytrack bench tracker $(BENCH_TRACKER_ARGS) $(if $(BENCH_JSON),--json $(BENCH_JSON))
