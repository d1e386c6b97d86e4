import sys

from flytrack_host.sim.faults.suite import main

sys.exit(main())
