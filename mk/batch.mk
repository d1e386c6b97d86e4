# Batches on Dask (host/flytrack_host/batch): re-tracking, sweeps and exports over many recordings.
.PHONY: test-batch bench-batch
PART_TARGETS += test-batch bench-batch
BENCH_TARGETS += bench-batch

test-batch: build
	@$(PYTEST) -q host/tests/batch

bench-batch: build
	@$(PY) -m flytrack_host.batch.bench $(if $(BENCH_JSON),--json $(BENCH_JSON))
