"""``python -m convoy.cli …`` is the ``convoy`` command (what the job service spawns for hosts and evaluations)."""

import sys

from convoy.cli.entry import main

sys.exit(main())
