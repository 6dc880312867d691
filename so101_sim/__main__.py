"""`python -m so101_sim` runs the `so101-sim` command (as `python -m so101_sim.cli` does)."""

import sys

from so101_sim.cli import main

sys.exit(main())
