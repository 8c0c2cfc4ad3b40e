"""``python -m service serve|worker|users ...``: the service's commands without the ``acinoset`` script."""

import sys

from service.cli import main

if __name__ == "__main__":
    sys.exit(main())
