# Event-camera files (edge/events: libflytrack_events; host/flytrack_host/events: its bindings).
.PHONY: test-events

# C unit test + fuzz test (ASan + UBSan), then the cross-checks against dv-processing, aedat and
# expelliarmus (pinned in host/requirements.txt, installed by setup).
test-events: cbuild
	@cd $(BUILD) && ctest --output-on-failure -R '^events_'
	@$(PYTEST) -q host/tests/events

PART_TARGETS += test-events
