"""`python -m pyvf <command>`: the same as the console script `pyvf <command>` (pyvf/cli/)."""

import sys

from pyvf.cli import main

sys.exit(main())
