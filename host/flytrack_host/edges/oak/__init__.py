"""OAK edge: frames of a Luxonis OAK camera (depthai) through the C feature extractor, out as FEATURES.

Python rather than C++: depthai's supported binding on PyPI is the Python wheel (depthai-core in C++
must be built from source with its own dependency tree, not packaged by Debian), and the C extractor
already has a Python binding (`flytrack_host.edges.features`), so the points are computed by the same code
as `flytrack-edge`'s.
"""

# Submodules are imported by name (edge, pipeline, source, cli), not here: `flytrack` imports this
# package's cli for its command table, and depthai should load only when an OAK command runs.
