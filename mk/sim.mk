# The simulated rig (host/flytrack_host/sim): `make demo` runs it (top Makefile); these are its parts.
.PHONY: test-sim bench-sim demo-stress
PART_TARGETS += test-sim bench-sim demo-stress
BENCH_TARGETS += bench-sim

test-sim: build
	@$(PYTEST) -q host/tests/sim tests/e2e

bench-sim: setup
	@$(PY) -m flytrack_host.sim.bench $(if $(BENCH_JSON),--json $(BENCH_JSON))

# The stress run of issue 7: 11 cameras, 10 animals, 200 fps on this machine.
demo-stress: build
	@$(PY) -m flytrack_host.cli demo --cameras 11 --animals 10 --fps 200 --seconds 10 \
	  --out $(BUILD)/demo-stress --json $(BUILD)/demo-stress/summary.json
