# DVS cameras calibrated with the frame cameras from a blinking LED (issue 13): trigger times from
# event files (edge/events), the LED wand simulation (host/flytrack_host/sim/dvs_wand.py), the LED
# finder (host/flytrack_host/calibration/led_events.py) and `flytrack calibrate dvs-points`.
.PHONY: test-dvs-calib demo-dvs-calib

test-dvs-calib: cbuild
	@cd $(BUILD) && ctest --output-on-failure -R '^events_'
	@$(PYTEST) -q host/tests/calibration/test_dvs_led.py host/tests/events/test_triggers.py

# The whole chain on the simulated wand (20 s, 4 frame cameras + 2 DVS): points against the truth,
# selfcal, DVS reprojection and camera-centre errors. DVS_CALIB_ARGS='--seconds S --dvs N
# --sensor dvs128 --no-frequency-check'; BENCH_JSON=PATH writes the figures.
demo-dvs-calib: cbuild
	@$(PY) -m flytrack_host.sim.dvs_calibration $(DVS_CALIB_ARGS) $(if $(BENCH_JSON),--json $(BENCH_JSON))

PART_TARGETS += test-dvs-calib demo-dvs-calib
