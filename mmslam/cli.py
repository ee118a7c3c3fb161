"""The ``mmslam`` command line: a thin layer over the library API.

Each subpackage owns its commands in its own ``cli.py`` (``register(app)``); heavy imports
(Sionna, matplotlib) happen inside the commands, so ``mmslam --help`` is fast.
User errors (:class:`~mmslam.errors.MmslamError`) print one line ``error: ...`` and exit non-zero.
"""
from __future__ import annotations

import sys

import typer

from mmslam.errors import MmslamError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Ray-traced mmWave multipath datasets and cooperative MM-PHD-SLAM.")


def _register_all() -> None:
    from mmslam.pipelines import cli as pipelines_cli
    from mmslam.raytrace import cli as raytrace_cli
    from mmslam.scenes import cli as scenes_cli
    from mmslam.slam import cli as slam_cli

    scenes_cli.register(app)
    raytrace_cli.register(app)
    slam_cli.register(app)
    pipelines_cli.register(app)


_register_all()


def _click_modules() -> tuple:
    """The click packages typer may raise from (typer >= 0.17 vendors click as ``typer._click``)."""
    mods = []
    for name in ("typer._click", "click"):
        try:
            mods.append(__import__(name, fromlist=["exceptions"]))
        except ImportError:
            pass
    return tuple(mods)


def main(argv: list[str] | None = None) -> int:
    """Console entry point; returns the exit code (2 for user errors, no traceback)."""
    try:
        app(args=argv, standalone_mode=False)
    except MmslamError as e:
        print(f"error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print("interrupted; finished work is kept, re-run to resume", file=sys.stderr)
        return 130
    except SystemExit as e:  # --help and explicit exits
        return int(e.code or 0)
    except OSError as e:  # an output path that is a file, a missing or read-only directory, a full disk
        where = e.filename if e.filename is not None else "output"
        print(f"error: {where}: {e.strerror or e}; choose a writable path (parent directories must exist "
              "and not be files)", file=sys.stderr)
        return 2
    except Exception as e:
        for mod in _click_modules():  # usage errors: bad option values, missing arguments
            if isinstance(e, mod.exceptions.ClickException):
                e.show()
                return 2
            if isinstance(e, mod.exceptions.Abort):
                return 1
        raise
    return 0


if __name__ == "__main__":
    sys.exit(main())
