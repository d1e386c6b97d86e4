# Trigger firmware (firmware/avr_trigger): AVR builds for both MCUs and the simavr tests.
.PHONY: firmware-avr test-firmware

firmware: firmware-avr

firmware-avr:
	@$(MAKE) --no-print-directory -C firmware/avr_trigger ROOT=$(ROOT) OUT=$(BUILD)/firmware

# Runs the real firmware in simavr (harness built by cbuild) and prints the figures.
test-firmware: cbuild firmware-avr
	@$(PYTEST) -q -s tests/firmware host/tests/trigger

PART_TARGETS += test-firmware

# CPU cost of the paced simavr harness (the simulated rig's trigger): prints % of a core.
.PHONY: bench-trigger-sim
bench-trigger-sim: cbuild firmware-avr
	@$(PY) firmware/avr_trigger/harness/bench_pacing.py

BENCH_TARGETS += bench-trigger-sim
PART_TARGETS += bench-trigger-sim
