"""``python -m torch_ao``: the ``torch-ao`` command line (:mod:`torch_ao.cli`)."""
import sys

from .cli import main

sys.exit(main())
