# Trigger firmware (firmware/avr_trigger): AVR builds for both MCUs and the simavr tests.
# DVS USB bridge firmware (firmware/dvs_usb): the ATmega32U4 target build and its simulator build.
.PHONY: firmware-avr firmware-dvs firmware-strawlab test-firmware

firmware: firmware-avr firmware-dvs firmware-strawlab

firmware-avr:
	@$(MAKE) --no-print-directory -C firmware/avr_trigger ROOT=$(ROOT) OUT=$(BUILD)/firmware

firmware-dvs:
	@$(MAKE) --no-print-directory -C firmware/dvs_usb ROOT=$(ROOT) OUT=$(BUILD)/firmware

# The strawlab triggerbox stand-in (firmware/strawlab_box) that the strawlab driver is tested against.
firmware-strawlab:
	@$(MAKE) --no-print-directory -C firmware/strawlab_box ROOT=$(ROOT) OUT=$(BUILD)/firmware

# Runs the real firmware in simavr (harnesses built by cbuild) and prints the figures: the trigger's,
# and the DVS bridge's sustained event rate, timestamp error and sync events == pulses sent.
test-firmware: cbuild firmware-avr firmware-dvs firmware-strawlab
	@$(PYTEST) -q -s tests/firmware host/tests/trigger

PART_TARGETS += test-firmware firmware-dvs

# CPU cost of the paced simavr harness (the simulated rig's trigger): prints % of a core.
.PHONY: bench-trigger-sim
bench-trigger-sim: cbuild firmware-avr
	@$(PY) firmware/avr_trigger/harness/bench_pacing.py

BENCH_TARGETS += bench-trigger-sim
PART_TARGETS += bench-trigger-sim

# The host's clock model against a crystal +37 ppm off drifting 0.5 ppm/s (paced simavr, ~40 s):
# prints the gain error against the harness's truth, its standard error, the trigger-edge time error.
.PHONY: bench-trigger-clock
bench-trigger-clock: cbuild firmware-avr
	@$(PY) -m flytrack_host.trigger.bench_clock $(if $(BENCH_JSON),--json $(BENCH_JSON))

BENCH_TARGETS += bench-trigger-clock
PART_TARGETS += bench-trigger-clock
