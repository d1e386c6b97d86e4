# Fault injection (issue 16): every fault against the simulated rig's real processes, one table.
.PHONY: test-faults
PART_TARGETS += test-faults

test-faults: build
	@$(PY) -m flytrack_host.sim.faults --json $(BUILD)/faults.json
