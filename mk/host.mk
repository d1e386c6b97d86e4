# Host data path: receiver, synchroniser, recording, export/import, retrack, live output, pipeline.
PART_TARGETS += test-host bench-host
BENCH_TARGETS += bench-host

.PHONY: test-host bench-host

test-host: setup
	@$(PYTEST) -q host/tests/host tests/host

bench-host: setup
	@$(PY) tests/host/bench_pipeline.py --seconds 5 $(if $(BENCH_JSON),--json $(BENCH_JSON))
