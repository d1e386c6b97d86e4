"""Small shared pieces every subsystem may use: the host clock seam (`hostclock`), rate-limited logging
(`ratelog`), finding the C libraries and binaries `make build` made (`native`), placing simulated hardware
processes on their own CPUs (`placement`), starting child processes that end with the process that
started them, whatever signal ends it (`children`), SIGTERM handled as Ctrl-C (`stopping`), and test
helpers (`testing`).

May import: nothing of FlyTrack.
"""
