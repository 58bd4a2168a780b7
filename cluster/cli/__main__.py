"""``python -m cluster.cli ARGS``: the ``ocv2`` command without its console script (tests start it so)."""

import sys

from cluster.cli.main import main

sys.exit(main())
