"""Fault injection against the simulated rig's real processes (`suite.py`, `make test-faults`)."""
