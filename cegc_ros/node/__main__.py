"""``python -m cegc_ros.node``: the same as the ``register_node`` console script."""

import sys

from cegc_ros.node.main import main

if __name__ == "__main__":
    sys.exit(main())
