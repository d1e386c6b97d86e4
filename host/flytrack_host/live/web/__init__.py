"""The live HTTP server: Braid-compatible event stream and the live web page."""
