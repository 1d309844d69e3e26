"""``python -m station.rigproc``: the rig process (see ``serve.py``); started by the daemon."""

import sys

from station.rigproc.serve import main

sys.exit(main())
