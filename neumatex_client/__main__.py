"""python -m neumatex_client submit | jobs | job (the same as `neumatex submit | jobs | job`)."""

import sys

from neumatex_client.cli import main

sys.exit(main())
