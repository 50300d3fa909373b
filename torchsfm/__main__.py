"""``python -m torchsfm`` runs the command line."""

import sys

from torchsfm.cli import main

sys.exit(main())
