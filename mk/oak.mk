# OAK edge (host/flytrack_host/edges/oak): the depthai pipeline built from the real library, frames
# through the FrameSource seam (no OAK device here) compared with flytrack-edge's FEATURES.
.PHONY: test-oak
PART_TARGETS += test-oak

test-oak: build
	@$(PYTEST) -q tests/edge/test_edge_oak.py
