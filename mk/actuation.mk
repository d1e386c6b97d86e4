# Closed loop (host/flytrack_host/actuation): rules on the live 3D state drive the trigger firmware's
# outputs and lab devices. Tests against real peers (simavr, pymodbus, python-can) and the benchmark of
# estimate -> device acknowledgement, engine vs the call made on the tracking thread.
.PHONY: test-actuation bench-actuation
PART_TARGETS += test-actuation bench-actuation
BENCH_TARGETS += bench-actuation

test-actuation: build
	@$(PYTEST) -q host/tests/actuation host/tests/host/test_actuation_pipeline.py tests/e2e/test_closed_loop.py

bench-actuation: build
	@$(PY) -m flytrack_host.actuation.bench $(if $(BENCH_JSON),--json $(BENCH_JSON))
