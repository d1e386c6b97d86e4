"""Live outputs besides HTTP: Braid's message model and the VR pose stream."""
