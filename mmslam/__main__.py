"""``python -m mmslam``: the same as the ``mmslam`` command."""
import sys

from mmslam.cli import main

sys.exit(main())
