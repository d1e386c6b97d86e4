# Live outputs (host/flytrack_host/live/web, host/flytrack_host/outputs): Braid event stream, VR pose stream,
# live page. Tests drive Debian's chromium (apt: chromium, chromium-driver) through selenium.
.PHONY: test-web bench-web
PART_TARGETS += test-web bench-web
BENCH_TARGETS += bench-web

test-web: build
	@$(PYTEST) -q host/tests/web tests/web

# Time the event stream + pose stream add to the tracking thread per frame, 11 cameras x 10 targets,
# 10 Braid clients connected, against writing the events synchronously on the tracking thread.
bench-web: setup
	@$(PY) -m flytrack_host.pipeline.bench_live --seconds 4 $(if $(BENCH_JSON),--json $(BENCH_JSON))
