# Event-camera files (edge/events: libflytrack_events; host/flytrack_host/dvs/events: its bindings).
.PHONY: test-events bench-events

# C unit test + fuzz test (ASan + UBSan), the DVS128 source through its USB seam, the cross-checks
# against dv-processing, aedat and expelliarmus (pinned in host/requirements.txt, installed by
# setup), and flytrack-edge with event sources.
test-events: cbuild
	@cd $(BUILD) && ctest --output-on-failure -R '^(events_|edge_dvs_)'
	@$(PYTEST) -q host/tests/events tests/edge/test_edge_events.py

# Decode speed per format, side by side with expelliarmus (EVT 2/3, DAT) and dv-processing (AEDAT 4)
# on the same files. BENCH_EVENTS_ARGS='--events N --repeats R'; BENCH_JSON=PATH writes figures.
bench-events: cbuild
	@$(PY) -m flytrack_host.dvs.events.bench $(BENCH_EVENTS_ARGS) $(if $(BENCH_JSON),--json $(BENCH_JSON))

PART_TARGETS += test-events bench-events
BENCH_TARGETS += bench-events
