"""The benchmark scripts' entry point: a library error is one line on stderr and exit 2, as in ``mmslam``."""
from __future__ import annotations

import sys
from collections.abc import Callable


def run(main: Callable[[], int], script: str) -> None:
    """``sys.exit(main())``; an :class:`~mmslam.errors.MmslamError` (a missing cache, a bad ``--set``) becomes
    ``"<script>: error: <message>"`` on stderr and exit status 2 (what was printed before it stays)."""
    from mmslam.errors import MmslamError

    try:
        sys.exit(main())
    except MmslamError as e:
        print(f"{script}: error: {e}", file=sys.stderr)
        sys.exit(2)
