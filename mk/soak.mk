# The soak (issue 24, "A whole rig day"): the simulated rig, recording, the live page in Chromium, Braid and
# pose clients and the closed loop on a Modbus server, for SOAK_MINUTES (60) at 11 cameras x 10 animals x
# 100 fps or what this machine sustains (found by short probe runs first), sampled every SOAK_SAMPLE_S (60)
# seconds. Prints the figures; writes build/soak/soak.json and build/soak/soak.png. Not part of `make test`.
.PHONY: soak
PART_TARGETS += soak
SOAK_MINUTES ?= 60
SOAK_SAMPLE_S ?= 60
SOAK_ARGS ?=

soak: build
	@$(PY) -m flytrack_host.sim.soak --minutes $(SOAK_MINUTES) --sample-s $(SOAK_SAMPLE_S) --out $(BUILD)/soak $(SOAK_ARGS)
