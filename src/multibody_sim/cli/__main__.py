"""`python -m multibody_sim.cli ...`: the same command line as the `multibody-sim` console script."""

import sys

from multibody_sim.cli import main

sys.exit(main())
