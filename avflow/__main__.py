"""``python -m avflow ...``: the command line, as ``avflow ...`` (:mod:`avflow.cli`)."""

import sys

from avflow.cli import main

sys.exit(main())
