# Fish shape tracking (host/flytrack_host/fish, seed 004): tests, the scored demo, the fit benchmark.
.PHONY: test-fish demo-fish bench-fish
PART_TARGETS += test-fish demo-fish bench-fish
BENCH_TARGETS += bench-fish

test-fish: build
	@$(PYTEST) -q host/tests/fish

# The figures and plots of docs/explanation/performance.md and docs/fish/: 4 fish, 200 frames at 250 fps (a few minutes on this machine).
demo-fish: build
	@$(PY) -m flytrack_host.cli fish demo --fish 4 --frames 200 --out docs/fish --json $(BUILD)/fish-demo.json

# Every compared path on one BLAS thread (threadpoolctl in fish/bench.py, as `fish track` tracks; the header
# prints the BLAS libraries' threads); FISH_BENCH_ARGS='--blas-threads 0' leaves the library's default.
bench-fish: build
	@$(PY) -m flytrack_host.fish.bench $(FISH_BENCH_ARGS) $(if $(BENCH_JSON),--json $(BENCH_JSON))
