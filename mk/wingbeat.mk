# Wing beats of a tethered fly (seed 002 part II): the host's file path (host/flytrack_host/dvs/wingbeat), the
# edge's C tracker (edge/events/algos/wingbeat.c) and the live path (flytrack-edge --wingbeat 1 -> UDP ->
# flytrack wingbeat --live).
.PHONY: test-wingbeat bench-wingbeat
PART_TARGETS += test-wingbeat bench-wingbeat
BENCH_TARGETS += bench-wingbeat

test-wingbeat: cbuild
	@cd $(BUILD) && ctest --output-on-failure -R '^event_wingbeat'
	@$(PYTEST) -q host/tests/wingbeat tests/edge/test_edge_wingbeat.py

# The C tracker side by side with the Python EKF on the same simulated events, and the daemon's CPU time.
# BENCH_WINGBEAT_ARGS='--seconds S --repeats R'; BENCH_JSON=PATH writes figures.
bench-wingbeat: cbuild
	@$(PY) -m flytrack_host.dvs.wingbeat.bench $(BENCH_WINGBEAT_ARGS) $(if $(BENCH_JSON),--json $(BENCH_JSON))
