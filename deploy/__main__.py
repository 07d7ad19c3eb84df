"""`python -m deploy ...` is `vamppi ...` (deploy.launch.cli)."""

import sys

from deploy.launch.cli import main

sys.exit(main())
