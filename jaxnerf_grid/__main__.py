import sys

from jaxnerf_grid.cli import main

sys.exit(main())
