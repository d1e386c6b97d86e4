import sys

from flytrack_host.faults.suite import main

sys.exit(main())
