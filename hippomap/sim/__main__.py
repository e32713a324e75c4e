"""``python -m hippomap.sim WORLD --out FOLDER``: see :mod:`hippomap.sim.cli`."""

import sys

from .cli import main

sys.exit(main())
