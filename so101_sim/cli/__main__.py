"""`python -m so101_sim.cli` runs the `so101-sim` command."""

import sys

from so101_sim.cli import main

sys.exit(main())
